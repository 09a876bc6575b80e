"""Occupancy maps on disk as ROS ``map_server`` files: an 8-bit PGM image and a YAML description.

The YAML is the map_server subset (``image``, ``resolution``, ``origin: [x, y, yaw]``, ``negate``,
``occupied_thresh``, ``free_thresh``, optional ``mode: trinary``), written and read without a YAML
library. Pixel values follow map_saver: 0 occupied, 254 free, 205 unknown; loading applies map_server's
rule p = (255 - v) / 255 (or v / 255 with ``negate: 1``).

A map is the pair that was written together or nothing. The YAML names its image, so each save writes its
image under a new name (``map.<UTC stamp>.pgm``) and then renames the YAML over ``map.yaml``: that one
rename is the commit, and a kill at any point leaves either the old pair or the new one (in a fresh
folder, no ``map.yaml`` at all). The pair being replaced stays loadable as ``map.prev.yaml`` (naming its
own image), and only images that neither YAML names are removed, after the commit. Every file goes
through a temporary file in the same folder, fsync and rename, with the permissions ``open()`` would give
(0666 less the umask). One writer per map folder: ``tidy_map_folder`` removes what a killed writer left.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import tempfile
from dataclasses import dataclass
from datetime import UTC, datetime
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


def new_file_mode() -> int:
    """What ``open()`` gives a new file: 0666 less the process's umask (``mkstemp`` alone gives 0600)."""
    try:
        # Read it where Linux shows it: setting the umask to read it back would briefly change it for
        # every thread of the process.
        for line in Path("/proc/self/status").read_text(encoding="ascii").splitlines():
            if line.startswith("Umask:"):
                return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


def fsync_dir(folder: Path) -> None:
    # A rename is durable only once the folder's entry is on disk; not every filesystem allows this.
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def write_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        os.fchmod(fd, new_file_mode())
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


# The stamp in an image's name: UTC to the microsecond, and a counter if two saves share one.
_STAMP = r"\d{8}T\d{12}Z(?:-\d+)?"


def _stem(yaml_file: Path) -> str:
    if yaml_file.suffix != ".yaml":
        raise ConfigError("map", f"the map description must end in .yaml: {yaml_file}")
    return yaml_file.stem


def _previous_yaml(yaml_file: Path) -> Path:
    return yaml_file.with_name(f"{_stem(yaml_file)}.prev.yaml")


def _image_version(yaml_file: Path) -> Path:
    """A name no file in the folder has yet: ``<stem>.<UTC stamp>.pgm``."""
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
    candidate = yaml_file.with_name(f"{_stem(yaml_file)}.{stamp}.pgm")
    counter = 0
    while candidate.exists():
        counter += 1
        candidate = yaml_file.with_name(f"{_stem(yaml_file)}.{stamp}-{counter}.pgm")
    return candidate


def _named_image(yaml_file: Path) -> Path | None:
    """The image a map description names, or None when there is no readable description."""
    try:
        fields = _parse_yaml(yaml_file.read_text(encoding="utf-8"), str(yaml_file))
    except (OSError, UnicodeDecodeError, ConfigError):
        return None
    if "image" not in fields:
        return None
    image = Path(fields["image"])
    return image if image.is_absolute() else yaml_file.parent / image


def _loadable_text(yaml_file: Path) -> bytes | None:
    """The description's bytes when it and its image load, else None (nothing worth keeping)."""
    try:
        text = yaml_file.read_bytes()
        load_map(yaml_file)
    except (OSError, ConfigError):
        return None
    return text


def _remove_unnamed_images(yaml_file: Path, *, legacy: bool) -> list[Path]:
    """Delete this map's images that neither ``<stem>.yaml`` nor ``<stem>.prev.yaml`` names: the
    versioned ones always (a kill before the commit leaves one), the fixed names of older releases
    (``<stem>.pgm``, ``<stem>.prev.pgm``) only when ``legacy``, i.e. right after a commit replaced them."""
    stem = _stem(yaml_file)
    named = {p.resolve() for p in (_named_image(yaml_file), _named_image(_previous_yaml(yaml_file))) if p}
    pattern = re.compile(rf"{re.escape(stem)}\.{_STAMP}\.pgm")
    removed: list[Path] = []
    for entry in yaml_file.parent.iterdir():
        ours = pattern.fullmatch(entry.name) is not None
        if legacy and entry.name in (f"{stem}.pgm", f"{stem}.prev.pgm"):
            ours = True
        if ours and entry.is_file() and entry.resolve() not in named:
            with contextlib.suppress(FileNotFoundError):
                entry.unlink()
                removed.append(entry)
    return removed


