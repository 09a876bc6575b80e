"""ROS ``camera_info`` YAML: the camera calibration file, written and read without a YAML library.

The format (``camera_calibration_parsers``, what ROS and OpenCV users already have)::

    image_width: 800
    image_height: 600
    camera_name: vlp_camera
    camera_matrix:
      rows: 3
      cols: 3
      data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]
    distortion_model: plumb_bob
    distortion_coefficients:
      rows: 1
      cols: 5
      data: [k1, k2, p1, p2, k3]
    rectification_matrix:
      rows: 3
      cols: 3
      data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
    projection_matrix:
      rows: 3
      cols: 4
      data: [fx', 0, cx', 0, 0, fy', cy', 0, 0, 0, 1, 0]

The reader takes the subset of YAML such files use: ``#`` comments, ``key: scalar``, nested mappings by
indentation, flow sequences (``[a, b]``, also across lines) and block sequences (``- a``). It is enough for
camera_info files written by ROS (camera_calibration_parsers, PyYAML) and by this module, and names the key
wrong when a file is not one.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from drivers.errors import ConfigError

__all__ = ["CameraInfo", "format_camera_info", "parse_camera_info", "parse_simple_yaml"]

FloatArray = npt.NDArray[np.float64]

_DISTORTION_LENGTHS = {"plumb_bob": (5,), "rational_polynomial": (8,), "equidistant": (4,)}


@dataclass(frozen=True, slots=True)
class CameraInfo:
    """A calibrated camera, as camera_info holds it (row-major matrices)."""

    width: int
    height: int
    camera_matrix: tuple[float, ...]
    distortion: tuple[float, ...]
    distortion_model: str = "plumb_bob"
    rectification: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    projection: tuple[float, ...] = ()
    camera_name: str = "camera"

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if len(self.camera_matrix) != 9 or len(self.rectification) != 9:
            raise ValueError("camera_matrix and rectification_matrix hold 9 numbers")
        if self.projection and len(self.projection) != 12:
            raise ValueError("projection_matrix holds 12 numbers")
        if not self.projection:
            k = self.camera_matrix
            object.__setattr__(
                self, "projection", (k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0)
            )

    @classmethod
    def from_matrices(
        cls,
        width: int,
        height: int,
        k: FloatArray,
        distortion: FloatArray,
        projection: FloatArray | None = None,
        camera_name: str = "camera",
    ) -> CameraInfo:
        p = () if projection is None else tuple(float(v) for v in np.asarray(projection).ravel())
        return cls(
            int(width),
            int(height),
            tuple(float(v) for v in np.asarray(k).ravel()),
            tuple(float(v) for v in np.asarray(distortion).ravel()),
            projection=p,
            camera_name=camera_name,
        )

    @property
    def fx(self) -> float:
        return self.camera_matrix[0]

    @property
    def fy(self) -> float:
        return self.camera_matrix[4]

    @property
    def cx(self) -> float:
        return self.camera_matrix[2]

    @property
    def cy(self) -> float:
        return self.camera_matrix[5]

    def k(self) -> FloatArray:
        return np.array(self.camera_matrix, dtype=np.float64).reshape(3, 3)

    def d(self) -> FloatArray:
        return np.array(self.distortion, dtype=np.float64)


def _number(value: float) -> str:
    return repr(float(value))


def _matrix(name: str, rows: int, cols: int, data: tuple[float, ...]) -> list[str]:
    return [
        f"{name}:",
        f"  rows: {rows}",
        f"  cols: {cols}",
        "  data: [" + ", ".join(_number(v) for v in data) + "]",
    ]


def format_camera_info(info: CameraInfo, comment: str = "") -> str:
    """camera_info YAML text; ``comment`` lines go on top as ``#`` comments."""
    lines = [f"# {line}" if line else "#" for line in comment.splitlines()]
    name = info.camera_name if re.fullmatch(r"[A-Za-z0-9_./-]+", info.camera_name) else "camera"
    lines += [f"image_width: {info.width}", f"image_height: {info.height}", f"camera_name: {name}"]
    lines += _matrix("camera_matrix", 3, 3, info.camera_matrix)
    lines.append(f"distortion_model: {info.distortion_model}")
    lines += _matrix("distortion_coefficients", 1, len(info.distortion), info.distortion)
    lines += _matrix("rectification_matrix", 3, 3, info.rectification)
    lines += _matrix("projection_matrix", 3, 4, info.projection)
    return "\n".join(lines) + "\n"


