"""The small frozen types the runtime passes between its loops and its pluggable algorithms.

They are the runtime's own, not the algorithm packages': ``agent.vlp`` and ``agent.slam`` are reached only
through the adapters in :mod:`agent.runtime.localizer` and :mod:`agent.runtime.mapper`, so the runtime
does not change when an algorithm's internals do. Times are ``time.monotonic_ns()`` (the drivers' host
time); units are in the names.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]

__all__ = ["AbsoluteFix", "NoFix", "Prior", "Tilt"]


@dataclass(frozen=True, slots=True)
class Tilt:
    """Roll and pitch of the robot base (from the IMU), radians."""

    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class Prior:
    """Where the fused estimate puts the base at a frame's time, and how it moves (map frame)."""

    x_m: float
    y_m: float
    yaw_rad: float
    sigma_xy_m: float
    sigma_yaw_rad: float
    vx_mps: float = 0.0
    vy_mps: float = 0.0
    yaw_rate_radps: float = 0.0


@dataclass(frozen=True, slots=True)
class AbsoluteFix:
    """A pose of the base in the map frame measured at ``t_ns`` (a VLP fix, a SLAM pose).

    ``yaw_rad`` None: position only, and ``covariance`` is 2x2; otherwise 3x3 over (x, y, yaw).
    ``detail``: what the source says about it (LED ids, residual, the filter's state), for logs and status.
    ``degraded`` and ``protection_level_m``: its integrity, as the source judges it (the fusion honours
    them, ``agent.fusion.FixIntegrity``).
    """

    t_ns: int
    x_m: float
    y_m: float
    yaw_rad: float | None
    covariance: FloatArray
    degraded: bool = False
    detail: dict[str, object] = field(default_factory=dict)
    # The largest position error the fix cannot rule out (VLP's protection level; inf: none can be, e.g.
    # two LEDs; NaN: the source gives none, e.g. SLAM).
    protection_level_m: float = math.nan

    @property
    def sigma_xy_m(self) -> float:
        c = self.covariance
        a, b, d = float(c[0, 0]), float(c[0, 1]), float(c[1, 1])
        return math.sqrt(max(0.5 * (a + d) + math.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0))


@dataclass(frozen=True, slots=True)
class NoFix:
    """No pose from this input, and why (one short sentence from the algorithm)."""

    t_ns: int
    reason: str
