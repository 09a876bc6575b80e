"""The ROS 2 message definitions a recording is exported with, as rosbag2 stores them in an MCAP file
(``ros2msg`` schema encoding: the type's own ``.msg`` fields, then each type it uses after a line of 80
``=`` and ``MSG: pkg/Type``), pure data.

The fields are those of ROS 2's ``common_interfaces`` (sensor_msgs, nav_msgs, geometry_msgs,
std_msgs, diagnostic_msgs with its constants), ``geometry2``'s tf2_msgs and
``rcl_interfaces/builtin_interfaces``, unchanged since Humble,
without comments and default values (neither changes the wire format). The export test compares them with
rosbags' Humble type store and decodes the bag with it, so a field that differed would fail there.
"""

from __future__ import annotations

__all__ = [
    "DIAGNOSTIC_ARRAY",
    "IMU",
    "LASER_SCAN",
    "OCCUPANCY_GRID",
    "ODOMETRY",
    "POSE_STAMPED",
    "POSE_WITH_COVARIANCE_STAMPED",
    "TF_MESSAGE",
    "TWIST_STAMPED",
    "TYPES",
    "msgdef",
]

_SEPARATOR = "=" * 80

_FIELDS: dict[str, str] = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
    "geometry_msgs/Twist": "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular",
    "geometry_msgs/Transform": "geometry_msgs/Vector3 translation\ngeometry_msgs/Quaternion rotation",
    "geometry_msgs/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/Transform transform"
    ),
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "geometry_msgs/PoseWithCovariance": "geometry_msgs/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/TwistWithCovariance": "geometry_msgs/Twist twist\nfloat64[36] covariance",
    "geometry_msgs/PoseWithCovarianceStamped": (
        "std_msgs/Header header\ngeometry_msgs/PoseWithCovariance pose"
    ),
    "nav_msgs/Odometry": (
        "std_msgs/Header header\nstring child_frame_id\ngeometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist"
    ),
    "nav_msgs/MapMetaData": (
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n"
        "geometry_msgs/Pose origin"
    ),
    "nav_msgs/OccupancyGrid": "std_msgs/Header header\nnav_msgs/MapMetaData info\nint8[] data",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\ngeometry_msgs/Pose pose",
    "geometry_msgs/TwistStamped": "std_msgs/Header header\ngeometry_msgs/Twist twist",
    "sensor_msgs/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\nfloat64[9] linear_acceleration_covariance"
    ),
    "diagnostic_msgs/KeyValue": "string key\nstring value",
    "diagnostic_msgs/DiagnosticStatus": (
        "byte OK=0\nbyte WARN=1\nbyte ERROR=2\nbyte STALE=3\nbyte level\nstring name\nstring message\n"
        "string hardware_id\ndiagnostic_msgs/KeyValue[] values"
    ),
    "diagnostic_msgs/DiagnosticArray": "std_msgs/Header header\ndiagnostic_msgs/DiagnosticStatus[] status",
    "sensor_msgs/LaserScan": (
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
        "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
        "float32[] ranges\nfloat32[] intensities"
    ),
}

_PRIMITIVES = frozenset(
    {"bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64"}
    | {"float32", "float64", "string"}
)


def _uses(name: str) -> list[str]:
    """The message types ``name`` uses, depth first, each once."""
    out: list[str] = []

    def walk(type_name: str) -> None:
        for line in _FIELDS[type_name].splitlines():
            field_type = line.split()[0].split("[")[0]
            if field_type in _PRIMITIVES or field_type in out:
                continue
            out.append(field_type)
            walk(field_type)

    walk(name)
    return out


def msgdef(name: str) -> str:
    """The full definition of ``pkg/msg/Type`` (or ``pkg/Type``) with every type it uses."""
    short = name.replace("/msg/", "/")
    parts = [_FIELDS[short]]
    for used in _uses(short):
        parts.append(f"{_SEPARATOR}\nMSG: {used}\n{_FIELDS[used]}")
    return "\n".join(parts) + "\n"


LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
IMU = "sensor_msgs/msg/Imu"
TWIST_STAMPED = "geometry_msgs/msg/TwistStamped"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
TYPES = (
    LASER_SCAN,
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    OCCUPANCY_GRID,
    TF_MESSAGE,
    IMU,
    TWIST_STAMPED,
    POSE_STAMPED,
    DIAGNOSTIC_ARRAY,
)
