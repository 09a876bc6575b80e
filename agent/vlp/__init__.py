"""Visible light positioning: LED detection, CamShift-Kalman tracking, stripe ids, pose solving, calibration.

Pure numpy/OpenCV/scipy on arrays and small frozen dataclasses: no threads, files or printing. The entry point
is :class:`~agent.vlp.pipeline.VlpPipeline`; the algorithms are in ``detect``, ``track``, ``decode``,
``geometry``, ``solve`` (with the bounded id association), ``integrity`` (the consistency test and the
protection level) and ``calibration``. See docs/vlp.md.
"""

from agent.vlp.calibration import (
    ResidualCorrection,
    VlpCalibration,
    fit_residual_correction,
    fit_rotation_centre,
    format_calibration,
    parse_calibration,
    validated_residual_correction,
)
from agent.vlp.model import (
    AssociationWork,
    CameraIntrinsics,
    CameraMount,
    LedMap,
    LedObservation,
    MapLed,
    Motion,
    NoFix,
    PosePrior,
    Signature,
    StageTimings,
    Tilt,
    VlpFix,
    VlpResult,
)
from agent.vlp.pipeline import VlpConfig, VlpPipeline

__all__ = [
    "AssociationWork",
    "CameraIntrinsics",
    "CameraMount",
    "LedMap",
    "LedObservation",
    "MapLed",
    "Motion",
    "NoFix",
    "PosePrior",
    "ResidualCorrection",
    "Signature",
    "StageTimings",
    "Tilt",
    "VlpCalibration",
    "VlpConfig",
    "VlpFix",
    "VlpPipeline",
    "VlpResult",
    "fit_residual_correction",
    "fit_rotation_centre",
    "format_calibration",
    "parse_calibration",
    "validated_residual_correction",
]