def tidy_map_folder(yaml_path: str | Path) -> list[Path]:
    """Remove what a writer killed mid-save left beside ``yaml_path``: its temporary files and any
    versioned image no description names. Call it when the single writer of that folder starts.
    Returns the paths removed (an absent folder is fine: nothing to tidy)."""
    yaml_file = Path(yaml_path)
    stem = _stem(yaml_file)
    if not yaml_file.parent.is_dir():
        return []
    temporary = re.compile(
        rf"\.{re.escape(stem)}\.(?:prev\.)?(?:{_STAMP}\.)?(?:yaml|pgm|png)\.[A-Za-z0-9_]+\.tmp"
    )
    removed: list[Path] = []
    try:
        for entry in yaml_file.parent.iterdir():
            if temporary.fullmatch(entry.name) and entry.is_file():
                with contextlib.suppress(FileNotFoundError):
                    entry.unlink()
                    removed.append(entry)
        removed += _remove_unnamed_images(yaml_file, legacy=False)
    except OSError as exc:
        # Left-overs cost disk space, not correctness: the start goes on, a save may still fail later.
        log.warning("cannot tidy the map folder %s: %s", yaml_file.parent, exc)
    for path in removed:
        log.info("removed %s, left by an interrupted map save", path)
    return removed


def save_map(image: OccupancyImage, yaml_path: str | Path, comment: str = "") -> MapFiles:
    """Write a new image ``<stem>.<stamp>.pgm`` and then ``<stem>.yaml`` naming it; a pair that loads
    is kept as ``<stem>.prev.yaml`` (naming its own image). See the module's docstring for why."""
    yaml_file = Path(yaml_path)
    _stem(yaml_file)
    previous: Path | None = None
    try:
        yaml_file.parent.mkdir(parents=True, exist_ok=True)
        # Whatever an earlier save killed half-way left (for writers with no start of their own to do it).
        tidy_map_folder(yaml_file)
        replaced = _loadable_text(yaml_file)
        pgm_file = _image_version(yaml_file)
        # 1. The image, under a name nothing refers to yet: a kill here leaves the old pair as it was.
        write_atomic(pgm_file, encode_pgm(image.pixels, comment))
        # 2. The pair about to be replaced becomes the previous version (its YAML names its own image).
        if replaced is not None:
            previous = _previous_yaml(yaml_file)
            write_atomic(previous, replaced)
        # 3. The commit: one rename puts the new description, naming the new image, in place.
        write_atomic(yaml_file, _yaml_text(pgm_file.name, image).encode("ascii"))
        fsync_dir(yaml_file.parent)
        # 4. Images neither description names any more (the previous-but-one, older releases' names).
        _remove_unnamed_images(yaml_file, legacy=True)
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


TOPOLOGY_SUFFIX = ".topology.geojson"


def topology_path(yaml_path: str | Path) -> Path:
    """Where the topological map of the map ``<stem>.yaml`` lives: ``<stem>.topology.geojson`` beside it
    (format: docs/exploration.md, "The topological map file")."""
    path = Path(yaml_path)
    return path.with_name(path.stem + TOPOLOGY_SUFFIX)


def save_topology(data: dict[str, object], path: str | Path) -> Path:
    """Write the topological map (``agent.exploration.topology.to_geojson``'s dict) as GeoJSON, atomically
    (a temporary file, fsync, rename: a kill leaves the old file or the new one)."""
    target = Path(path)
    try:
        text = json.dumps(data, indent=1, sort_keys=False, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ConfigError("topology", f"not JSON: {exc}", str(target)) from exc
    try:
        write_atomic(target, (text + "\n").encode("utf-8"))
        fsync_dir(target.parent)
    except OSError as exc:
        raise ConfigError("topology", f"cannot write: {exc.strerror or exc}", str(target)) from exc
    log.info("topological map written to %s", target)
    return target


def load_topology(path: str | Path) -> dict[str, object]:
    """Read a topological map file back as its JSON object (``agent.exploration.topology.from_geojson``
    makes the HTM of it)."""
    source = Path(path)
    try:
        data = json.loads(source.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError("topology", f"cannot read: {exc.strerror or exc}", str(source)) from exc
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError("topology", f"not JSON: {exc}", str(source)) from exc
    if not isinstance(data, dict):
        raise ConfigError("topology", "not a JSON object", str(source))
    return data


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
