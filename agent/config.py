"""The robot's config file: one TOML file per robot, checked whole on load (the keys are ``docs/config.md``).

``load_config(path)`` returns an :class:`AgentConfig` or raises :class:`~drivers.errors.ConfigError` naming
the file and the exact key (``servos.baudrate``, ``vlp.leds[3].duty``), with a "did you mean" for a
misspelt key. Nothing is opened here: device paths are only checked for type, because a device may be
plugged in after the config is written; files the config points at (a LED map, a camera_info, a
calibration, a world) are read now, so that a wrong path fails at start-up and not an hour later.

Device tables (``[camera]``, ``[laser]``, ``[servos]``, ``[imu]``, ``[rfid]``) say ``backend = "..."`` and
give that backend's options under the driver's own argument names. The options a backend takes, and their
types, are read from the driver class's signature (``drivers.registry.backend_class``), so the config can
never drift from the drivers. With a ``[sim]`` table the devices are the simulated robot's
(``drivers.sim.harness.SimulatedRobot``): where they are (ports, buses) comes from the simulation, the
tables may still set the other options, and the VLP camera model and LED map default to the world's
(the nominal calibration and the surveyed map, i.e. what a calibrated robot would believe).

Angles may be given in degrees wherever a key ends in ``_rad`` (``yaw_deg = 90``), as in world files.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import inspect
import math
import os
import tomllib
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agent.config_slam import MountConfig, SlamConfig, SlamMode
from agent.exploration.config import ExploreConfig, ExplorerKind, NamedPoint
from agent.navigation.config import NavConfig
from drivers.errors import BackendUnavailable, ConfigError
from drivers.registry import (
    BACKENDS,
    FORWARD_CAMERA_BACKENDS,
    DeviceKind,
    backend_class,
    forward_camera_class,
)
from drivers.sim.world import World
from drivers.sim.worldfile import MAX_LEDS
from drivers.toml_table import TomlTable, read_toml, type_name

__all__ = [
    "AgentConfig",
    "ControlConfig",
    "DeviceConfig",
    "FleetConfig",
    "FollowingConfig",
    "ForwardViewConfig",
    "FusionConfig",
    "HealthConfig",
    "IntrinsicsConfig",
    "LedConfig",
    "MountConfig",
    "OutputConfig",
    "OutputFormat",
    "RecordConfig",
    "SimConfig",
    "SlamConfig",
    "SlamMode",
    "VlpConfig",
    "load_config",
    "parse_config",
    "read_camera_info",
    "read_led_map",
]

# Arguments a device table never sets: the registry name, objects the agent passes itself, and the
# camera's settings (given as flat keys, see CAMERA_SETTINGS).
_NOT_OPTIONS = {"self", "name", "settings", "simulation", "capture_factory"}
CAMERA_SETTINGS = ("width", "height", "pixel_format", "exposure_s", "gain_db", "frame_rate_hz")
# Keys the simulated robot sets: where each device is.
SIM_LOCATION_KEYS: dict[DeviceKind, tuple[str, ...]] = {
    DeviceKind.LASER: ("url",),
    DeviceKind.SERVOS: ("port",),
    DeviceKind.RFID: ("url",),
    DeviceKind.IMU: ("bus",),
    DeviceKind.CAMERA: (),
}
# In the simulation these come from the world and may not be set in the config (they would disagree).
_SIM_WORLD_KEYS: dict[DeviceKind, tuple[str, ...]] = {
    DeviceKind.SERVOS: ("left_id", "right_id", "wheel_radius_m", "track_m"),
}
_SECTIONS = (
    "sim",
    *(k.value for k in DeviceKind),
    "vlp",
    "slam",
    "fusion",
    "output",
    "control",
    "health",
    "record",
    "recorder",
    "scheduling",
    "navigation",
    "exploration",
    "following",
    "fleet",
)
# pyserial URL handlers that open network sockets: never for the pose stream (nothing leaves over IP).
_NETWORK_SCHEMES = ("socket", "rfc2217")
# Devices whose loops the watchdog waits for by default (a robot localizes without its IMU or RFID reader).
_CRITICAL = (DeviceKind.CAMERA, DeviceKind.LASER, DeviceKind.SERVOS)
# SCHED_FIFO priorities allowed for the hot path: the kernel's IRQ threads (50) and watchdogs (99) stay above.
MAX_REALTIME_PRIORITY = 49
# The PM QoS request is a signed 32-bit value; a second is far beyond any C-state's exit latency.
MAX_CPU_LATENCY_US = 1_000_000
# The serial line carries 10 bits per byte (8N1); the pose stream may use at most this share of it.
_LINE_SHARE = 0.8
# Bounds on every count and size a config gives (docs/config.md, "Limits"), checked on the number before
# anything is built from it, so a slip fails at once with its key instead of allocating or looping for ever.
MAX_IMAGE_SIDE_PX = 8192  # frames and sensors: [vlp.intrinsics], [vlp.rolling_shutter], camera_info, [camera]
MAX_MAP_LEDS = MAX_LEDS  # an LED map holds no more LEDs than a world may
MAX_RECORD_MB = 1_000_000  # a terabyte of recording
# Integer device options that are counts or sizes, by the driver's argument name (one meaning in every
# backend that takes it): (lowest, highest, why).
_OPTION_RANGES: dict[str, tuple[int, int, str]] = {
    "queue_size": (1, 4096, "samples kept for the consumer"),
    "truth_history": (1, 4096, "frames that keep their ground truth"),
    "time_sync_samples": (1, 100, "round trips to the laser at connect"),
    "retries": (0, 100, "retries of one bus transaction"),
    "cluster": (1, 99, "SCIP 2.0 sends it in 2 digits"),
    "first_step": (0, 9999, "SCIP 2.0 sends step numbers in 4 digits"),
    "last_step": (0, 9999, "SCIP 2.0 sends step numbers in 4 digits"),
    "device_index": (0, 255, "cameras on one GenTL producer"),
}
# Array options: the most entries each may have.
_OPTION_LENGTHS: dict[str, int] = {"antenna_ports": 15}  # Mercury readers number their ports 1..15


class OutputFormat(enum.StrEnum):
    FRAME = "frame"
    MAVLINK = "mavlink"


# -- the configuration, as the agent uses it -----------------------------------------------------------
@dataclass(frozen=True)
class SimConfig:
    """The simulated robot: which world (its file and what was read from it), and the seed of its sensors'
    noise."""

    world_file: Path
    world: World
    seed: int = 0
    # SCHED_FIFO priority of the fake devices' serving threads (0: time-shared): they stand in for hardware,
    # which keeps its time whatever the computer's load (docs/config.md).
    device_priority: int = 20


@dataclass(frozen=True)
class DeviceConfig:
    """One device: its backend and the keyword arguments for the backend's class (already checked)."""

    kind: DeviceKind
    backend: str
    options: Mapping[str, Any] = field(default_factory=dict)
    critical: bool = True


@dataclass(frozen=True)
class IntrinsicsConfig:
    """The camera as calibrated, at the resolution of the frames the agent gets, plus its rolling shutter.

    ``sensor_width_px``/``sensor_height_px``: the sensor's size when frames are resized from it with nearest
    neighbour (0: frames are full sensor resolution)."""

    width_px: int
    height_px: int
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    t_row_s: float
    exposure_s: float = 20e-6
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    sensor_width_px: int = 0
    sensor_height_px: int = 0
    source: str = ""


@dataclass(frozen=True)
class LedConfig:
    id: str
    x_m: float
    y_m: float
    z_m: float
    frequency_hz: float
    duty: float
    diameter_m: float = 0.086
    # The survey's standard deviation of this LED's x and y (None: the VLP solver's map_sigma_m, 3 mm).
    survey_sigma_m: float | None = None


@dataclass(frozen=True)
class VlpConfig:
    """``intrinsics``/``leds``/``mount``: None means "the simulated world's" (only with ``[sim]``).
    ``calibration``: the text of a VLP calibration file (``agent.vlp.calibration``), already checked."""

    enabled: bool = True
    intrinsics: IntrinsicsConfig | None = None
    leds: tuple[LedConfig, ...] | None = None
    mount: MountConfig | None = None
    calibration: str | None = None
    calibration_file: str | None = None
    sigma_floor_m: float = 0.005
    sigma_floor_yaw_rad: float = math.radians(0.5)
    # Integrity (agent.fusion.IntegrityPolicy): the largest position error the application tolerates; a
    # fix whose protection level exceeds it is fused only under the guard, its sigmas multiplied by
    # guarded_sigma_scale (0: never fused); a fix flagged degraded is not fused (fuse_degraded: guarded).
    alert_limit_m: float = 0.10
    guarded_sigma_scale: float = 3.0
    fuse_degraded: bool = False


@dataclass(frozen=True)
class FusionConfig:
    """EKF tuning (``agent.fusion``) and how long each source counts as live after its last measurement."""

    initial_pose: tuple[float, float, float] | None = None
    initial_sigma_xy_m: float = 0.05
    initial_sigma_yaw_rad: float = math.radians(2.0)
    odometry_sigma_m_per_m: float = 0.02
    odometry_yaw_rate_sigma_radps: float = 0.02
    odometry_time_sigma_s: float = 0.002
    gyro_sigma_radps: float = 0.005
    yaw_rate_walk_radps2: float = 2.0
    gyro_bias_walk_radps: float = 1e-4
    gate_probability: float = 0.999
    history_s: float = 1.0
    vlp_timeout_s: float = 0.5
    slam_timeout_s: float = 2.0
    odometry_timeout_s: float = 0.3
    imu_timeout_s: float = 0.3


