"""MAVLink 2 pose output, the alternative to the pose frame for autopilots (PX4, ArduPilot) and MAVLink tools.

The same :class:`~firmware_protocol.pose_frame.PoseFrame` the frame encoder takes becomes one of

* ``VISION_POSITION_ESTIMATE`` (#102, CRC_EXTRA 158): position, roll/pitch/yaw, a 21-float covariance and
  the reset counter; at most 129 bytes on the wire (MAVLink 2 drops trailing zero bytes of a payload);
* ``ODOMETRY`` (#331, CRC_EXTRA 91, MAVLink 2 only): pose as a quaternion plus (here unknown) velocities
  and both covariances, the reset counter, an estimator type and a quality; up to 245 bytes.

Encoding goes through pymavlink's generated ``pymavlink.dialects.v20.common`` (pure packing: no port, no
I/O); ``MAVLINK20=1`` is put in the environment first, as pymavlink wants before any of its modules load.
pymavlink is imported on first use, so importing this module costs nothing when the pose frame is chosen
(and ``firmware_protocol`` itself still needs nothing outside the standard library).

Conventions, as a receiver sees them:

* **Frames.** Our map frame is right-handed with z up and yaw counter-clockwise; MAVLink's local frames
  are z down. We rotate by pi about x: ``(x, y, yaw) -> (x, -y, -yaw)``, z = roll = pitch = 0 (a ground
  robot). ODOMETRY says ``frame_id = MAV_FRAME_LOCAL_FRD`` (20) and ``child_frame_id = MAV_FRAME_BODY_FRD``
  (12), its quaternion is ``[cos(yaw/2), 0, 0, sin(yaw/2)]`` of the FRD yaw.
* **Time.** ``usec`` / ``time_usec`` is ``PoseFrame.t_us``: the agent's monotonic clock ("time since system
  boot" in MAVLink's words).
* **Covariance** (upper triangle of the 6x6 over x, y, z, roll, pitch, yaw, row-major): var x = var y =
  ``sigma_xy_m**2`` (indices 0 and 6), var yaw = ``sigma_yaw_rad**2`` (index 20), everything else 0
  (z, roll and pitch are fixed by the floor). An unknown ``sigma_xy_m`` puts NaN in element 0, MAVLink's
  "covariance unknown"; an unknown ``sigma_yaw_rad`` alone becomes pi**2/3, the variance of an angle
  spread evenly round the circle. ODOMETRY's velocities and velocity covariance are NaN (unknown).
* **Sequence.** The MAVLink header's 8-bit sequence is ``PoseFrame.sequence`` modulo 256, so a controller
  counts lost frames the same way for either output.
"""

from __future__ import annotations

import enum
import functools
import importlib
import math
import os
import struct
import types
from collections.abc import Sequence
from typing import Any

from firmware_protocol.errors import ProtocolError
from firmware_protocol.pose_frame import PoseFrame

__all__ = [
    "CRC_EXTRA",
    "DEFAULT_COMPID",
    "DEFAULT_SYSID",
    "MAV_ESTIMATOR_TYPE_VISION",
    "MAV_FRAME_BODY_FRD",
    "MAV_FRAME_LOCAL_FRD",
    "MSG_ID",
    "MavlinkEncodeError",
    "MavlinkMessage",
    "MavlinkPoseEncoder",
    "pose_covariance",
]


class MavlinkMessage(enum.StrEnum):
    """Which MAVLink message carries the pose (the config's name for it)."""

    VISION_POSITION_ESTIMATE = "vision_position_estimate"
    ODOMETRY = "odometry"


MSG_ID = {MavlinkMessage.VISION_POSITION_ESTIMATE: 102, MavlinkMessage.ODOMETRY: 331}
CRC_EXTRA = {MavlinkMessage.VISION_POSITION_ESTIMATE: 158, MavlinkMessage.ODOMETRY: 91}

MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
DEFAULT_SYSID = 1  # a companion computer usually shares the autopilot's system id
DEFAULT_COMPID = 197  # MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: where PX4 and ArduPilot expect external vision

_YAW_UNKNOWN_VARIANCE = math.pi**2 / 3  # variance of a yaw uniform on the circle
_NAN21 = (math.nan,) + (0.0,) * 20


class MavlinkEncodeError(ProtocolError):
    """A pose that cannot be put into the chosen MAVLink message."""