# -- reading ---------------------------------------------------------------------------------------------
def _strip_comment(line: str) -> str:
    quote: str | None = None
    for i, ch in enumerate(line):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line.rstrip()


def _scalar(text: str) -> Any:
    text = text.strip()
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    if text in ("", "~", "null", "Null", "NULL"):
        return None
    if text in ("true", "True", "TRUE"):
        return True
    if text in ("false", "False", "FALSE"):
        return False
    if re.fullmatch(r"[-+]?\d+", text):
        return int(text)
    lowered = text.lower()
    if lowered in (".nan", "nan"):
        return math.nan
    if lowered in (".inf", "+.inf", "inf"):
        return math.inf
    if lowered in ("-.inf", "-inf"):
        return -math.inf
    try:
        return float(text)
    except ValueError:
        return text


def _flow_sequence(text: str, line_no: int) -> list[Any]:
    inner = text.strip()
    if not (inner.startswith("[") and inner.endswith("]")):
        raise ValueError(f"line {line_no}: unterminated [ ... ] sequence")
    body = inner[1:-1].strip()
    if not body:
        return []
    return [_scalar(item) for item in body.split(",")]


def parse_simple_yaml(text: str) -> dict[str, Any]:
    """The subset of YAML camera_info files use, as nested dicts and lists. Raises ValueError with the line
    number on anything else."""
    raw = text.splitlines()
    lines: list[tuple[int, int, str]] = []  # (line number, indent, content)
    i = 0
    while i < len(raw):
        content = _strip_comment(raw[i])
        number = i + 1
        i += 1
        if not content.strip() or content.strip() in ("---", "...") or content.lstrip().startswith("%"):
            continue
        if "\t" in content[: len(content) - len(content.lstrip())]:
            raise ValueError(f"line {number}: tabs are not allowed for indentation")
        # A flow sequence may continue over several lines: join until its bracket closes.
        while content.count("[") > content.count("]") and i < len(raw):
            content += " " + _strip_comment(raw[i]).strip()
            i += 1
        indent = len(content) - len(content.lstrip())
        lines.append((number, indent, content.strip()))

    def block(start: int, indent: int) -> tuple[Any, int]:
        if (start < len(lines) and lines[start][2].startswith("- ")) or (
            start < len(lines) and lines[start][2] == "-"
        ):
            items: list[Any] = []
            pos = start
            while pos < len(lines) and lines[pos][1] == indent and lines[pos][2].startswith("-"):
                number, _, content = lines[pos]
                rest = content[1:].strip()
                if ":" in rest and not rest.startswith("["):
                    raise ValueError(f"line {number}: mappings inside sequences are not supported")
                items.append(_flow_sequence(rest, number) if rest.startswith("[") else _scalar(rest))
                pos += 1
            return items, pos
        mapping: dict[str, Any] = {}
        pos = start
        while pos < len(lines) and lines[pos][1] == indent:
            number, _, content = lines[pos]
            match = re.fullmatch(r"([^:\s][^:]*?)\s*:(?:\s+(.*))?", content)
            if not match:
                raise ValueError(f"line {number}: expected 'key: value', got {content!r}")
            key, value = match.group(1).strip(), match.group(2)
            if key in mapping:
                raise ValueError(f"line {number}: key {key!r} given twice")
            pos += 1
            if value is None or value.strip() == "":
                if pos < len(lines) and (
                    lines[pos][1] > indent or (lines[pos][1] == indent and lines[pos][2].startswith("-"))
                ):
                    mapping[key], pos = block(pos, lines[pos][1])
                else:
                    mapping[key] = None
            elif value.strip().startswith("["):
                mapping[key] = _flow_sequence(value, number)
            elif value.strip().startswith("{"):
                raise ValueError(f"line {number}: flow mappings are not supported")
            else:
                mapping[key] = _scalar(value)
        if pos < len(lines) and lines[pos][1] > indent:
            raise ValueError(f"line {lines[pos][0]}: unexpected indentation")
        return mapping, pos

    if not lines:
        return {}
    result, pos = block(0, lines[0][1])
    if pos != len(lines):
        raise ValueError(f"line {lines[pos][0]}: unexpected indentation")
    if not isinstance(result, dict):
        raise ValueError("the top level is a sequence, not a mapping")
    return result