@dataclass(frozen=True)
class OutputConfig:
    """``url``: where the pose stream goes (a device path, a pty, any pyserial URL); ``"pty"`` under
    ``[sim]`` means a pseudo-terminal the simulator makes and reads as a controller would."""

    format: OutputFormat = OutputFormat.FRAME
    url: str | None = None
    baud: int = 115200
    rate_hz: float = 20.0
    write_timeout_s: float = 0.005
    mavlink_message: str = "vision_position_estimate"
    mavlink_sysid: int = 1
    mavlink_compid: int = 197


@dataclass(frozen=True)
class ControlConfig:
    deadman_timeout_s: float = 0.5
    recovery_hold_s: float = 0.5
    loop_rate_hz: float = 50.0
    max_speed_mps: float = 0.22
    max_turn_radps: float = 2.0


@dataclass(frozen=True)
class HealthConfig:
    watchdog: bool = True
    loop_timeout_s: float = 3.0
    status_interval_s: float = 2.0
    ready_grace_s: float = 15.0
    not_localizing_log_s: float = 60.0
    camera_stall_s: float = 0.5
    laser_lost_s: float = 0.5
    servo_fault_s: float = 0.2


@dataclass(frozen=True)
class RecordConfig:
    """Where the fusion's inputs and outputs are recorded (``agent.runtime.recorder``); None: nowhere."""

    path: Path | None = None
    max_mb: float = 200.0


def _all_channels() -> tuple[str, ...]:
    from agent.recording.messages import CHANNELS

    return tuple(CHANNELS)


@dataclass(frozen=True)
class RecorderConfig:
    """The flight recorder (``agent.recording``): every sample in MCAP files named ``<stem>-<n>.mcap``
    beside ``path``; None: nothing recorded. Sizes in MB (10^6 bytes), durations in seconds."""

    path: Path | None = None
    channels: tuple[str, ...] = field(default_factory=_all_channels)
    chunk_s: float = 1.0
    file_mb: float = 100.0
    file_s: float = 600.0
    total_mb: float = 2000.0
    min_free_mb: float = 200.0
    queue_size: int = 20_000
    map_period_s: float = 5.0
    snapshot_s: float = 0.0
    snapshot_mb: float = 64.0
    continuous: bool = True


@dataclass(frozen=True)
class SchedulingConfig:
    """``realtime_priority``: SCHED_FIFO priority of the camera and hot-path threads where the system
    permits it (``agent.runtime.priority``); 0: leave them time-shared. ``cpu_latency_us``: the CPU
    wake-up latency the agent asks the kernel for while it runs (PM QoS, ``/dev/cpu_dma_latency``;
    0: idle cores poll instead of sleeping); -1: no request."""

    realtime_priority: int = 10
    cpu_latency_us: int = 0


@dataclass(frozen=True)
class ForwardViewConfig:
    """``[camera.forward]``'s geometry (``docs/config.md``): where the forward camera sits on the base and
    its lens, for person following's fine layer (image column -> bearing). ``mount``: x, y, z (m), yaw and
    pitch (optical axis tilted up; rad); the lens: ``hfov_rad`` or ``fx_px`` (with ``fy_px``, None: the
    same), principal point ``cx_px``/``cy_px`` (None: the image centre), at ``width_px`` x ``height_px``
    (the ``width``/``height`` settings; None: the frames' own size; frames of another size scale them).
    ``lens_given``: whether the config gave ``hfov`` or ``fx_px`` (following on a real camera needs it).
    With ``camera_info`` (the file ``vlp-agent calibrate forward-camera`` wrote) the lens is that file's:
    ``fx_px`` to ``height_px`` and ``distortion`` (OpenCV's k1, k2, p1, p2, k3)."""

    mount: MountConfig = field(default_factory=lambda: MountConfig(0.1, 0.0, 1.3))
    hfov_rad: float | None = None
    fx_px: float | None = None
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    width_px: int | None = None
    height_px: int | None = None
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    camera_info: str | None = None

    @property
    def lens_given(self) -> bool:
        return self.hfov_rad is not None or self.fx_px is not None


@dataclass(frozen=True)
class FollowingConfig:
    """``[following]``: whom the robot follows and how its RFID layer reads the reader.

    ``tag_id``: the followed person's tag as the reader reports it (None: following is not set up);
    ``rfid_table``: the likelihood table file ``vlp-agent calibrate rfid`` wrote, read now into ``table``
    (None: the physical model of ``antenna_yaws_rad``, one yaw per port of ``[rfid] antenna_ports``);
    ``cycle_s``: the read cycle the coarse filter updates at."""

    tag_id: str | None = None
    rfid_table: Path | None = None
    table: Any = None  # agent.following.coarse.LikelihoodTable
    antenna_yaws_rad: tuple[float, ...] = (math.radians(50.0), math.radians(-50.0))
    cycle_s: float = 0.25
    # The follower (agent.following.follower, docs/following.md).
    distance_m: float = 1.0
    min_gap_m: float = 0.6
    max_speed_mps: float = 0.95
    lost_after_s: float = 1.0
    search_after_s: float = 1.0


def read_rfid_table(path: Path, key: str, file: str) -> Any:
    """The likelihood table in ``path`` (``docs/following.md``); ConfigError naming ``key`` when it cannot be
    read or is malformed."""
    from agent.following.coarse import LikelihoodTable

    try:
        with open(path, "rb") as fp:
            data = tomllib.load(fp)
    except OSError as exc:
        raise ConfigError(key, f"cannot read the RFID table {path}: {exc.strerror or exc}", file) from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(key, f"{path} is not valid TOML: {exc}", file) from exc
    try:
        return LikelihoodTable.from_dict(data)
    except ValueError as exc:
        raise ConfigError(key, f"{path} is not an RFID likelihood table: {exc}", file) from exc


@dataclass(frozen=True)
class FleetConfig:
    """``[fleet]``: the Unix socket the agent serves its bridge on (``agent.runtime.fleet_loop``; None: no
    fleet), how often this robot's pose goes to it, and how often its status. No network socket: the
    bridge process (``vlp-agent bridge``) holds those."""

    socket: Path | None = None
    pose_rate_hz: float = 10.0
    status_period_s: float = 1.0
    peer_timeout_s: float = 2.0  # another robot with no pose for this long is dropped (no longer an obstacle)
    peer_radius_m: float = 0.0  # the other robots' footprint radius; 0: this robot's [navigation] radius_m


# A Unix socket path is at most 107 bytes (sun_path) on Linux.
MAX_SOCKET_PATH = 107


