"""OTB-style tracking sequences (``img/*.jpg`` + ``groundtruth_rect*.txt``) and OTB's two scores.

Format, as the Object Tracking Benchmark ships it (Wu, Lim, Yang, TPAMI 2015; ``../shared/data/person/
PROVENANCE.md``):

* ``img/0001.jpg ... NNNN.jpg``: the frames, in name order.
* ``groundtruth_rect.txt``: one box per line, line i for frame i: ``x y w h``, the top-left corner and size
  in pixels, in MATLAB's 1-based pixel coordinates. The separator is a comma, a TAB or spaces depending on
  the sequence; lines end in LF or CRLF; the last line may lack its newline. Blank lines are skipped.
* A sequence with several targets has one file per target, ``groundtruth_rect.1.txt``,
  ``groundtruth_rect.2.txt`` (Jogging) and no plain ``groundtruth_rect.txt``.

Boxes are returned 0-based (x - 1, y - 1, w, h), the convention of numpy and OpenCV images and of the
tracker; the scores compare boxes in one convention, so the shift does not change them.

Scores (OTB's one-pass evaluation): the *precision at 20 px* is the fraction of frames whose box centre lies
within 20 px (Euclidean) of the ground truth's; the *success AUC* is the area under the success plot, the
fraction of frames whose intersection-over-union exceeds t, averaged over t = 0, 0.05, ..., 1.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.errors import ConfigError
from firmware_protocol.errors import ProtocolError

__all__ = [
    "OtbFormatError",
    "OtbSequence",
    "OtbTarget",
    "centre_errors",
    "load_sequence",
    "overlaps",
    "parse_groundtruth",
    "precision_at",
    "success_auc",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]

_SEPARATORS = re.compile(rb"[,\s]+")
SUCCESS_THRESHOLDS: FloatArray = np.linspace(0.0, 1.0, 21)


class OtbFormatError(ProtocolError):
    """A ground-truth line that is not four numbers with a positive size. ``file`` and ``line_number``
    (1-based) say where."""

    def __init__(self, reason: str, file: str, line_number: int, line: bytes = b"") -> None:
        super().__init__(reason, line)
        self.file = file
        self.line_number = line_number
        shown = line[:48].decode("ascii", "replace")
        self.args = (f"{file}:{line_number}: {reason} (line: {shown!r})",)


def parse_groundtruth(data: bytes, file: str = "<groundtruth>") -> FloatArray:
    """OTB ground-truth text -> (N, 4) float boxes ``x, y, w, h``, 0-based. Any separator of commas and
    white space, LF or CRLF, with or without a final newline; blank lines skipped; anything else raises
    :class:`OtbFormatError`."""
    boxes: list[list[float]] = []
    for number, raw in enumerate(data.split(b"\n"), start=1):
        line = raw.strip()
        if line.startswith(b"\xef\xbb\xbf"):  # a UTF-8 byte-order mark some editors write
            line = line[3:].strip()
        if not line:
            continue
        fields = [f for f in _SEPARATORS.split(line) if f]
        if len(fields) != 4:
            raise OtbFormatError(f"expected 4 numbers (x, y, w, h), got {len(fields)}", file, number, raw)
        try:
            x, y, w, h = (float(f) for f in fields)
        except ValueError:
            raise OtbFormatError("not a number", file, number, raw) from None
        if not all(np.isfinite((x, y, w, h))):
            raise OtbFormatError("not a finite number", file, number, raw)
        if w <= 0.0 or h <= 0.0:
            raise OtbFormatError("box width and height must be positive", file, number, raw)
        boxes.append([x - 1.0, y - 1.0, w, h])
    if not boxes:
        raise OtbFormatError("no boxes", file, 0)
    return np.asarray(boxes, dtype=np.float64)


@dataclass(frozen=True)
class OtbTarget:
    """One annotated target: its name (the sequence's, or ``Jogging-1`` for ``groundtruth_rect.1.txt``), the
    file and the boxes, one per frame from the first."""

    name: str
    groundtruth_file: Path
    boxes: FloatArray


@dataclass(frozen=True)
class OtbSequence:
    name: str
    frames: tuple[Path, ...]
    targets: tuple[OtbTarget, ...]


def load_sequence(directory: str | Path) -> OtbSequence:
    """Read an OTB-style folder: its frames' paths (``img/*.jpg`` in name order) and every
    ``groundtruth_rect*.txt``. A target annotated on fewer frames than there are is evaluated on those;
    more boxes than frames is an error."""
    root = Path(directory)
    if not root.is_dir():
        raise ConfigError("--sequence", f"{root} is not a folder")
    frames = tuple(sorted((root / "img").glob("*.jpg")))
    if not frames:
        raise ConfigError("--sequence", f"{root}/img holds no .jpg frames (an OTB folder: img/*.jpg)")
    files = sorted(root.glob("groundtruth_rect*.txt"))
    if not files:
        raise ConfigError("--sequence", f"{root} has no groundtruth_rect*.txt")
    targets = []
    for path in files:
        boxes = parse_groundtruth(path.read_bytes(), str(path))
        if len(boxes) > len(frames):
            raise OtbFormatError(f"{len(boxes)} boxes for {len(frames)} frames", str(path), len(boxes))
        if len(boxes) < len(frames):
            log.warning(
                "%s: %d boxes for %d frames; scoring the first %d", path, len(boxes), len(frames), len(boxes)
            )
        # groundtruth_rect.txt -> the sequence's name; groundtruth_rect.2.txt -> "<name>-2" (OTB's naming).
        middle = path.name[len("groundtruth_rect") : -len(".txt")].strip(".")
        targets.append(OtbTarget(f"{root.name}-{middle}" if middle else root.name, path, boxes))
    return OtbSequence(root.name, frames, tuple(targets))


def _check(pred: FloatArray, truth: FloatArray) -> None:
    if pred.shape != truth.shape or pred.ndim != 2 or pred.shape[1] != 4:
        raise ValueError(f"boxes must both be (N, 4), got {pred.shape} and {truth.shape}")


def centre_errors(pred: FloatArray, truth: FloatArray) -> FloatArray:
    """Euclidean distance (px) between the centres of each pair of boxes (N,)."""
    _check(pred, truth)
    dc = (pred[:, :2] + pred[:, 2:] / 2.0) - (truth[:, :2] + truth[:, 2:] / 2.0)
    return np.asarray(np.hypot(dc[:, 0], dc[:, 1]), dtype=np.float64)


def overlaps(pred: FloatArray, truth: FloatArray) -> FloatArray:
    """Intersection over union of each pair of boxes (N,), 0 for disjoint boxes."""
    _check(pred, truth)
    x0 = np.maximum(pred[:, 0], truth[:, 0])
    y0 = np.maximum(pred[:, 1], truth[:, 1])
    x1 = np.minimum(pred[:, 0] + pred[:, 2], truth[:, 0] + truth[:, 2])
    y1 = np.minimum(pred[:, 1] + pred[:, 3], truth[:, 1] + truth[:, 3])
    inter = np.clip(x1 - x0, 0.0, None) * np.clip(y1 - y0, 0.0, None)
    union = pred[:, 2] * pred[:, 3] + truth[:, 2] * truth[:, 3] - inter
    return np.asarray(inter / np.maximum(union, 1e-12), dtype=np.float64)


def precision_at(errors_px: FloatArray, threshold_px: float = 20.0) -> float:
    """OTB precision: the fraction of frames with centre error within ``threshold_px``."""
    return float(np.mean(errors_px <= threshold_px)) if len(errors_px) else float("nan")


def success_auc(ious: FloatArray) -> float:
    """OTB success AUC: the mean over t = 0, 0.05, ..., 1 of the fraction of frames with IoU > t."""
    if not len(ious):
        return float("nan")
    return float(np.mean([np.mean(ious > t) for t in SUCCESS_THRESHOLDS]))
