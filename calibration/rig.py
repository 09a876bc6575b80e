"""The robot's devices for a step: opened from the robot's config, or on the simulated robot.

Devices are opened on first use, through the same backends and options the agent uses (``drivers.registry``
and ``agent.config``), and closed when the step ends, whatever way it ends; the wheels are stopped first.
:class:`Nominal` is what the robot believes before calibrating: the config's values, or the world file's
design values on the simulated robot.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Self

from calibration.context import StepContext
from calibration.report import CalibrationError
from drivers.camera.base import Camera, CameraSettings
from drivers.errors import ConfigError, DeviceError
from drivers.imu.base import Imu
from drivers.laser.base import LaserScanner
from drivers.registry import DeviceKind, backend_class
from drivers.rfid.base import RfidReader
from drivers.servos.base import WheelServos
from drivers.sim.simulation import Simulation
from drivers.sim.world import Mount, World

__all__ = ["Nominal", "Rig"]

_OPEN_ATTEMPTS = 3

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Nominal:
    """The robot's values before this calibration (config or design)."""

    wheel_radius_m: float = 0.033
    track_m: float = 0.160
    camera_mount: Mount = field(default_factory=lambda: Mount(0.0, 0.0, 0.2))
    laser_mount: Mount = field(default_factory=lambda: Mount(0.0, 0.0, 0.18))
    fx_px: float | None = None
    image_width_px: int | None = None
    sensor_size_px: tuple[int, int] | None = None

    def intrinsics_f_px(self, width: int) -> float:
        if self.fx_px is not None and self.image_width_px:
            return self.fx_px * width / self.image_width_px
        return 0.8 * width


def _mount(m: Any) -> Mount:
    return Mount(m.x_m, m.y_m, m.z_m, m.yaw_rad, m.roll_rad, m.pitch_rad)


def _open_device(what: str, build: Callable[[], Any]) -> Any:
    """Build and open a device; a DeviceError at open is retried (a missed reply at bring-up: a busy bus, an
    adapter still enumerating), a ConfigError is not."""
    for attempt in range(1, _OPEN_ATTEMPTS + 1):
        try:
            device = build()
            device.open()
            return device
        except ConfigError as exc:
            raise CalibrationError(f"cannot open the {what}: {exc}") from exc
        except DeviceError as exc:
            if attempt == _OPEN_ATTEMPTS:
                raise CalibrationError(f"cannot open the {what}: {exc}") from exc
            log.warning("opening the %s failed (%s); trying again", what, exc)
            time.sleep(0.3)
    raise AssertionError("unreachable")


