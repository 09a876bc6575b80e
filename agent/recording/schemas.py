"""The JSON schemas of the recording's channels (MCAP ``jsonschema`` encoding), pure data.

Foxglove recognizes a channel by its schema *name*: ``foxglove.LaserScan``, ``foxglove.PoseInFrame``,
``foxglove.FrameTransforms`` and ``foxglove.Grid`` are written with the field names of Foxglove's own
JSON schemas (github.com/foxglove/schemas, ``schemas/jsonschema/*.json``), so Foxglove draws them with
nothing else installed. The ``vlp_agent.*`` schemas are the project's: what the devices and loops produce,
field for field, with units in the names; every field they declare is required.

There is deliberately no image schema: camera images are never recorded (ARCHITECTURE.md, "No camera image
ever leaves the robot").
"""

from __future__ import annotations

from typing import Any

__all__ = ["SCHEMAS", "Schema"]

Schema = dict[str, Any]

_NUMBER: Schema = {"type": "number"}
_INTEGER: Schema = {"type": "integer"}
_STRING: Schema = {"type": "string"}
_BOOLEAN: Schema = {"type": "boolean"}

_TIME: Schema = {
    "type": "object",
    "title": "time",
    "properties": {
        "sec": {"type": "integer", "minimum": 0},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999},
    },
}
_VECTOR3: Schema = {
    "title": "foxglove.Vector3",
    "type": "object",
    "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER},
}
_QUATERNION: Schema = {
    "title": "foxglove.Quaternion",
    "type": "object",
    "properties": {"x": _NUMBER, "y": _NUMBER, "z": _NUMBER, "w": _NUMBER},
}
_POSE: Schema = {
    "title": "foxglove.Pose",
    "type": "object",
    "properties": {"position": _VECTOR3, "orientation": _QUATERNION},
}


def _array(items: Schema) -> Schema:
    return {"type": "array", "items": items}


def _nullable(schema: Schema) -> Schema:
    return {**schema, "type": [schema["type"], "null"]}


def _project(name: str, description: str, properties: dict[str, Schema]) -> Schema:
    return {
        "title": name,
        "description": description,
        "type": "object",
        "properties": properties,
        "required": list(properties),
    }


_LED: Schema = {
    "type": "object",
    "properties": {
        "track_id": _INTEGER,
        "id": _nullable(_STRING),
        "id_confidence": _NUMBER,
        "frame_id": _nullable(_STRING),
        "u_px": _NUMBER,
        "v_px": _NUMBER,
        "radius_px": _NUMBER,
        "visibility": _STRING,
        "map_index": _nullable(_INTEGER),
        "used": _BOOLEAN,
    },
    "required": [
        "track_id",
        "id",
        "id_confidence",
        "frame_id",
        "u_px",
        "v_px",
        "radius_px",
        "visibility",
        "map_index",
        "used",
    ],
}