def parse_camera_info(text: str, source: str | None = None) -> CameraInfo:
    """A camera_info from YAML text. Raises ConfigError naming the key on anything missing or wrong."""
    try:
        data = parse_simple_yaml(text)
    except ValueError as exc:
        raise ConfigError("", f"not a camera_info YAML file: {exc}", source) from exc

    def integer(key: str) -> int:
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ConfigError(key, f"must be a positive integer, got {value!r}", source)
        return value

    def matrix(
        key: str, rows: int | None, cols: int | None, required: bool = True
    ) -> tuple[float, ...] | None:
        node = data.get(key)
        if node is None and not required:
            return None
        if not isinstance(node, dict):
            raise ConfigError(key, "missing (a mapping with rows, cols and data)", source)
        values = node.get("data")
        if not isinstance(values, list):
            raise ConfigError(f"{key}.data", "missing (a list of numbers)", source)
        numbers: list[float] = []
        for n, v in enumerate(values):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
                raise ConfigError(f"{key}.data[{n}]", f"must be a finite number, got {v!r}", source)
            numbers.append(float(v))
        got_rows, got_cols = node.get("rows"), node.get("cols")
        if rows is not None and got_rows != rows:
            raise ConfigError(f"{key}.rows", f"must be {rows}, got {got_rows!r}", source)
        if cols is not None and got_cols != cols:
            raise ConfigError(f"{key}.cols", f"must be {cols}, got {got_cols!r}", source)
        if (
            not isinstance(got_rows, int)
            or not isinstance(got_cols, int)
            or got_rows * got_cols != len(numbers)
        ):
            raise ConfigError(
                f"{key}.data", f"holds {len(numbers)} numbers, rows x cols is {got_rows} x {got_cols}", source
            )
        return tuple(numbers)

    width, height = integer("image_width"), integer("image_height")
    k = matrix("camera_matrix", 3, 3)
    assert k is not None
    if not (k[0] > 0 and k[4] > 0) or k[6:] != (0.0, 0.0, 1.0):
        raise ConfigError(
            "camera_matrix", f"is not a camera matrix (fx, fy > 0, last row 0 0 1): {k}", source
        )
    model = data.get("distortion_model", "plumb_bob")
    if model not in _DISTORTION_LENGTHS:
        raise ConfigError(
            "distortion_model", f"must be one of {sorted(_DISTORTION_LENGTHS)}, got {model!r}", source
        )
    dist = matrix("distortion_coefficients", 1, None, required=False) or ()
    if dist and len(dist) not in _DISTORTION_LENGTHS[model] and not (model == "plumb_bob" and len(dist) == 4):
        raise ConfigError(
            "distortion_coefficients",
            f"{model} takes {_DISTORTION_LENGTHS[model][0]} numbers, got {len(dist)}",
            source,
        )
    rect = matrix("rectification_matrix", 3, 3, required=False) or (
        1.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        0.0,
        0.0,
        1.0,
    )
    proj = matrix("projection_matrix", 3, 4, required=False) or ()
    name = data.get("camera_name", "camera")
    return CameraInfo(
        width,
        height,
        k,
        dist or (0.0,) * _DISTORTION_LENGTHS[model][0],
        str(model),
        rect,
        proj,
        str(name) if name is not None else "camera",
    )