class Rig:
    """Devices of one robot for one step. Use as a context manager."""

    def __init__(
        self,
        tables: dict[DeviceKind, tuple[str, dict[str, Any]]],
        nominal: Nominal,
        *,
        simulation: Simulation | None = None,
        robot: Any = None,
        seed: int = 0,
        forward: tuple[Any, str, Any] | None = None,
    ) -> None:
        self._tables = tables
        # [camera.forward]: its agent.config.DeviceConfig, the config file, its ForwardViewConfig.
        self._forward = forward
        self.forward_view = forward[2] if forward is not None else None
        self.nominal = nominal
        self.simulation = simulation
        self._robot = robot  # drivers.sim.harness.SimulatedRobot, when simulated
        self._seed = seed
        self._open: dict[DeviceKind, Any] = {}
        self._extra: dict[str, Any] = {}  # devices of no DeviceKind of their own (the forward camera)
        self._stack = contextlib.ExitStack()

    # -- making one -------------------------------------------------------------------------------------
    @classmethod
    def for_context(cls, ctx: StepContext, world: World | None = None) -> Rig:
        """The robot of ``ctx``: the simulated one (on ``world``, default the context's world) or the one the
        config describes."""
        if ctx.sim is not None:
            return cls.simulated(world if world is not None else ctx.sim.load(), ctx.sim.seed)
        if ctx.config is None:
            raise CalibrationError("this step needs the robot: pass --config FILE or --sim")
        return cls.from_config(ctx.config)

    @classmethod
    def simulated(cls, world: World, seed: int = 0, design: World | None = None) -> Rig:
        """Fake devices on ``world`` (the robot as built); ``design`` (default ``world``) gives the nominal
        values the robot believes."""
        from drivers.sim.harness import SimulatedRobot
        from drivers.sim.worldfile import nominal_camera

        robot = SimulatedRobot(world, seed=seed)
        robot.start()
        tables: dict[DeviceKind, tuple[str, dict[str, Any]]] = {}
        for name, table in robot.device_config().items():
            table = dict(table)
            backend = table.pop("backend")
            kind = DeviceKind(name)
            if kind is DeviceKind.RFID:
                table["protocol"] = backend
            if kind is DeviceKind.CAMERA:
                table = {"simulation": robot.simulation, "seed": seed}
            tables[kind] = (backend, table)
        d = design if design is not None else world
        cam = nominal_camera(d).focal_length_px
        scale = d.camera.sensor_width_px / d.camera.output_width_px
        nominal = Nominal(
            d.robot.wheel_radius_m,
            d.robot.track_m,
            d.robot.camera_mount,
            d.robot.laser_mount,
            cam / scale,
            d.camera.output_width_px,
            (d.camera.sensor_width_px, d.camera.sensor_height_px),
        )
        rig = cls(tables, nominal, simulation=robot.simulation, robot=robot, seed=seed)
        rig._stack.callback(robot.close)
        return rig

    @classmethod
    def from_config(cls, path: Any) -> Rig:
        from agent.config import load_config

        config = load_config(path)
        forward = (
            (config.forward_camera, config.file, config.forward_view)
            if config.forward_camera is not None
            else None
        )
        if config.sim is not None:
            raise CalibrationError(
                f"{path} describes the simulated robot ([sim]); use --sim instead of --config"
            )
        tables = {kind: (dev.backend, dict(dev.options)) for kind, dev in config.devices.items()}
        servo_options = tables.get(DeviceKind.SERVOS, ("", {}))[1]
        vlp, slam = config.vlp, config.slam
        intr = vlp.intrinsics
        nominal = Nominal(
            float(servo_options.get("wheel_radius_m", 0.033)),
            float(servo_options.get("track_m", 0.160)),
            _mount(vlp.mount) if vlp.mount is not None else Mount(0.0, 0.0, 0.2),
            _mount(slam.laser_mount) if slam.laser_mount is not None else Mount(0.0, 0.0, 0.18),
            intr.fx_px if intr is not None else None,
            intr.width_px if intr is not None else None,
            (intr.sensor_width_px, intr.sensor_height_px)
            if intr is not None and intr.sensor_width_px
            else None,
        )
        return cls(tables, nominal, forward=forward)

    # -- devices ----------------------------------------------------------------------------------------
    def has(self, kind: DeviceKind) -> bool:
        """Whether the robot has this kind of device (in its config, or the simulated robot)."""
        return kind in self._tables

    def _device(self, kind: DeviceKind, **overrides: Any) -> Any:
        if kind in self._open:
            return self._open[kind]
        if kind not in self._tables:
            raise CalibrationError(f"the robot has no [{kind.value}] device in its config")
        backend, options = self._tables[kind]
        options = {**options, **overrides}
        try:
            cls = backend_class(kind, backend)
        except (DeviceError, ConfigError) as exc:
            raise CalibrationError(f"cannot open the {kind.value} ({backend}): {exc}") from exc
        device = _open_device(f"{kind.value} ({backend})", lambda: cls(**options))
        self._open[kind] = device
        return device

    def camera(self, exposure_s: float | None = None) -> Camera:
        overrides: dict[str, Any] = {}
        if exposure_s is not None:
            options = self._tables.get(DeviceKind.CAMERA, ("", {}))[1]
            settings = options.get("settings") or CameraSettings()
            overrides["settings"] = dataclasses.replace(settings, exposure_s=exposure_s)
        camera: Camera = self._device(DeviceKind.CAMERA, **overrides)
        return camera

    def forward_camera(self, exposure_s: float | None = None) -> Camera:
        """The forward camera of ``[camera.forward]`` (person following's), opened with its settings
        (``exposure_s``: in place of the config's)."""
        if self._forward is None:
            raise CalibrationError(
                "the robot has no forward camera: its config has no [camera.forward] table (or it has "
                "enabled = false); see docs/config.md"
            )
        if "forward_camera" in self._extra:
            camera: Camera = self._extra["forward_camera"]
            return camera
        from agent.runtime.devices import build_forward_camera

        device, file, _ = self._forward
        if exposure_s is not None:
            settings = device.options.get("settings") or CameraSettings()
            options = {**device.options, "settings": dataclasses.replace(settings, exposure_s=exposure_s)}
            device = dataclasses.replace(device, options=options)
        camera = _open_device(
            f"forward camera ({device.backend})", lambda: build_forward_camera(device, file)
        )
        self._extra["forward_camera"] = camera
        return camera

    def servos(self) -> WheelServos:
        servos: WheelServos = self._device(DeviceKind.SERVOS)
        return servos

    def laser(self) -> LaserScanner:
        laser: LaserScanner = self._device(DeviceKind.LASER)
        return laser

    def imu(self) -> Imu:
        imu: Imu = self._device(DeviceKind.IMU)
        return imu

    def rfid(self) -> RfidReader:
        backend = self._tables.get(DeviceKind.RFID, ("", {}))[0]
        overrides = (
            {} if "protocol" in self._tables.get(DeviceKind.RFID, ("", {}))[1] else {"protocol": backend}
        )
        reader: RfidReader = self._device(DeviceKind.RFID, **overrides)
        return reader

    # -- lifecycle --------------------------------------------------------------------------------------
    def close(self) -> None:
        servos = self._open.get(DeviceKind.SERVOS)
        if servos is not None:
            with contextlib.suppress(DeviceError):
                servos.stop()
        opened = [(kind.value, device) for kind, device in self._open.items()] + list(self._extra.items())
        for name, device in reversed(opened):
            try:
                device.close()
            except DeviceError as exc:
                log.warning("closing the %s: %s", name, exc)
        self._open.clear()
        self._extra.clear()
        self._stack.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