SCHEMAS: dict[str, Schema] = {
    "foxglove.LaserScan": {
        "title": "foxglove.LaserScan",
        "description": "A single scan from a planar laser range-finder",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": _STRING,
            "pose": _POSE,
            "start_angle": _NUMBER,
            "end_angle": _NUMBER,
            "ranges": _array(_NUMBER),
            "intensities": _array(_NUMBER),
        },
    },
    "foxglove.PoseInFrame": {
        "title": "foxglove.PoseInFrame",
        "description": "A timestamped pose for an object or reference frame in 3D space",
        "type": "object",
        "properties": {"timestamp": _TIME, "frame_id": _STRING, "pose": _POSE},
    },
    "foxglove.FrameTransforms": {
        "title": "foxglove.FrameTransforms",
        "description": "An array of FrameTransform messages",
        "type": "object",
        "properties": {
            "transforms": _array(
                {
                    "title": "foxglove.FrameTransform",
                    "type": "object",
                    "properties": {
                        "timestamp": _TIME,
                        "parent_frame_id": _STRING,
                        "child_frame_id": _STRING,
                        "translation": _VECTOR3,
                        "rotation": _QUATERNION,
                    },
                }
            )
        },
    },
    "foxglove.Grid": {
        "title": "foxglove.Grid",
        "description": "A 2D grid of data",
        "type": "object",
        "properties": {
            "timestamp": _TIME,
            "frame_id": _STRING,
            "pose": _POSE,
            "column_count": {"type": "integer", "minimum": 0},
            "cell_size": {
                "title": "foxglove.Vector2",
                "type": "object",
                "properties": {"x": _NUMBER, "y": _NUMBER},
            },
            "row_stride": {"type": "integer", "minimum": 0},
            "cell_stride": {"type": "integer", "minimum": 0},
            "fields": _array(
                {
                    "title": "foxglove.PackedElementField",
                    "type": "object",
                    "properties": {
                        "name": _STRING,
                        "offset": {"type": "integer", "minimum": 0},
                        "type": _INTEGER,  # foxglove.NumericType: 1 = UINT8
                    },
                }
            ),
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    },
    "vlp_agent.Scan": _project(
        "vlp_agent.Scan",
        "A laser scan as the driver gave it: raw range values (below min_range_mm: the device's error "
        "codes), the host receive time and the device's own unwrapped millisecond stamp",
        {
            "host_time_ns": _INTEGER,
            "device_time_ms": _nullable(_INTEGER),
            "sequence": _INTEGER,
            "angle_min_rad": _NUMBER,
            "angle_increment_rad": _NUMBER,
            "min_range_mm": _INTEGER,
            "max_range_mm": _INTEGER,
            "ranges_mm": _array(_INTEGER),
        },
    ),
    "vlp_agent.WheelState": _project(
        "vlp_agent.WheelState",
        "The two drive wheels (left, right) as read from the servos",
        {
            "host_time_ns": _INTEGER,
            "position_rad": _array(_NUMBER),
            "velocity_radps": _array(_NUMBER),
            "hardware_error": _array(_INTEGER),
        },
    ),
    "vlp_agent.WheelCommand": _project(
        "vlp_agent.WheelCommand",
        "The wheel velocities sent to the servos (left, right) and the base velocity they were made from",
        {
            "host_time_ns": _INTEGER,
            "left_radps": _NUMBER,
            "right_radps": _NUMBER,
            "v_mps": _NUMBER,
            "omega_radps": _NUMBER,
        },
    ),
    "vlp_agent.ImuSample": _project(
        "vlp_agent.ImuSample",
        "Accelerometer and gyroscope in the sensor frame, and the die temperature",
        {
            "host_time_ns": _INTEGER,
            "accel_mps2": _array(_NUMBER),
            "gyro_radps": _array(_NUMBER),
            "temperature_c": _NUMBER,
        },
    ),
    "vlp_agent.TagRead": _project(
        "vlp_agent.TagRead",
        "One RFID tag detection (the optional fields null from readers that do not report them)",
        {
            "host_time_ns": _INTEGER,
            "tag_id": _STRING,
            "reader": _STRING,
            "rssi_dbm": _nullable(_NUMBER),
            "antenna": _nullable(_INTEGER),
            "frequency_khz": _nullable(_INTEGER),
            "phase_deg": _nullable(_NUMBER),
            "device_time_ms": _nullable(_INTEGER),
        },
    ),
    "vlp_agent.VlpFix": _project(
        "vlp_agent.VlpFix",
        "A VLP fix of the base in the map frame with the LED observations it came from (image points in "
        "output pixels); covariance row-major over (x_m, y_m, yaw_rad), or (x_m, y_m) when yaw is null",
        {
            "t_ns": _INTEGER,
            "x_m": _NUMBER,
            "y_m": _NUMBER,
            "yaw_rad": _nullable(_NUMBER),
            "covariance": _array(_NUMBER),
            "degraded": _BOOLEAN,
            "ids": _array(_STRING),
            "residual_rms": _nullable(_NUMBER),
            "flags": _array(_STRING),
            "leds": _array(_LED),
        },
    ),
    "vlp_agent.NoFix": _project(
        "vlp_agent.NoFix",
        "A frame that gave no VLP fix, and why",
        {"t_ns": _INTEGER, "reason": _STRING},
    ),
    "vlp_agent.FusedPose": _project(
        "vlp_agent.FusedPose",
        "A fused pose written on the pose output: the filter's input count when it was read, the estimate, "
        "its covariance (row-major 3x3 over x_m, y_m, yaw_rad) and the status flags",
        {
            "t_ns": _INTEGER,
            "version": _INTEGER,
            "x_m": _NUMBER,
            "y_m": _NUMBER,
            "yaw_rad": _NUMBER,
            "covariance": _array(_NUMBER),
            "flags": _INTEGER,
        },
    ),
    "vlp_agent.SlamPose": _project(
        "vlp_agent.SlamPose",
        "A SLAM filter update's pose of the base (map frame) and its covariance (row-major 3x3)",
        {
            "t_ns": _INTEGER,
            "x_m": _NUMBER,
            "y_m": _NUMBER,
            "yaw_rad": _NUMBER,
            "covariance": _array(_NUMBER),
        },
    ),
    "vlp_agent.Command": _project(
        "vlp_agent.Command",
        "A command received from the controller: its kind and its fields as decoded",
        {"host_time_ns": _INTEGER, "kind": _STRING, "fields": {"type": "object"}},
    ),
    "vlp_agent.GoalState": _project(
        "vlp_agent.GoalState",
        "A goal status sent to the controller",
        {"host_time_ns": _INTEGER, "state": _STRING, "fields": {"type": "object"}},
    ),
    "vlp_agent.FusionSetup": _project(
        "vlp_agent.FusionSetup",
        "How the fusion filter was set up (agent.fusion.PoseFilter.parameters), once at the start",
        {"parameters": {"type": "object"}},
    ),
    "vlp_agent.FusionInput": {
        "title": "vlp_agent.FusionInput",
        "description": "One input the fusion filter took, in the order it took them (agent.fusion's observer "
        "record: k = odometry | gyro | pose, with its measurement and arrival times)",
        "type": "object",
        "properties": {"k": _STRING, "a": _nullable(_INTEGER)},
        "required": ["k", "a"],
    },
    "vlp_agent.SlamSetup": _project(
        "vlp_agent.SlamSetup",
        "How the SLAM mapper was built, once at the start: the [slam] config (every key, as in the config "
        "file), the laser's mount on the base and the mapper's name (slam, mcl)",
        {"config": {"type": "object"}, "mount": {"type": "object"}, "mapper": _STRING},
    ),
    "vlp_agent.SlamInput": {
        "title": "vlp_agent.SlamInput",
        "description": "One call the SLAM loop made into its mapper, in the order it made them: k = scan "
        "(t = the scan's host_time_ns on /laser/scan_raw, seq, odom = the odometry pose it went with, step = "
        "what the mapper did), fix (an absolute fix x, y, yaw, cov with the odometry pose at its time) or "
        "start (the pose the map was told to start at, null: not known yet)",
        "type": "object",
        "properties": {"k": _STRING, "t": _INTEGER},
        "required": ["k", "t"],
    },
    "vlp_agent.SimTruth": _project(
        "vlp_agent.SimTruth",
        "The simulated robot's true base pose (map frame) at the time of each pose written (vlp-agent sim)",
        {"t_ns": _INTEGER, "x_m": _NUMBER, "y_m": _NUMBER, "yaw_rad": _NUMBER},
    ),
    "vlp_agent.HealthEvent": _project(
        "vlp_agent.HealthEvent",
        "A device's state changed (up, lost, recovered), with the reason",
        {"host_time_ns": _INTEGER, "device": _STRING, "ok": _BOOLEAN, "reason": _STRING},
    ),
}