@functools.cache
def mavlink_dialect() -> types.ModuleType:
    os.environ.setdefault("MAVLINK20", "1")
    try:
        module = importlib.import_module("pymavlink.dialects.v20.common")
    except ImportError as exc:
        raise MavlinkEncodeError("MAVLink pose output needs pymavlink: pip install pymavlink") from exc
    if module.WIRE_PROTOCOL_VERSION != "2.0":
        raise MavlinkEncodeError(f"pymavlink dialect speaks MAVLink {module.WIRE_PROTOCOL_VERSION}, not 2.0")
    return module


def pose_covariance(pose: PoseFrame) -> list[float]:
    """The 21-element upper-triangle pose covariance (x, y, z, roll, pitch, yaw) for ``pose``."""
    if not math.isfinite(pose.sigma_xy_m):
        return list(_NAN21)
    cov = [0.0] * 21
    cov[0] = cov[6] = pose.sigma_xy_m**2
    cov[20] = pose.sigma_yaw_rad**2 if math.isfinite(pose.sigma_yaw_rad) else _YAW_UNKNOWN_VARIANCE
    return cov


def _u8(value: int, what: str) -> int:
    if not 0 <= value <= 0xFF:
        raise MavlinkEncodeError(f"{what} {value} does not fit in 0..255")
    return value


class MavlinkPoseEncoder:
    """Encodes poses as one MAVLink 2 message kind from one (sysid, compid); pure, keeps no per-call state.

    ``estimator_type`` and ``quality`` only matter for ODOMETRY (quality: 0 unknown, 1..100, -1 failed).
    """

    def __init__(
        self,
        message: MavlinkMessage | str = MavlinkMessage.VISION_POSITION_ESTIMATE,
        sysid: int = DEFAULT_SYSID,
        compid: int = DEFAULT_COMPID,
        estimator_type: int = MAV_ESTIMATOR_TYPE_VISION,
    ) -> None:
        try:
            self.message = MavlinkMessage(message)
        except ValueError as exc:
            choices = ", ".join(m.value for m in MavlinkMessage)
            raise MavlinkEncodeError(f"unknown MAVLink pose message {message!r} (one of {choices})") from exc
        self.sysid = _u8(sysid, "sysid")
        self.compid = _u8(compid, "compid")
        self.estimator_type = _u8(estimator_type, "estimator_type")
        self._mav: Any = mavlink_dialect().MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)

    def encode(self, pose: PoseFrame, quality: int = 0) -> bytes:
        """One complete MAVLink 2 frame (unsigned) for ``pose``."""
        for name in ("x_m", "y_m", "yaw_rad"):
            if not math.isfinite(getattr(pose, name)):
                raise MavlinkEncodeError(f"pose {name} must be finite, got {getattr(pose, name)}")
        if not 0 <= pose.t_us < 1 << 64:
            raise MavlinkEncodeError(f"t_us {pose.t_us} does not fit in 64 bits")
        if not -1 <= quality <= 100:
            raise MavlinkEncodeError(f"quality must be -1..100, got {quality}")
        reset = _u8(pose.reset_counter, "reset_counter")
        x, y, yaw = pose.x_m, -pose.y_m, -pose.yaw_rad  # map (z up, CCW) -> FRD (z down)
        yaw = math.remainder(yaw, math.tau)
        cov = pose_covariance(pose)
        dialect = mavlink_dialect()
        if self.message is MavlinkMessage.VISION_POSITION_ESTIMATE:
            msg = dialect.MAVLink_vision_position_estimate_message(
                pose.t_us, x, y, 0.0, 0.0, 0.0, yaw, cov, reset
            )
        else:
            q = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
            nan3: Sequence[float] = (math.nan, math.nan, math.nan)
            msg = dialect.MAVLink_odometry_message(
                pose.t_us,
                MAV_FRAME_LOCAL_FRD,
                MAV_FRAME_BODY_FRD,
                x,
                y,
                0.0,
                q,
                *nan3,
                *nan3,
                cov,
                list(_NAN21),
                reset,
                self.estimator_type,
                quality,
            )
        self._mav.seq = pose.sequence & 0xFF
        try:
            return bytes(msg.pack(self._mav))
        except (struct.error, OverflowError) as exc:  # a float beyond float32 range, say
            raise MavlinkEncodeError(f"pymavlink could not pack {self.message.value}: {exc}") from exc
