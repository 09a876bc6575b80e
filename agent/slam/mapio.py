"""Occupancy maps on disk as ROS ``map_server`` files: an 8-bit PGM image and a YAML description.

The YAML is the map_server subset (``image``, ``resolution``, ``origin: [x, y, yaw]``, ``negate``,
``occupied_thresh``, ``free_thresh``, optional ``mode: trinary``), written and read without a YAML
library. Pixel values follow map_saver: 0 occupied, 254 free, 205 unknown; loading applies map_server's
rule p = (255 - v) / 255 (or v / 255 with ``negate: 1``).

Writes are atomic per file (a temporary file in the same folder, fsync, rename) and keep the previous
version: saving ``map.yaml`` over an existing map first copies the old pair to ``map.prev.pgm`` and
``map.prev.yaml`` (the latter pointing at the former), so a bad run never destroys the last good map.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from agent.slam.render import OccupancyImage
from drivers.errors import ConfigError

log = logging.getLogger(__name__)

Uint8Array = npt.NDArray[np.uint8]


@dataclass(frozen=True)
class MapFiles:
    yaml: Path
    image: Path
    previous_yaml: Path | None


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def encode_pgm(pixels: Uint8Array, comment: str = "") -> bytes:
    """Binary PGM (P5), 8 bits per pixel."""
    if pixels.dtype != np.uint8 or pixels.ndim != 2:
        raise ValueError(f"PGM needs a 2-D uint8 image, got {pixels.dtype} {pixels.shape}")
    h, w = pixels.shape
    note = "".join(f"# {line}\n" for line in comment.splitlines())
    return f"P5\n{note}{w} {h}\n255\n".encode("ascii") + np.ascontiguousarray(pixels).tobytes()


def decode_pgm(data: bytes, source: str = "<pgm>") -> Uint8Array:
    """Read a P5 (binary) or P2 (ASCII) PGM with maxval <= 255."""
    tokens: list[bytes] = []
    pos = 0
    # Header: magic, width, height, maxval, separated by whitespace, '#' comments to end of line.
    while len(tokens) < 4:
        match = re.compile(rb"\s*(#[^\n]*\n\s*)*(\S+)").match(data, pos)
        if match is None:
            raise ConfigError("image", "truncated PGM header", source)
        tokens.append(match.group(2))
        pos = match.end()
    magic = tokens[0]
    if magic not in (b"P5", b"P2"):
        raise ConfigError("image", f"not a PGM (magic {magic[:8]!r}); map images must be P5 or P2", source)
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError as exc:
        raise ConfigError("image", "PGM header sizes are not numbers", source) from exc
    if width <= 0 or height <= 0 or not 0 < maxval <= 255:
        raise ConfigError("image", f"unsupported PGM {width}x{height} maxval {maxval} (need 8-bit)", source)
    if magic == b"P5":
        body = data[pos + 1 : pos + 1 + width * height]  # exactly one whitespace byte after maxval
        if len(body) != width * height:
            raise ConfigError("image", f"PGM data truncated: {len(body)} of {width * height} bytes", source)
        pixels = np.frombuffer(body, dtype=np.uint8).reshape(height, width)
    else:
        try:
            values = np.array(data[pos:].split(), dtype=np.int64)
        except ValueError as exc:
            raise ConfigError("image", "ASCII PGM data is not numbers", source) from exc
        if values.size != width * height:
            raise ConfigError("image", f"PGM data has {values.size} of {width * height} values", source)
        pixels = values.reshape(height, width).astype(np.uint8)
    if maxval != 255:
        pixels = np.round(pixels.astype(np.float64) * (255.0 / maxval)).astype(np.uint8)
    return pixels.copy()


def _yaml_text(image_name: str, image: OccupancyImage) -> str:
    x, y, yaw = image.origin
    return (
        f"image: {image_name}\n"
        f"mode: trinary\n"
        f"resolution: {image.resolution_m:.6f}\n"
        f"origin: [{x:.6f}, {y:.6f}, {yaw:.6f}]\n"
        f"negate: 0\n"
        f"occupied_thresh: {image.occupied_thresh}\n"
        f"free_thresh: {image.free_thresh}\n"
    )


def save_map(image: OccupancyImage, yaml_path: str | Path, comment: str = "") -> MapFiles:
    """Write ``<stem>.pgm`` and ``<stem>.yaml``; an existing pair becomes ``<stem>.prev.*`` first."""
    yaml_file = Path(yaml_path)
    if yaml_file.suffix != ".yaml":
        raise ConfigError("map", f"the map description must end in .yaml: {yaml_file}")
    stem = yaml_file.with_suffix("")
    pgm_file = stem.with_suffix(".pgm")
    previous: Path | None = None
    try:
        if yaml_file.exists() and pgm_file.exists():
            prev_pgm = stem.parent / f"{stem.name}.prev.pgm"
            previous = stem.parent / f"{stem.name}.prev.yaml"
            write_atomic(prev_pgm, pgm_file.read_bytes())
            old = load_map(yaml_file)
            write_atomic(previous, _yaml_text(prev_pgm.name, old).encode("ascii"))
        write_atomic(pgm_file, encode_pgm(image.pixels, comment))
        write_atomic(yaml_file, _yaml_text(pgm_file.name, image).encode("ascii"))
    except OSError as exc:
        raise ConfigError("map", f"cannot write the map: {exc.strerror or exc}", str(yaml_file)) from exc
    log.info("map written to %s (%dx%d cells)", yaml_file, image.pixels.shape[1], image.pixels.shape[0])
    return MapFiles(yaml_file, pgm_file, previous)


def _parse_yaml(text: str, source: str) -> dict[str, str]:
    fields: dict[str, str] = {}
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        key, sep, value = line.partition(":")
        if not sep or not key.strip() or key != key.lstrip():
            raise ConfigError(f"line {number}", f"not a 'key: value' line: {raw!r}", source)
        fields[key.strip()] = value.strip().strip("'\"")
    return fields


def _number(fields: dict[str, str], key: str, source: str, default: float | None = None) -> float:
    if key not in fields:
        if default is None:
            raise ConfigError(key, "missing", source)
        return default
    try:
        value = float(fields[key])
    except ValueError as exc:
        raise ConfigError(key, f"not a number: {fields[key]!r}", source) from exc
    if not math.isfinite(value):
        raise ConfigError(key, f"not finite: {fields[key]!r}", source)
    return value


def load_map(yaml_path: str | Path) -> OccupancyImage:
    """Read a map_server YAML and its image. Errors name the file and the key."""
    yaml_file = Path(yaml_path)
    source = str(yaml_file)
    try:
        text = yaml_file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError("map", f"cannot read the map description: {exc}", source) from exc
    fields = _parse_yaml(text, source)
    if "image" not in fields:
        raise ConfigError("image", "missing", source)
    resolution = _number(fields, "resolution", source)
    if resolution <= 0.0:
        raise ConfigError("resolution", f"must be positive, got {resolution}", source)
    origin_text = fields.get("origin", "")
    match = re.fullmatch(r"\[\s*([^,\]]+),\s*([^,\]]+),\s*([^,\]]+)\s*\]", origin_text)
    if match is None:
        raise ConfigError("origin", f"must be [x, y, yaw], got {origin_text!r}", source)
    try:
        origin = (float(match.group(1)), float(match.group(2)), float(match.group(3)))
    except ValueError as exc:
        raise ConfigError("origin", f"not numbers: {origin_text!r}", source) from exc
    negate = _number(fields, "negate", source, 0.0)
    occupied = _number(fields, "occupied_thresh", source, 0.65)
    free = _number(fields, "free_thresh", source, 0.196)
    if not 0.0 <= free < occupied <= 1.0:
        raise ConfigError(
            "free_thresh", f"need 0 <= free_thresh < occupied_thresh <= 1, got {free}, {occupied}", source
        )
    mode = fields.get("mode", "trinary")
    if mode != "trinary":
        raise ConfigError("mode", f"only trinary maps are supported, got {mode!r}", source)
    image_file = Path(fields["image"])
    if not image_file.is_absolute():
        image_file = yaml_file.parent / image_file
    try:
        data = image_file.read_bytes()
    except OSError as exc:
        raise ConfigError("image", f"cannot read {image_file}: {exc.strerror or exc}", source) from exc
    pixels = decode_pgm(data, str(image_file))
    if negate:
        pixels = (255 - pixels).astype(np.uint8)
    return OccupancyImage(pixels, resolution, origin, occupied, free)


def write_png(path: str | Path, picture: Uint8Array) -> Path:
    """Encode an image (grey or BGR) as PNG and write it atomically."""
    target = Path(path)
    ok, encoded = cv2.imencode(".png", picture)
    if not ok:
        raise ConfigError("png", "the image could not be encoded", str(target))
    try:
        write_atomic(target, encoded.tobytes())
    except OSError as exc:
        raise ConfigError("png", f"cannot write: {exc.strerror or exc}", str(target)) from exc
    return target