@dataclass(frozen=True)
class AgentConfig:
    file: str
    devices: Mapping[DeviceKind, DeviceConfig]
    sim: SimConfig | None = None
    vlp: VlpConfig = VlpConfig()
    slam: SlamConfig = SlamConfig()  # noqa: RUF009 (frozen, agent.config_slam)
    fusion: FusionConfig = FusionConfig()
    output: OutputConfig = OutputConfig()
    control: ControlConfig = ControlConfig()
    health: HealthConfig = HealthConfig()
    record: RecordConfig = RecordConfig()
    scheduling: SchedulingConfig = SchedulingConfig()
    navigation: NavConfig = field(default_factory=NavConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    exploration: ExploreConfig = field(default_factory=ExploreConfig)
    forward_camera: DeviceConfig | None = None
    following: FollowingConfig = field(default_factory=FollowingConfig)
    fleet: FleetConfig = field(default_factory=FleetConfig)
    forward_view: ForwardViewConfig | None = None  # [camera.forward]'s mount and lens (None: no such camera)

    def replace(self, **changes: Any) -> AgentConfig:
        return dataclasses.replace(self, **changes)


# -- entry points --------------------------------------------------------------------------------------
def load_config(path: str | os.PathLike[str]) -> AgentConfig:
    """Read and check a config file. Raises ConfigError (with the file and the key) on any mistake."""
    file = os.fspath(path)
    return parse_config(read_toml(file), file)


def parse_config(data: Mapping[str, Any] | str, file: str = "<config>") -> AgentConfig:
    """Build a config from TOML text or a parsed table; relative paths are taken from ``file``'s folder."""
    if isinstance(data, str):
        try:
            data = tomllib.loads(data)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError("", f"not valid TOML: {exc}", file) from exc
    return _Reader(dict(data), file).read()


# -- reading tables ------------------------------------------------------------------------------------
class _Table(TomlTable):
    """One table of a config file (see :class:`drivers.toml_table.TomlTable`) with the config's getters."""

    # typed getters ---------------------------------------------------------------------------------
    def number(
        self, name: str, default: float, check: tuple[typing.Callable[[float], bool], str] | None = None
    ) -> float:
        if not self.has(name):
            return default
        value = self.take(name)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise self.error(name, f"must be a number, not {type_name(value)}")
        number = float(value)
        if not math.isfinite(number):
            raise self.error(name, f"must be finite, got {value}")
        if check is not None and not check[0](number):
            raise self.error(name, f"{check[1]}, got {value}")
        return number

    def angle(self, name: str, default: float, limit_rad: float | None = None) -> float:
        """``<name>_rad`` or ``<name>_deg`` (not both); ``name`` is given without the suffix."""
        rad, deg = f"{name}_rad", f"{name}_deg"
        self.known.update((rad, deg))
        if rad in self.data and deg in self.data:
            raise self.error(deg, f"give {rad} or {deg}, not both")
        if deg in self.data:
            value = math.radians(self.number(deg, 0.0))
            key = deg
        else:
            value = self.number(rad, default)
            key = rad
        if limit_rad is not None and not abs(value) <= limit_rad:
            raise self.error(key, f"must be within +-{math.degrees(limit_rad):g} degrees")
        return value

    def integer(
        self, name: str, default: int, check: tuple[typing.Callable[[int], bool], str] | None = None
    ) -> int:
        if not self.has(name):
            return default
        value = self.take(name)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(name, f"must be an integer, not {type_name(value)}")
        if check is not None and not check[0](value):
            raise self.error(name, f"{check[1]}, got {value}")
        return value

    def string(self, name: str, default: str | None = None) -> str | None:
        if not self.has(name):
            return default
        value = self.take(name)
        if not isinstance(value, str):
            raise self.error(name, f"must be a string, not {type_name(value)}")
        if not value.strip():
            raise self.error(name, "must not be empty")
        return value

    def required_string(self, name: str, what: str) -> str:
        value = self.string(name)
        if value is None:
            raise self.error(name, f"missing ({what})")
        return value

    def choice(self, name: str, default: str, choices: typing.Iterable[str]) -> str:
        options = list(choices)
        value = self.string(name, default)
        assert value is not None
        if value not in options:
            close = difflib.get_close_matches(value, options, n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise self.error(name, f"must be one of {options}, got {value!r}{hint}")
        return value

    def numbers(self, name: str, n: int) -> tuple[float, ...] | None:
        if not self.has(name):
            return None
        value = self.take(name)
        if not isinstance(value, list) or len(value) != n:
            raise self.error(name, f"must be an array of {n} numbers, not {type_name(value)}")
        out = []
        for i, v in enumerate(value):
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(float(v)):
                raise ConfigError(f"{self.key(name)}[{i}]", f"must be a finite number, got {v!r}", self.file)
            out.append(float(v))
        return tuple(out)

    def table(self, name: str) -> _Table | None:
        if not self.has(name):
            return None
        value = self.take(name)
        if not isinstance(value, dict):
            raise self.error(name, f"must be a table ([{self.key(name)}]), not {type_name(value)}")
        return _Table(value, self.key(name), self.file)

    def tables(self, name: str) -> list[_Table] | None:
        if not self.has(name):
            return None
        value = self.take(name)
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise self.error(
                name, f"must be an array of tables ([[{self.key(name)}]]), not {type_name(value)}"
            )
        return [_Table(v, f"{self.key(name)}[{i}]", self.file) for i, v in enumerate(value)]

    def path_value(self, name: str, base: Path) -> Path | None:
        text = self.string(name)
        if text is None:
            return None
        path = Path(os.path.expandvars(os.path.expanduser(text)))
        return path if path.is_absolute() else base / path


_POSITIVE = (lambda v: v > 0, "must be > 0")
_NON_NEGATIVE = (lambda v: v >= 0, "must be >= 0")
_UNIT_INTERVAL = (lambda v: 0 <= v <= 1, "must be in [0, 1]")
_SURVEY_SIGMA = (lambda v: 0 <= v <= 1.0, "must be in [0, 1] m")
_PROBABILITY = (lambda v: 0 < v < 1, "must be strictly between 0 and 1")
_BYTE = (lambda v: 0 <= v <= 255, "must be 0..255")


# -- device options from driver signatures -------------------------------------------------------------
@dataclass(frozen=True)
class _Option:
    name: str
    accepts: tuple[type, ...]  # int, float, str, bool, tuple (of ints), an Enum subclass
    required: bool

    def describe(self) -> str:
        names = {
            int: "an integer",
            float: "a number",
            str: "a string",
            bool: "true or false",
            tuple: "an array of integers",
        }
        parts = []
        for t in self.accepts:
            if isinstance(t, type) and issubclass(t, enum.Enum):
                parts.append(f"one of {[m.value for m in t]}")
            else:
                parts.append(names.get(t, t.__name__))
        return " or ".join(dict.fromkeys(parts))


def _accepted_types(hint: Any) -> tuple[type, ...] | None:
    """What TOML values an annotation takes; None when a config file cannot express it."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        out: list[type] = []
        for arg in typing.get_args(hint):
            if arg is type(None):
                continue
            sub = _accepted_types(arg)
            if sub is None:
                return None
            out.extend(sub)
        return tuple(out) or None
    if origin is tuple:
        args = typing.get_args(hint)
        return (tuple,) if args and all(a in (int, Ellipsis) for a in args) else None
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return (hint,)
    if hint in (int, float, str, bool):
        return (hint,)
    return None


def backend_options(kind: DeviceKind, backend: str, cls: Any = None) -> dict[str, _Option]:
    """The options a device table may give for ``backend``, from its class's ``__init__`` signature
    (``cls``: that class, when it is not the registry's for ``kind``, as the forward camera's)."""
    cls = backend_class(kind, backend) if cls is None else cls
    signature = inspect.signature(cls.__init__)
    hints = typing.get_type_hints(cls.__init__)
    options: dict[str, _Option] = {}
    for name, param in signature.parameters.items():
        if name in _NOT_OPTIONS or param.kind in (param.VAR_POSITIONAL, param.VAR_KEYWORD):
            continue
        if kind is DeviceKind.RFID and name == "protocol":
            continue  # the backend name is the protocol
        accepts = _accepted_types(hints.get(name, Any))
        if accepts is None:
            continue
        options[name] = _Option(name, accepts, param.default is inspect.Parameter.empty)
    return options


def _convert_option(option: _Option, value: Any, table: _Table) -> Any:
    key = option.name
    for t in option.accepts:
        if t is bool:
            if isinstance(value, bool):
                return value
        elif t is int:
            if isinstance(value, int) and not isinstance(value, bool):
                return value
        elif t is float:
            if isinstance(value, int | float) and not isinstance(value, bool):
                if not math.isfinite(float(value)):
                    raise table.error(key, f"must be finite, got {value}")
                return float(value)
        elif t is str:
            if isinstance(value, str):
                if not value.strip():
                    raise table.error(key, "must not be empty")
                return value
        elif t is tuple:
            if isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in value):
                return tuple(value)
        elif issubclass(t, enum.Enum) and isinstance(value, str):
            try:
                return t(value)
            except ValueError:
                continue
    raise table.error(key, f"must be {option.describe()}, not {type_name(value)} ({value!r})")


def _check_option_size(name: str, value: Any, table: _Table) -> Any:
    if name in _OPTION_RANGES and isinstance(value, int) and not isinstance(value, bool):
        low, high, why = _OPTION_RANGES[name]
        if not low <= value <= high:
            raise table.error(name, f"must be {low}..{high} ({why}), got {value}")
    if name in _OPTION_LENGTHS and isinstance(value, tuple) and len(value) > _OPTION_LENGTHS[name]:
        raise table.error(name, f"has {len(value)} entries, more than the limit of {_OPTION_LENGTHS[name]}")
    return value


def _image_side(value: int) -> bool:
    return 0 < value <= MAX_IMAGE_SIDE_PX


_IMAGE_SIDE = (_image_side, f"must be 1..{MAX_IMAGE_SIDE_PX} px (the limit on an image side)")
_SENSOR_SIDE = (
    lambda v: 0 <= v <= MAX_IMAGE_SIDE_PX,
    f"must be 0..{MAX_IMAGE_SIDE_PX} px (0: frames are full resolution; the limit on an image side)",
)


# -- external files ------------------------------------------------------------------------------------
def _check_saved_map(t: _Table, saved: Path, resolution_m: float | None) -> None:
    """The map ``[slam] map`` names loads (both files, whole), and, when the map is to be continued
    (``resolution_m`` given), has the cell size the filter will map at: a start fails here, naming the key
    and what is wrong, rather than running without SLAM."""
    from agent.slam.mapio import load_map

    if not saved.is_file():
        raise t.error("map", f"no such map file: {saved}")
    try:
        image = load_map(saved)
    except ConfigError as exc:
        raise t.error("map", f"the saved map {saved} does not load: {exc}") from exc
    if resolution_m is not None and not math.isclose(image.resolution_m, resolution_m, rel_tol=1e-6):
        raise t.error(
            "map",
            f"the saved map {saved} has {image.resolution_m:g} m cells, [slam] resolution_m is "
            f"{resolution_m:g} m: continue a map at the resolution it was made with",
        )


def read_camera_info(path: Path, key: str, file: str) -> IntrinsicsConfig:
    """Width, height, camera matrix and distortion from a ROS ``camera_info`` YAML file.

    ``t_row_s`` is not in camera_info: it is set to 0 here and must come from the config."""
    import cv2

    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(key, f"cannot read camera_info {path}: {exc}", file) from exc
    # OpenCV's YAML reader wants its directive; ROS writes plain YAML 1.1 without one.
    body = text if text.lstrip().startswith("%YAML") else "%YAML:1.0\n---\n" + text
    try:
        storage = cv2.FileStorage(body, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:
        raise ConfigError(key, f"{path} is not a camera_info YAML file: {exc}", file) from exc

    def numbers(name: str, n: int) -> list[float]:
        node = storage.getNode(name)
        data = node.getNode("data") if not node.empty() else node
        if node.empty() or data.empty() or data.size() != n:
            raise ConfigError(key, f"{path}: {name}.data must hold {n} numbers", file)
        return finite(name, [float(data.at(i).real()) for i in range(n)])

    def finite(name: str, values: list[float]) -> list[float]:
        for i, v in enumerate(values):
            if not math.isfinite(v):
                raise ConfigError(key, f"{path}: {name}.data[{i}] must be finite, got {v}", file)
        return values

    def integer(name: str) -> int:
        node = storage.getNode(name)
        if node.empty() or not node.isInt() or not _image_side(int(node.real())):
            raise ConfigError(key, f"{path}: {name} must be an integer 1..{MAX_IMAGE_SIDE_PX}", file)
        return int(node.real())

    width, height = integer("image_width"), integer("image_height")
    k = numbers("camera_matrix", 9)
    dist_node = storage.getNode("distortion_coefficients")
    dist: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    if not dist_node.empty():
        data = dist_node.getNode("data")
        if not data.empty() and data.size() > 5:
            raise ConfigError(key, f"{path}: distortion_coefficients must hold 5 numbers (plumb_bob)", file)
        values = [float(data.at(i).real()) for i in range(data.size())] if not data.empty() else []
        finite("distortion_coefficients", values)
        if len(values) not in (0, 4, 5):
            raise ConfigError(key, f"{path}: distortion_coefficients must hold 5 numbers (plumb_bob)", file)
        values += [0.0] * (5 - len(values))
        dist = (values[0], values[1], values[2], values[3], values[4])
    model = storage.getNode("distortion_model")
    if not model.empty() and model.string() not in ("plumb_bob", "rational_polynomial", ""):
        raise ConfigError(
            key, f"{path}: distortion_model {model.string()!r} is not supported (plumb_bob)", file
        )
    if not (k[0] > 0 and k[4] > 0):
        raise ConfigError(key, f"{path}: camera_matrix has non-positive focal lengths {k[0]}, {k[4]}", file)
    return IntrinsicsConfig(width, height, k[0], k[4], k[2], k[5], 0.0, distortion=dist, source=str(path))


def _led(t: _Table) -> LedConfig:
    led_id = t.string("id")
    if led_id is None:
        value = t.data.get("id")
        if isinstance(value, int) and not isinstance(value, bool):
            t.take("id")
            led_id = str(value)
        else:
            raise t.error("id", "missing (a string naming the LED's signature)")
    led = LedConfig(
        led_id,
        t.number("x_m", math.nan),
        t.number("y_m", math.nan),
        t.number("z_m", math.nan),
        t.number("frequency_hz", math.nan, _POSITIVE),
        t.number("duty", math.nan, _PROBABILITY),
        t.number("diameter_m", 0.086, _POSITIVE),
    )
    if t.has("survey_sigma_m"):
        sigma = t.number("survey_sigma_m", math.nan, _SURVEY_SIGMA)
        led = dataclasses.replace(led, survey_sigma_m=sigma)
    for name in ("x_m", "y_m", "z_m", "frequency_hz", "duty"):
        if math.isnan(getattr(led, name)):
            raise t.error(name, "missing (every LED needs id, x_m, y_m, z_m, frequency_hz and duty)")
    t.finish()
    return led


def _leds(tables: list[_Table], key: str, file: str) -> tuple[LedConfig, ...]:
    if len(tables) > MAX_MAP_LEDS:
        raise ConfigError(key, f"has {len(tables)} LEDs, more than the limit of {MAX_MAP_LEDS}", file)
    leds = tuple(_led(t) for t in tables)
    if not leds:
        raise ConfigError(key, "the LED map is empty", file)
    signatures: dict[str, tuple[float, float]] = {}
    for i, led in enumerate(leds):
        known = signatures.setdefault(led.id, (led.frequency_hz, led.duty))
        if known != (led.frequency_hz, led.duty):
            raise ConfigError(
                f"{key}[{i}]",
                f"LED id {led.id!r} appears with two signatures: {known} and {(led.frequency_hz, led.duty)}",
                file,
            )
    return leds


def read_led_map(path: Path, key: str, file: str) -> tuple[LedConfig, ...]:
    """A surveyed LED map: TOML with ``[[leds]]`` tables (id, x_m, y_m, z_m, frequency_hz, duty,
    diameter_m, survey_sigma_m). Errors name the map file and the LED."""
    try:
        with open(path, "rb") as fp:
            data = tomllib.load(fp)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("", f"not valid TOML: {exc}", str(path)) from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(key, f"cannot read the LED map {path}: {exc}", file) from exc
    top = _Table(data, "", str(path))
    tables = top.tables("leds")
    if tables is None:
        raise ConfigError("leds", "missing: an LED map is an array of [[leds]] tables", str(path))
    leds = _leds(tables, "leds", str(path))
    top.finish()
    return leds


# -- the reader ----------------------------------------------------------------------------------------
class _Reader:
    def __init__(self, data: dict[str, Any], file: str) -> None:
        self.top = _Table(data, "", file)
        self.file = file
        self.base = Path(file).resolve().parent if not file.startswith("<") else Path.cwd()

    def read(self) -> AgentConfig:
        top = self.top
        top.known.update(_SECTIONS)
        sim = self._sim()
        forward, forward_view = self._forward_camera(sim)
        devices: dict[DeviceKind, DeviceConfig] = {}
        for kind in DeviceKind:
            device = self._device(kind, sim)
            if device is not None:
                devices[kind] = device
        vlp = self._vlp(sim, DeviceKind.CAMERA in devices)
        slam = self._slam(DeviceKind.LASER in devices)
        fusion = self._fusion()
        output = self._output(sim)
        control = self._control()
        health = self._health()
        record = self._record()
        recorder = self._recorder()
        scheduling = self._scheduling()
        navigation = self._navigation()
        exploration = self._exploration()
        following = self._following()
        fleet = self._fleet()
        top.finish()
        if not (DeviceKind.SERVOS in devices or (DeviceKind.CAMERA in devices and vlp.enabled)):
            raise ConfigError(
                "", "no pose source: configure [servos] (wheel odometry) or [camera] with [vlp]", self.file
            )
        return AgentConfig(
            self.file,
            devices,
            sim,
            vlp,
            slam,
            fusion,
            output,
            control,
            health,
            record,
            scheduling,
            navigation,
            recorder,
            exploration,
            forward,
            following,
            fleet,
            forward_view,
        )

    # [sim] ---------------------------------------------------------------------------------------
    def _sim(self) -> SimConfig | None:
        t = self.top.table("sim")
        if t is None:
            return None
        world = t.path_value("world", self.base)
        if world is None:
            raise t.error("world", "missing (the world file the simulated robot lives in, docs/world.md)")
        if not world.is_file():
            raise t.error("world", f"no such world file: {world}")
        seed = t.integer("seed", 0, _NON_NEGATIVE)
        priority = t.integer(
            "device_priority",
            SimConfig.device_priority,
            (
                lambda v: 0 <= v <= MAX_REALTIME_PRIORITY,
                f"must be 0..{MAX_REALTIME_PRIORITY} (0: the fake devices' threads time-shared)",
            ),
        )
        t.finish()
        from drivers.sim.worldfile import load_world

        return SimConfig(world, load_world(world), seed, priority)

    # devices -------------------------------------------------------------------------------------
    def _device(self, kind: DeviceKind, sim: SimConfig | None) -> DeviceConfig | None:
        t = self.top.table(kind.value)
        if t is None:
            if sim is None:
                return None
            t = _Table({}, kind.value, self.file)
        if not t.boolean("enabled", True):
            return None  # the other keys of a disabled device are kept for later, not checked
        simulated = _sim_backend(kind, sim.world) if sim is not None else None
        if t.has("backend"):
            backend = t.choice("backend", "", BACKENDS[kind])
        elif simulated is not None:
            backend = simulated
        else:
            raise t.error("backend", f"missing (one of {sorted(BACKENDS[kind])})")
        if simulated is not None and backend != simulated:
            raise t.error("backend", f"the simulated robot's {kind.value} is backend = {simulated!r}")
        critical = t.boolean("critical", kind in _CRITICAL)
        try:
            known = backend_options(kind, backend)
        except BackendUnavailable as exc:
            raise t.error("backend", str(exc)) from exc
        options: dict[str, Any] = {}
        location = SIM_LOCATION_KEYS[kind] if sim is not None else ()
        world_keys = _SIM_WORLD_KEYS.get(kind, ()) if sim is not None else ()
        settings: dict[str, Any] = {}
        t.known.update(known)
        if kind is DeviceKind.CAMERA:
            t.known.update(CAMERA_SETTINGS)
        for name in list(t.data):
            if name in ("backend", "enabled", "critical"):
                continue
            if kind is DeviceKind.CAMERA and name in CAMERA_SETTINGS:
                settings[name] = t.take(name)
                continue
            if name not in known:
                continue  # finish() reports it, with a suggestion
            if name in location:
                raise t.error(name, "is set by the simulated robot ([sim]); remove it")
            if name in world_keys:
                raise t.error(name, "comes from the world file under [sim]; set it there ([robot])")
            options[name] = _check_option_size(name, _convert_option(known[name], t.take(name), t), t)
        t.finish()
        for name, option in known.items():
            if option.required and name not in options and name not in location:
                raise t.error(name, f"missing ({option.describe()}; required by the {backend!r} backend)")
        if settings:
            options["settings"] = self._camera_settings(settings, t)
        return DeviceConfig(kind, backend, options, critical)

    def _forward_camera(self, sim: SimConfig | None) -> tuple[DeviceConfig | None, ForwardViewConfig | None]:
        """``[camera.forward]``, taken out of ``[camera]`` before that is read as the ceiling camera (which
        it leaves out when it held nothing else), and its mount and lens. Not critical by default: the robot
        localizes without it."""
        camera = self.top.data.get("camera")
        if not isinstance(camera, dict) or "forward" not in camera:
            return None, None
        camera = dict(camera)  # the caller's table stays as it was
        value = camera.pop("forward")
        top = self.top.data
        assert isinstance(top, dict)  # _Reader made it one
        if not camera and sim is None:
            del top["camera"]
        else:
            top["camera"] = camera
        if not isinstance(value, dict):
            raise ConfigError("camera.forward", f"must be a table, not {type_name(value)}", self.file)
        t = _Table(value, "camera.forward", self.file)
        if not t.boolean("enabled", True):
            return None, None
        if t.has("backend"):
            backend = t.choice("backend", "", FORWARD_CAMERA_BACKENDS)
        elif sim is not None:
            backend = "sim"
        else:
            raise t.error("backend", f"missing (one of {sorted(FORWARD_CAMERA_BACKENDS)})")
        if sim is not None and backend != "sim":
            raise t.error("backend", "the simulated robot's forward camera is backend = 'sim'")
        if sim is None and backend == "sim":
            raise t.error("backend", "'sim' needs the simulated robot ([sim])")
        critical = t.boolean("critical", False)
        try:
            known = backend_options(DeviceKind.CAMERA, backend, forward_camera_class(backend))
        except BackendUnavailable as exc:
            raise t.error("backend", str(exc)) from exc
        t.known.update(known)
        t.known.update(CAMERA_SETTINGS)
        view = self._forward_view(t, sim)
        options: dict[str, Any] = {}
        settings: dict[str, Any] = {"pixel_format": "BGR8"}
        for name in list(t.data):
            if name in ("backend", "enabled", "critical"):
                continue
            if name in CAMERA_SETTINGS:
                settings[name] = t.take(name)
            elif name in known:
                options[name] = _check_option_size(name, _convert_option(known[name], t.take(name), t), t)
        t.finish()
        for name, option in known.items():
            if option.required and name not in options:
                raise t.error(name, f"missing ({option.describe()}; required by the {backend!r} backend)")
        if backend == "fake":
            image = Path(os.path.expandvars(os.path.expanduser(options["image"])))
            image = image if image.is_absolute() else self.base / image
            if not image.is_file():
                raise t.error("image", f"no such image file: {image}")
            options["image"] = str(image)
        options["settings"] = self._camera_settings(settings, t)
        width, height = settings.get("width"), settings.get("height")
        if view.camera_info is not None:
            pass  # the calibration's own size; frames of another size scale it
        elif isinstance(width, int) and isinstance(height, int):
            for key, v, side in (("cx_px", view.cx_px, width), ("cy_px", view.cy_px, height)):
                if v is not None and not 0.0 <= v <= side:
                    raise t.error(key, f"must be inside the {width}x{height} image, got {v:g}")
            view = dataclasses.replace(view, width_px=width, height_px=height)
        elif view.cx_px is not None or view.cy_px is not None:
            raise t.error("cx_px", "a principal point needs the image size it is for: give width and height")
        return DeviceConfig(DeviceKind.CAMERA, backend, options, critical), view

    _FORWARD_LENS = ("hfov_deg", "hfov_rad", "fx_px", "fy_px", "cx_px", "cy_px")

    def _forward_view(self, t: _Table, sim: SimConfig | None) -> ForwardViewConfig:
        """``[camera.forward.mount]`` and the lens keys; under ``[sim]`` the world's ``[forward_camera]``
        sets them (the renderer draws with those), so the config may not."""
        given = [k for k in ("mount", "camera_info", *self._FORWARD_LENS) if t.has(k)]
        if sim is not None:
            if given:
                raise t.error(
                    given[0], "comes from the world file under [sim] ([forward_camera] in docs/world.md)"
                )
            return ForwardViewConfig()
        d = ForwardViewConfig()
        mount = d.mount
        m = t.table("mount")
        if m is not None:
            mount = MountConfig(
                m.number("x_m", d.mount.x_m),
                m.number("y_m", d.mount.y_m),
                m.number("z_m", d.mount.z_m, (lambda v: 0.0 < v <= 3.0, "must be 0..3 m above the floor")),
                m.angle("yaw", 0.0, math.pi),
                0.0,
                m.angle("pitch", 0.0, math.radians(45.0)),
            )
            m.finish()
        t.known.update(self._FORWARD_LENS)
        t.known.add("camera_info")
        if t.has("camera_info"):
            lens = [k for k in self._FORWARD_LENS if t.has(k)]
            if lens:
                raise t.error(lens[0], "give camera_info (the calibrated lens) or the lens keys, not both")
            path = t.path_value("camera_info", self.base)
            assert path is not None
            info = read_camera_info(path, t.key("camera_info"), self.file)
            return ForwardViewConfig(
                mount,
                None,
                info.fx_px,
                info.fy_px,
                info.cx_px,
                info.cy_px,
                info.width_px,
                info.height_px,
                info.distortion,
                str(path),
            )
        hfov = None
        if t.has("hfov_deg") or t.has("hfov_rad"):
            hfov = t.angle("hfov", 0.0)
            if not math.radians(10.0) <= hfov <= math.radians(170.0):
                raise t.error(
                    "hfov_deg" if t.has("hfov_deg") else "hfov_rad",
                    f"must be 10..170 degrees (the horizontal field of view), got {math.degrees(hfov):g}",
                )
        fx = t.number("fx_px", 0.0, _POSITIVE) if t.has("fx_px") else None
        fy = t.number("fy_px", 0.0, _POSITIVE) if t.has("fy_px") else None
        if hfov is not None and fx is not None:
            raise t.error("fx_px", "give the field of view (hfov_deg) or the focal length (fx_px), not both")
        if fy is not None and fx is None:
            raise t.error("fy_px", "needs fx_px")
        cx = t.number("cx_px", 0.0) if t.has("cx_px") else None
        cy = t.number("cy_px", 0.0) if t.has("cy_px") else None
        return ForwardViewConfig(mount, hfov, fx, fy, cx, cy)

    def _following(self) -> FollowingConfig:
        t = self.top.table("following") or _Table({}, "following", self.file)
        d = FollowingConfig()
        tag_id = t.string("tag_id")
        path = t.path_value("rfid_table", self.base)
        table = read_rfid_table(path, t.key("rfid_table"), self.file) if path is not None else None
        yaws = d.antenna_yaws_rad
        if t.has("antenna_yaws_rad") or t.has("antenna_yaws_deg"):
            name = "antenna_yaws_rad" if t.has("antenna_yaws_rad") else "antenna_yaws_deg"
            scale = 1.0 if name.endswith("_rad") else math.pi / 180.0
            value = t.take(name)
            if (
                not isinstance(value, list)
                or not 1 <= len(value) <= 15
                or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            ):
                raise t.error(
                    name, f"must be an array of 1 to 15 numbers (one per antenna port), not {value!r}"
                )
            yaws = tuple(float(v) * scale for v in value)
        t.known.update({"antenna_yaws_rad", "antenna_yaws_deg"})
        following = FollowingConfig(
            tag_id=tag_id,
            rfid_table=path,
            table=table,
            antenna_yaws_rad=yaws,
            cycle_s=t.number("cycle_s", d.cycle_s, (lambda v: 0.05 <= v <= 5.0, "must be 0.05..5 s")),
            distance_m=t.number("distance_m", d.distance_m, (lambda v: 0.3 <= v <= 4.0, "must be 0.3..4 m")),
            min_gap_m=t.number("min_gap_m", d.min_gap_m, (lambda v: 0.2 <= v <= 4.0, "must be 0.2..4 m")),
            max_speed_mps=t.number(
                "max_speed_mps", d.max_speed_mps, (lambda v: 0.0 < v <= 3.0, "must be > 0 and <= 3 m/s")
            ),
            lost_after_s=t.number(
                "lost_after_s", d.lost_after_s, (lambda v: 0.1 <= v <= 10.0, "must be 0.1..10 s")
            ),
            search_after_s=t.number(
                "search_after_s", d.search_after_s, (lambda v: 0.0 <= v <= 60.0, "must be 0..60 s")
            ),
        )
        if following.min_gap_m >= following.distance_m:
            raise t.error("min_gap_m", f"must be below distance_m ({following.distance_m} m)")
        t.finish()
        return following

    def _camera_settings(self, values: dict[str, Any], t: _Table) -> Any:
        from drivers.camera.base import CameraSettings

        converted: dict[str, Any] = {}
        for name, value in values.items():
            if name == "pixel_format":
                if not isinstance(value, str):
                    raise t.error(name, f"must be a string, not {type_name(value)}")
                converted[name] = value
            elif name in ("width", "height"):
                if isinstance(value, bool) or not isinstance(value, int):
                    raise t.error(name, f"must be an integer, not {type_name(value)}")
                if value > MAX_IMAGE_SIDE_PX:
                    raise t.error(
                        name,
                        f"must be at most {MAX_IMAGE_SIDE_PX} px (the limit on an image side), got {value}",
                    )
                converted[name] = value
            else:
                if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
                    raise t.error(name, f"must be a finite number, not {value!r}")
                converted[name] = float(value)
        settings = CameraSettings(**converted)
        try:
            settings.validate(t.path)
        except ConfigError as exc:
            raise ConfigError(exc.key, exc.reason, self.file) from exc
        return settings

    # [vlp] ---------------------------------------------------------------------------------------
    def _mount(self, t: _Table | None, default_z_m: float) -> MountConfig | None:
        if t is None:
            return None
        tilt_limit = math.radians(20.0)
        mount = MountConfig(
            t.number("x_m", 0.0),
            t.number("y_m", 0.0),
            t.number("z_m", default_z_m),
            t.angle("yaw", 0.0, math.pi),
            t.angle("roll", 0.0, tilt_limit),
            t.angle("pitch", 0.0, tilt_limit),
        )
        t.finish()
        return mount

    def _vlp(self, sim: SimConfig | None, has_camera: bool) -> VlpConfig:
        t = self.top.table("vlp") or _Table({}, "vlp", self.file)
        enabled = t.boolean("enabled", has_camera)
        if enabled and not has_camera:
            raise t.error("enabled", "VLP needs a [camera]")
        intrinsics = self._intrinsics(t)
        leds: tuple[LedConfig, ...] | None = None
        map_path = t.path_value("led_map", self.base)
        inline = t.tables("leds")
        if map_path is not None and inline is not None:
            raise t.error("leds", "give led_map (a file) or [[vlp.leds]], not both")
        if map_path is not None:
            leds = read_led_map(map_path, t.key("led_map"), self.file)
        elif inline is not None:
            leds = _leds(inline, t.key("leds"), self.file)
        mount = self._mount(t.table("mount"), 0.2)
        calibration_path = t.path_value("calibration", self.base)
        calibration: str | None = None
        if calibration_path is not None:
            calibration = self._calibration(calibration_path, t.key("calibration"))
        d = VlpConfig()
        floor_m = t.number("sigma_floor_m", d.sigma_floor_m, _NON_NEGATIVE)
        floor_yaw = t.angle("sigma_floor_yaw", d.sigma_floor_yaw_rad)
        if floor_yaw < 0:
            raise t.error("sigma_floor_yaw_rad", "must be >= 0")
        alert_limit = t.number("alert_limit_m", d.alert_limit_m, _POSITIVE)
        sigma_scale = t.number(
            "guarded_sigma_scale", d.guarded_sigma_scale, (lambda v: v == 0 or v >= 1, "must be 0 or >= 1")
        )
        fuse_degraded = t.boolean("fuse_degraded", d.fuse_degraded)
        t.finish()
        if enabled and sim is None:
            if intrinsics is None:
                raise t.error(
                    "camera_info",
                    'missing: the camera\'s calibration (camera_info = "file.yaml" '
                    "or a [vlp.intrinsics] table)",
                )
            if leds is None:
                raise t.error(
                    "led_map", 'missing: the surveyed LED map (led_map = "file.toml" or [[vlp.leds]])'
                )
        return VlpConfig(
            enabled,
            intrinsics,
            leds,
            mount,
            calibration,
            str(calibration_path) if calibration_path else None,
            floor_m,
            floor_yaw,
            alert_limit,
            sigma_scale,
            fuse_degraded,
        )

    def _calibration(self, path: Path, key: str) -> str:
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ConfigError(key, f"cannot read the VLP calibration {path}: {exc}", self.file) from exc
        try:
            from agent.vlp.calibration import parse_calibration
        except ImportError as exc:  # the VLP package is not installed or broken
            raise ConfigError(key, f"cannot check the VLP calibration: {exc}", self.file) from exc
        parse_calibration(text, str(path))  # raises ConfigError naming that file and its key
        return text

    def _intrinsics(self, t: _Table) -> IntrinsicsConfig | None:
        info_path = t.path_value("camera_info", self.base)
        inline = t.table("intrinsics")
        if info_path is not None and inline is not None:
            raise t.error("intrinsics", "give camera_info (a file) or [vlp.intrinsics], not both")
        rolling = t.table("rolling_shutter")
        if info_path is None and inline is None:
            if rolling is not None:
                raise t.error("rolling_shutter", "needs camera_info or [vlp.intrinsics] beside it")
            return None
        if info_path is not None:
            base = read_camera_info(info_path, t.key("camera_info"), self.file)
        else:
            assert inline is not None
            dist = inline.numbers("distortion", 5) or (0.0, 0.0, 0.0, 0.0, 0.0)
            base = IntrinsicsConfig(
                inline.integer("width_px", 0, _IMAGE_SIDE),
                inline.integer("height_px", 0, _IMAGE_SIDE),
                inline.number("fx_px", 0.0, _POSITIVE),
                inline.number("fy_px", 0.0, _POSITIVE),
                inline.number("cx_px", math.nan),
                inline.number("cy_px", math.nan),
                0.0,
                distortion=(dist[0], dist[1], dist[2], dist[3], dist[4]),
                source=inline.path,
            )
            for name in ("width_px", "height_px", "fx_px", "fy_px", "cx_px", "cy_px"):
                value = getattr(base, name)
                if value == 0 or (isinstance(value, float) and math.isnan(value)):
                    raise inline.error(name, "missing (width_px, height_px, fx_px, fy_px, cx_px, cy_px)")
            inline.finish()
        r = rolling or _Table({}, t.key("rolling_shutter"), self.file)
        if not r.has("t_row_s"):
            raise r.error("t_row_s", "missing: the sensor's row time (the stripes' clock)")
        t_row_s = r.number("t_row_s", 0.0, _POSITIVE)
        exposure_s = r.number("exposure_s", 20e-6, _POSITIVE)
        sensor_w = r.integer("sensor_width_px", 0, _SENSOR_SIDE)
        sensor_h = r.integer("sensor_height_px", 0, _SENSOR_SIDE)
        if (sensor_w == 0) != (sensor_h == 0):
            raise r.error("sensor_height_px", "give both sensor_width_px and sensor_height_px, or neither")
        if sensor_w and (sensor_w < base.width_px or sensor_h < base.height_px):
            raise r.error(
                "sensor_width_px",
                f"the sensor ({sensor_w}x{sensor_h}) is smaller than the frames "
                f"({base.width_px}x{base.height_px})",
            )
        r.finish()
        return dataclasses.replace(
            base, t_row_s=t_row_s, exposure_s=exposure_s, sensor_width_px=sensor_w, sensor_height_px=sensor_h
        )

    # [slam] --------------------------------------------------------------------------------------
    def _slam(self, has_laser: bool) -> SlamConfig:
        t = self.top.table("slam") or _Table({}, "slam", self.file)
        enabled = t.boolean("enabled", has_laser)
        if enabled and not has_laser:
            raise t.error("enabled", "SLAM needs a [laser]")
        d = SlamConfig()
        mode = SlamMode(t.choice("mode", d.mode.value, [m.value for m in SlamMode]))
        saved = t.path_value("map", self.base)
        resolution_m = t.number(
            "resolution_m", d.resolution_m, (lambda v: 0.01 <= v <= 0.5, "must be 0.01..0.5")
        )
        if mode is not SlamMode.MAPPING and enabled:
            if saved is None:
                raise t.error(
                    "map", f"missing: mode = {mode.value!r} needs the saved map (a map_server .yaml)"
                )
            _check_saved_map(t, saved, resolution_m if mode is SlamMode.CONTINUE else None)
        elif saved is not None and mode is SlamMode.MAPPING:
            raise t.error("map", 'only used with mode = "localization" or "continue"')
        slam = SlamConfig(
            enabled=enabled,
            mode=mode,
            map=saved,
            particles=t.integer("particles", d.particles, (lambda v: 1 <= v <= 1000, "must be 1..1000")),
            map_mode=t.choice("map_mode", d.map_mode, ("per_particle", "shared")),
            resolution_m=resolution_m,
            linear_update_m=t.number("linear_update_m", d.linear_update_m, _POSITIVE),
            angular_update_rad=t.angle("angular_update", d.angular_update_rad),
            laser_mount=self._mount(t.table("laser_mount"), 0.18),
            queue_size=t.integer("queue_size", d.queue_size, (lambda v: 1 <= v <= 64, "must be 1..64")),
            map_dir=t.path_value("map_dir", self.base),
            save_interval_s=t.number("save_interval_s", d.save_interval_s, _NON_NEGATIVE),
            sigma_xy_m=t.number("sigma_xy_m", d.sigma_xy_m, _POSITIVE),
            sigma_yaw_rad=t.angle("sigma_yaw", d.sigma_yaw_rad),
            seed=t.integer("seed", d.seed, _NON_NEGATIVE),
            process=t.boolean("process", d.process),
            along_surface_weight=t.number("along_surface_weight", d.along_surface_weight, _UNIT_INTERVAL),
            degenerate_noise_scale=t.number(
                "degenerate_noise_scale",
                d.degenerate_noise_scale,
                (lambda v: 0 < v <= 1, "must be in (0, 1]"),
            ),
            match_min_inliers=t.integer(
                "match_min_inliers", d.match_min_inliers, (lambda v: 1 <= v <= 10000, "must be 1..10000")
            ),
            match_min_inlier_fraction=t.number(
                "match_min_inlier_fraction", d.match_min_inlier_fraction, _UNIT_INTERVAL
            ),
            match_both_starts=t.boolean("match_both_starts", d.match_both_starts),
            match_gate_residual=t.boolean("match_gate_residual", d.match_gate_residual),
            normal_radius_per_m=t.number(
                "normal_radius_per_m", d.normal_radius_per_m, (lambda v: 0 <= v <= 1, "must be in [0, 1]")
            ),
            normal_thickness_m=t.number(
                "normal_thickness_m", d.normal_thickness_m, (lambda v: 0 < v <= 0.5, "must be in (0, 0.5] m")
            ),
            match_min_translation_information=t.number(
                "match_min_translation_information", d.match_min_translation_information, _NON_NEGATIVE
            ),
            match_medial_window_cells=t.integer(
                "match_medial_window_cells",
                d.match_medial_window_cells,
                (lambda v: 0 <= v <= 8, "must be in [0, 8]"),
            ),
            match_iterations=self._match_iterations(t, d.match_iterations),
            failed_match_draw=t.choice("failed_match_draw", d.failed_match_draw, ("motion", "grid")),
            miss_log_odds=t.number(
                "miss_log_odds", d.miss_log_odds, (lambda v: -2.0 <= v < 0, "must be in [-2, 0)")
            ),
            search_increment_rad=t.number(
                "search_increment_rad", d.search_increment_rad, (lambda v: v > 0, "must be > 0")
            ),
            search_yaw_rad=t.number(
                "search_yaw_rad", d.search_yaw_rad, (lambda v: 0 < v <= math.pi, "must be in (0, pi]")
            ),
            search_below_inliers=t.number("search_below_inliers", d.search_below_inliers, _UNIT_INTERVAL),
            shared_field_updates=t.integer(
                "shared_field_updates", d.shared_field_updates, (lambda v: 0 <= v <= 1000, "must be 0..1000")
            ),
            odometry_noise=self._odometry_noise(t),
            reversal_ratio=t.number("reversal_ratio", 0.5, (lambda v: 0 < v <= 1, "must be in (0, 1]"))
            if t.has("reversal_ratio")
            else None,
            loop_correction_odometry_sigmas=t.number(
                "loop_correction_odometry_sigmas", 1.0, (lambda v: 0 <= v <= 10, "must be in [0, 10]")
            )
            if t.has("loop_correction_odometry_sigmas")
            else None,
            loop_accept_graph_chi2=(
                t.number("loop_accept_graph_chi2", 16.3, (lambda v: 0 <= v <= 1e6, "must be in [0, 1e6]"))
                or None
            ),
            loop_snap_forward_m=(
                t.number("loop_snap_forward_m", 0.15, (lambda v: 0 <= v <= 10, "must be 0..10 m")) or None
            ),
            loop_final_scan_chain=t.boolean("loop_final_scan_chain", d.loop_final_scan_chain),
            free_margin_m=t.number("free_margin_m", 0.0, (lambda v: 0 <= v <= 0.5, "must be 0..0.5 m"))
            if t.has("free_margin_m")
            else None,
            grid_phase_from_walls=t.boolean("grid_phase_from_walls", d.grid_phase_from_walls),
        )
        if not slam.angular_update_rad > 0:
            raise t.error("angular_update_rad", "must be > 0")
        if not slam.sigma_yaw_rad > 0:
            raise t.error("sigma_yaw_rad", "must be > 0")
        t.finish()
        return slam

    @staticmethod
    def _match_iterations(t: _Table, default: tuple[int, int, int]) -> tuple[int, int, int]:
        """``[slam] match_iterations``: the proposal match's Gauss-Newton iterations per stage, three
        integers in 1..20 (wide, middle, fine)."""
        values = t.numbers("match_iterations", 3)
        if values is None:
            return default
        if not all(v == int(v) and 1 <= v <= 20 for v in values):
            raise t.error("match_iterations", f"must be three integers in 1..20, got {list(values)}")
        wide, middle, fine = (int(v) for v in values)
        return wide, middle, fine

    @staticmethod
    def _odometry_noise(t: _Table) -> tuple[float, float, float, float] | None:
        """``[slam] odometry_noise``: the motion model's [srr, srt, str, stt], each >= 0."""
        values = t.numbers("odometry_noise", 4)
        if values is None:
            return None
        if not all(v >= 0 for v in values):
            raise t.error("odometry_noise", f"must be >= 0, got {list(values)}")
        srr, srt, str_, stt = values
        return srr, srt, str_, stt

    # [fusion] ------------------------------------------------------------------------------------
    def _fusion(self) -> FusionConfig:
        t = self.top.table("fusion") or _Table({}, "fusion", self.file)
        d = FusionConfig()
        pose: tuple[float, float, float] | None = None
        start = t.table("initial_pose")
        if start is not None:
            for name in ("x_m", "y_m"):
                if not start.has(name):
                    raise start.error(name, "missing (initial_pose needs x_m, y_m and yaw_rad or yaw_deg)")
            pose = (start.number("x_m", 0.0), start.number("y_m", 0.0), start.angle("yaw", 0.0, math.pi))
            start.finish()
        fusion = FusionConfig(
            initial_pose=pose,
            initial_sigma_xy_m=t.number("initial_sigma_xy_m", d.initial_sigma_xy_m, _POSITIVE),
            initial_sigma_yaw_rad=t.angle("initial_sigma_yaw", d.initial_sigma_yaw_rad),
            odometry_sigma_m_per_m=t.number("odometry_sigma_m_per_m", d.odometry_sigma_m_per_m, _POSITIVE),
            odometry_yaw_rate_sigma_radps=t.number(
                "odometry_yaw_rate_sigma_radps", d.odometry_yaw_rate_sigma_radps, _POSITIVE
            ),
            odometry_time_sigma_s=t.number("odometry_time_sigma_s", d.odometry_time_sigma_s, _NON_NEGATIVE),
            gyro_sigma_radps=t.number("gyro_sigma_radps", d.gyro_sigma_radps, _POSITIVE),
            yaw_rate_walk_radps2=t.number("yaw_rate_walk_radps2", d.yaw_rate_walk_radps2, _POSITIVE),
            gyro_bias_walk_radps=t.number("gyro_bias_walk_radps", d.gyro_bias_walk_radps, _POSITIVE),
            gate_probability=t.number("gate_probability", d.gate_probability, _PROBABILITY),
            history_s=t.number("history_s", d.history_s, (lambda v: 0.1 <= v <= 10, "must be 0.1..10")),
            vlp_timeout_s=t.number("vlp_timeout_s", d.vlp_timeout_s, _POSITIVE),
            slam_timeout_s=t.number("slam_timeout_s", d.slam_timeout_s, _POSITIVE),
            odometry_timeout_s=t.number("odometry_timeout_s", d.odometry_timeout_s, _POSITIVE),
            imu_timeout_s=t.number("imu_timeout_s", d.imu_timeout_s, _POSITIVE),
        )
        for name in ("initial_sigma_yaw_rad",):
            if not getattr(fusion, name) > 0:
                raise t.error(name, "must be > 0")
        t.finish()
        return fusion

    # [output] ------------------------------------------------------------------------------------
    def _output(self, sim: SimConfig | None) -> OutputConfig:
        t = self.top.table("output") or _Table({}, "output", self.file)
        d = OutputConfig()
        fmt = OutputFormat(t.choice("format", d.format.value, [f.value for f in OutputFormat]))
        url = t.string("url")
        if url is None and sim is None:
            raise t.error("url", 'missing (the serial port the pose goes out on, e.g. "/dev/ttyS0")')
        if url == "pty" and sim is None:
            raise t.error("url", '"pty" (a simulator-made pseudo-terminal) only exists under [sim]')
        from firmware_protocol.mavlink_out import MavlinkMessage

        output = OutputConfig(
            format=fmt,
            url=url or ("pty" if sim is not None else None),
            baud=t.integer("baud", d.baud, (lambda v: 1200 <= v <= 12_000_000, "must be 1200..12000000 bps")),
            rate_hz=t.number("rate_hz", d.rate_hz, (lambda v: 0 < v <= 1000, "must be in (0, 1000]")),
            write_timeout_s=t.number("write_timeout_s", d.write_timeout_s, _POSITIVE),
            mavlink_message=t.choice("mavlink_message", d.mavlink_message, [m.value for m in MavlinkMessage]),
            mavlink_sysid=t.integer(
                "mavlink_sysid", d.mavlink_sysid, (lambda v: 1 <= v <= 255, "must be 1..255")
            ),
            mavlink_compid=t.integer("mavlink_compid", d.mavlink_compid, _BYTE),
        )
        if fmt is OutputFormat.FRAME:
            for name in ("mavlink_message", "mavlink_sysid", "mavlink_compid"):
                if name in t.data:
                    raise t.error(name, 'only applies to format = "mavlink"')
        t.finish()
        # The line must carry the stream: bytes per pose x 10 bits at the rate, within a share of the baud.
        frame_bytes = _frame_bytes(output)
        need = frame_bytes * 10 * output.rate_hz
        if need > _LINE_SHARE * output.baud:
            raise ConfigError(
                "output.rate_hz",
                f"{output.rate_hz:g} poses/s of {frame_bytes} bytes need {need:.0f} bit/s, more than "
                f"{_LINE_SHARE:.0%} of {output.baud} baud: lower the rate or raise output.baud",
                self.file,
            )
        return output

    # [control], [health] -------------------------------------------------------------------------
    def _control(self) -> ControlConfig:
        t = self.top.table("control") or _Table({}, "control", self.file)
        d = ControlConfig()
        control = ControlConfig(
            deadman_timeout_s=t.number("deadman_timeout_s", d.deadman_timeout_s, _POSITIVE),
            recovery_hold_s=t.number("recovery_hold_s", d.recovery_hold_s, _NON_NEGATIVE),
            loop_rate_hz=t.number(
                "loop_rate_hz", d.loop_rate_hz, (lambda v: 1 <= v <= 500, "must be 1..500")
            ),
            max_speed_mps=t.number("max_speed_mps", d.max_speed_mps, _POSITIVE),
            max_turn_radps=t.number("max_turn_radps", d.max_turn_radps, _POSITIVE),
        )
        t.finish()
        if control.deadman_timeout_s < 2.0 / control.loop_rate_hz:
            raise ConfigError(
                "control.deadman_timeout_s",
                f"{control.deadman_timeout_s:g} s is shorter than two servo loop periods "
                f"({2.0 / control.loop_rate_hz:g} s at loop_rate_hz = {control.loop_rate_hz:g})",
                self.file,
            )
        return control

    # [navigation] --------------------------------------------------------------------------------
    def _navigation(self) -> NavConfig:
        """Every :class:`NavConfig` field is a key (``*_rad`` also as ``*_deg``); numbers must be positive
        except the margins (>= 0); then the keys that must agree with each other are checked."""
        t = self.top.table("navigation") or _Table({}, "navigation", self.file)
        d = NavConfig()
        values: dict[str, Any] = {}
        for f in dataclasses.fields(NavConfig):
            default = getattr(d, f.name)
            if isinstance(default, bool):
                values[f.name] = t.boolean(f.name, default)
            elif isinstance(default, int):
                values[f.name] = t.integer(f.name, default, (lambda v: v >= 1, "must be >= 1"))
            elif f.name.endswith("_rad"):
                name = f.name.removesuffix("_rad")
                value = t.angle(name, default)
                if not 0 < value <= math.pi:
                    raise t.error(f.name, "must be in (0, 180] degrees")
                values[f.name] = value
            else:
                margin = f.name in ("safety_margin_m", "stop_margin_m")
                values[f.name] = t.number(f.name, default, _NON_NEGATIVE if margin else _POSITIVE)
        t.finish()
        nav = NavConfig(**values)
        checks = (
            ("slow_margin_m", nav.slow_margin_m > nav.stop_margin_m, "must be larger than stop_margin_m"),
            ("slow_speed_fraction", nav.slow_speed_fraction <= 1.0, "must be at most 1"),
            (
                "inflation_radius_m",
                nav.inflation_radius_m >= nav.inscribed_m,
                "must be at least radius_m + safety_margin_m",
            ),
            (
                "lookahead_max_m",
                nav.lookahead_max_m >= nav.lookahead_min_m,
                "must be at least lookahead_min_m",
            ),
            (
                "max_speed_mps",
                nav.max_speed_mps <= nav.max_wheel_speed_mps,
                "must be at most max_wheel_speed_mps (the wheels' top speed)",
            ),
            (
                "xy_tolerance_m",
                nav.xy_tolerance_m >= nav.resolution_m / 2,
                "must be at least half a costmap cell (resolution_m / 2)",
            ),
            ("resolution_m", 0.01 <= nav.resolution_m <= 0.5, "must be 0.01..0.5"),
        )
        for key, ok, reason in checks:
            if not ok:
                raise ConfigError(f"navigation.{key}", f"{reason}, got {getattr(nav, key)}", self.file)
        return nav

    # [exploration] -------------------------------------------------------------------------------
    def _exploration(self) -> ExploreConfig:
        """Every :class:`ExploreConfig` field is a key: ``explorer`` by name, counts >= 1 (``ast_beams``
        8..3600), the rest > 0 (``gain_scale``, ``switch_margin`` and ``locality_m`` >= 0)."""
        t = self.top.table("exploration") or _Table({}, "exploration", self.file)
        d = ExploreConfig()
        values: dict[str, Any] = {}
        for f in dataclasses.fields(ExploreConfig):
            default = getattr(d, f.name)
            if f.name == "explorer":
                values[f.name] = ExplorerKind(
                    t.choice(f.name, default.value, [k.value for k in ExplorerKind])
                )
            elif f.name == "places":
                values[f.name] = self._places(t)
            elif isinstance(default, bool):
                values[f.name] = t.boolean(f.name, default)
            elif f.name == "ast_beams":
                values[f.name] = t.integer(f.name, default, (lambda v: 8 <= v <= 3600, "must be 8..3600"))
            elif isinstance(default, int):
                values[f.name] = t.integer(f.name, default, (lambda v: v >= 1, "must be >= 1"))
            else:
                zero_ok = f.name in ("gain_scale", "switch_margin", "locality_m")
                values[f.name] = t.number(f.name, default, _NON_NEGATIVE if zero_ok else _POSITIVE)
        t.finish()
        return ExploreConfig(**values)

    def _places(self, t: _Table) -> tuple[NamedPoint, ...]:
        """``[[exploration.places]]``: ``name`` (unique), ``x_m``, ``y_m``, optional ``yaw_deg`` /
        ``yaw_rad``."""
        out: list[NamedPoint] = []
        for p in t.tables("places") or []:
            name = p.required_string("name", "the place's name")
            if any(q.name == name for q in out):
                raise p.error("name", f"{name!r} names two places")
            if len(name.encode()) > 16:
                raise p.error("name", "at most 16 bytes (the go-to-place frame's name field)")
            x = p.number("x_m", math.nan)
            y = p.number("y_m", math.nan)
            if math.isnan(x) or math.isnan(y):
                raise p.error("x_m" if math.isnan(x) else "y_m", "missing (the place's position, metres)")
            has_yaw = p.has("yaw_deg") or p.has("yaw_rad")
            yaw = p.angle("yaw", 0.0)
            out.append(NamedPoint(name, x, y, yaw if has_yaw else None))
            p.finish()
        return tuple(out)

    def _record(self) -> RecordConfig:
        t = self.top.table("record") or _Table({}, "record", self.file)
        record = RecordConfig(
            path=t.path_value("path", self.base),
            max_mb=t.number(
                "max_mb",
                RecordConfig().max_mb,
                (lambda v: 0 < v <= MAX_RECORD_MB, f"must be > 0 and at most {MAX_RECORD_MB} (a terabyte)"),
            ),
        )
        t.finish()
        return record

    def _recorder(self) -> RecorderConfig:
        t = self.top.table("recorder") or _Table({}, "recorder", self.file)
        d = RecorderConfig()
        channels = d.channels
        if t.has("channels"):
            value = t.take("channels")
            if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
                raise t.error("channels", f"must be a non-empty array of channel names, not {value!r}")
            for name in value:
                if name not in d.channels:
                    # No image channel exists: the camera's frames never leave the process (ARCHITECTURE.md).
                    image = any(w in name.lower() for w in ("image", "camera", "frame"))
                    why = "camera images are never recorded; " if image else ""
                    raise t.error("channels", f"{why}{name!r} is not a channel (one of {list(d.channels)})")
            channels = tuple(dict.fromkeys(value))
        size = (lambda v: 0 < v <= MAX_RECORD_MB, f"must be > 0 and at most {MAX_RECORD_MB} (a terabyte)")
        free = (lambda v: 0 <= v <= MAX_RECORD_MB, f"must be 0..{MAX_RECORD_MB}")
        queue = (lambda v: 100 <= v <= 10**6, "must be 100..1000000")
        maps = (lambda v: v == 0 or 0.5 <= v <= 3600, "must be 0 (no map snapshots) or 0.5..3600")
        recorder = RecorderConfig(
            path=t.path_value("path", self.base),
            channels=channels,
            chunk_s=t.number("chunk_s", d.chunk_s, (lambda v: 0.05 <= v <= 60, "must be 0.05..60")),
            file_mb=t.number("file_mb", d.file_mb, size),
            file_s=t.number("file_s", d.file_s, (lambda v: 1 <= v <= 86_400, "must be 1..86400 (a day)")),
            total_mb=t.number("total_mb", d.total_mb, size),
            min_free_mb=t.number("min_free_mb", d.min_free_mb, free),
            queue_size=t.integer("queue_size", d.queue_size, queue),
            map_period_s=t.number("map_period_s", d.map_period_s, maps),
            snapshot_s=t.number(
                "snapshot_s",
                d.snapshot_s,
                (lambda v: v == 0 or 1 <= v <= 3600, "must be 0 (no snapshots) or 1..3600"),
            ),
            snapshot_mb=t.number("snapshot_mb", d.snapshot_mb, (lambda v: 1 <= v <= 4096, "must be 1..4096")),
            continuous=t.boolean("continuous", d.continuous),
        )
        if not recorder.continuous and recorder.snapshot_s == 0:
            raise t.error("continuous", "false records nothing unless snapshot_s > 0")
        if recorder.file_mb > recorder.total_mb:
            raise t.error(
                "file_mb", f"must be at most total_mb ({recorder.total_mb:g}), got {recorder.file_mb:g}"
            )
        t.finish()
        return recorder

    def _scheduling(self) -> SchedulingConfig:
        t = self.top.table("scheduling") or _Table({}, "scheduling", self.file)
        priority = t.number(
            "realtime_priority",
            SchedulingConfig().realtime_priority,
            (
                lambda v: v == int(v) and 0 <= v <= MAX_REALTIME_PRIORITY,
                f"must be a whole number 0..{MAX_REALTIME_PRIORITY} (0: no real-time scheduling)",
            ),
        )
        latency = t.number(
            "cpu_latency_us",
            SchedulingConfig().cpu_latency_us,
            (
                lambda v: v == int(v) and -1 <= v <= MAX_CPU_LATENCY_US,
                f"must be a whole number of microseconds 0..{MAX_CPU_LATENCY_US} (-1: no request)",
            ),
        )
        t.finish()
        return SchedulingConfig(realtime_priority=int(priority), cpu_latency_us=int(latency))

    def _fleet(self) -> FleetConfig:
        t = self.top.table("fleet") or _Table({}, "fleet", self.file)
        d = FleetConfig()
        socket = t.path_value("socket", self.base)
        if socket is not None and len(os.fsencode(socket)) > MAX_SOCKET_PATH:
            raise t.error("socket", f"a Unix socket path is at most {MAX_SOCKET_PATH} bytes: {socket}")
        fleet = FleetConfig(
            socket=socket,
            pose_rate_hz=t.number(
                "pose_rate_hz", d.pose_rate_hz, (lambda v: 0.1 <= v <= 100, "must be 0.1..100")
            ),
            status_period_s=t.number(
                "status_period_s", d.status_period_s, (lambda v: 0.05 <= v <= 60, "must be 0.05..60")
            ),
            peer_timeout_s=t.number(
                "peer_timeout_s", d.peer_timeout_s, (lambda v: 0.1 <= v <= 600, "must be 0.1..600")
            ),
            peer_radius_m=t.number(
                "peer_radius_m", d.peer_radius_m, (lambda v: 0 <= v <= 5, "must be 0..5 (0: this robot's)")
            ),
        )
        t.finish()
        return fleet

    def _health(self) -> HealthConfig:
        t = self.top.table("health") or _Table({}, "health", self.file)
        d = HealthConfig()
        health = HealthConfig(
            watchdog=t.boolean("watchdog", d.watchdog),
            loop_timeout_s=t.number("loop_timeout_s", d.loop_timeout_s, _POSITIVE),
            status_interval_s=t.number("status_interval_s", d.status_interval_s, _POSITIVE),
            ready_grace_s=t.number("ready_grace_s", d.ready_grace_s, _POSITIVE),
            not_localizing_log_s=t.number("not_localizing_log_s", d.not_localizing_log_s, _POSITIVE),
            camera_stall_s=t.number("camera_stall_s", d.camera_stall_s, _POSITIVE),
            laser_lost_s=t.number("laser_lost_s", d.laser_lost_s, _POSITIVE),
            servo_fault_s=t.number("servo_fault_s", d.servo_fault_s, _POSITIVE),
        )
        t.finish()
        return health


def _sim_backend(kind: DeviceKind, world: World) -> str:
    """The backend each simulated device needs (the fake reader speaks the world's RFID protocol)."""
    return {
        DeviceKind.CAMERA: "sim",
        DeviceKind.LASER: "urg",
        DeviceKind.SERVOS: "dynamixel",
        DeviceKind.IMU: "mpu6050",
        DeviceKind.RFID: world.rfid.protocol,
    }[kind]


def _frame_bytes(output: OutputConfig) -> int:
    """Bytes one pose takes on the line (the largest a message can be)."""
    if output.format is OutputFormat.FRAME:
        from firmware_protocol.pose_frame import WIRE_LENGTH

        return WIRE_LENGTH
    # MAVLink 2: 12 header/CRC bytes + the payload before trailing-zero truncation.
    return 12 + (117 if output.mavlink_message == "vision_position_estimate" else 233)
