"""The description of a simulated world: plain frozen dataclasses (and a door's schedule read off one).

Units are in the names. Angles are counter-clockwise, radians; the world frame is x east, y north, z up,
the frame of the building's LED survey. ``worldfile`` builds these from TOML (documented in docs/world.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class Pose2D:
    x_m: float
    y_m: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class Mount:
    """Where a sensor sits on the robot base: offset in the base frame (x forward, y left, z up) and
    orientation (yaw about z; roll and pitch are mounting tilt)."""

    x_m: float = 0.0
    y_m: float = 0.0
    z_m: float = 0.0
    yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0


@dataclass(frozen=True, slots=True)
class Wall:
    """A wall as a line segment in the floor plane."""

    x1_m: float
    y1_m: float
    x2_m: float
    y2_m: float


@dataclass(frozen=True, slots=True)
class Door:
    """A door as a line segment across a doorway: a wall while it is closed, nothing while it is open.

    Open at the start unless only ``opens_at_s`` is given; ``closes_at_s`` / ``opens_at_s`` are simulated
    seconds from the start (None: never). Both given: closed between them (or, with ``opens_at_s`` first,
    open between them). A door does not close on the robot: it waits until the doorway is clear
    (``drivers.sim.simulation``)."""

    name: str
    x1_m: float
    y1_m: float
    x2_m: float
    y2_m: float
    closes_at_s: float | None = None
    opens_at_s: float | None = None


@dataclass(frozen=True, slots=True)
class Place:
    """A named point of the world (a room, a desk, a charging spot): where missions go."""

    name: str
    x_m: float
    y_m: float
    yaw_rad: float | None = None


def door_scheduled_closed(door: Door, t_s: float) -> bool:
    """Whether ``door``'s schedule has it closed ``t_s`` simulated seconds after the start."""
    closes, opens = door.closes_at_s, door.opens_at_s
    if closes is None:
        return opens is not None and t_s < opens
    if opens is None:
        return t_s >= closes
    if closes < opens:
        return closes <= t_s < opens
    return t_s < opens or t_s >= closes


@dataclass(frozen=True, slots=True)
class Led:
    """A ceiling LED: a disk facing down, modulated on/off with a PWM square wave."""

    id: str
    x_m: float
    y_m: float
    z_m: float
    diameter_m: float = 0.086
    frequency_hz: float = 2000.0
    duty: float = 0.5
    # What the LED map given to the agent states as this LED's survey uncertainty (per axis); None: none.
    survey_sigma_m: float | None = None


@dataclass(frozen=True, slots=True)
class CameraModel:
    """An upward-looking rolling-shutter camera. Defaults: MindVision MV-UB300 with a 4 mm lens, run as the
    reference system ran it (20 us exposure, output resized to 800x600 with nearest-neighbour).

    ``cx_px``/``cy_px`` are the true principal point in sensor pixels (None: the sensor centre).
    ``distortion`` is OpenCV's (k1, k2, p1, p2, k3) in sensor pixels.
    """

    sensor_width_px: int = 2048
    sensor_height_px: int = 1536
    pixel_size_m: float = 3.2e-6
    focal_length_m: float = 4.0e-3
    cx_px: float | None = None
    cy_px: float | None = None
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    t_row_s: float = 32e-6
    exposure_s: float = 20e-6
    output_width_px: int = 800
    output_height_px: int = 600
    frame_rate_hz: float = 30.0
    led_peak_dn: float = 230.0
    black_level_dn: float = 16.0
    read_noise_dn: float = 1.5
    full_well_e: float = 10000.0
    blur_sigma_px: float = 0.7
    radial_falloff: float = 0.3
    # Fraction of the charge above full well that spills into each vertical neighbour (blooming).
    bloom_fraction: float = 0.05

    @property
    def focal_length_px(self) -> float:
        return self.focal_length_m / self.pixel_size_m

    @property
    def principal_point_px(self) -> tuple[float, float]:
        cx = (self.sensor_width_px - 1) / 2 if self.cx_px is None else self.cx_px
        cy = (self.sensor_height_px - 1) / 2 if self.cy_px is None else self.cy_px
        return cx, cy


@dataclass(frozen=True, slots=True)
class LaserModel:
    """A scanning laser. Defaults: Hokuyo URG-04LX(-UG01), the values its PP command reports."""

    model: str = "URG-04LX-UG01(Simple-URG)(Hokuyo Automatic Co.,Ltd.)"
    min_range_mm: int = 20
    max_range_mm: int = 5600
    steps_per_rev: int = 1024
    first_step: int = 44
    last_step: int = 725
    front_step: int = 384
    scan_rpm: int = 600
    range_noise_mm: float = 10.0
    dropout: float = 0.0


@dataclass(frozen=True, slots=True)
class RobotSpec:
    """A differential-drive robot. Defaults: TurtleBot3 burger (wheel radius 0.033 m, track 0.160 m,
    XL430 servos with ids 1 (left) and 2 (right))."""

    start: Pose2D = Pose2D(0.0, 0.0, 0.0)
    wheel_radius_m: float = 0.033
    track_m: float = 0.160
    left_id: int = 1
    right_id: int = 2
    max_wheel_radps: float = 6.6
    max_wheel_accel_radps2: float = 20.0
    camera_mount: Mount = Mount(0.0, 0.0, 0.2)
    laser_mount: Mount = Mount(0.0, 0.0, 0.18)
    imu_mount: Mount = Mount()
    radius_m: float = 0.105


@dataclass(frozen=True, slots=True)
class Person:
    """Someone walking a looped path, carrying an RFID tag."""

    name: str
    tag_id: str
    path: tuple[tuple[float, float], ...]
    speed_mps: float = 0.8
    radius_m: float = 0.2
    # A pedestrian stops for the robot's body in their way ahead (``drivers/sim/pedestrians.py``).
    yields: bool = True
    reaction_s: float = 0.4


@dataclass(frozen=True, slots=True)
class RfidModel:
    """The reader on the robot: which protocol it speaks, and how far it reads."""

    protocol: str = "id12la"
    range_m: float = 1.5
    repeat_s: float = 0.25


@dataclass(frozen=True, slots=True)
class ErrorModel:
    """Realistic errors, part of the world: what the agent believes differs from the truth by these.

    The true principal point is offset from the nominal one by ``principal_point_error_px``; the LED map
    the agent is given is off by ``led_survey_error_m`` (standard deviation, per axis) and
    ``led_height_error_m``; the camera is tilted on its mount by ``camera_tilt_rad`` (roll, pitch).
    """

    principal_point_error_px: tuple[float, float] = (0.0, 0.0)
    led_survey_error_m: float = 0.0
    led_height_error_m: float = 0.0
    camera_tilt_rad: tuple[float, float] = (0.0, 0.0)
    seed: int = 0


@dataclass(frozen=True, slots=True)
class World:
    name: str
    walls: tuple[Wall, ...] = ()
    doors: tuple[Door, ...] = ()
    places: tuple[Place, ...] = ()
    leds: tuple[Led, ...] = ()
    robot: RobotSpec = RobotSpec()
    camera: CameraModel = CameraModel()
    laser: LaserModel = LaserModel()
    rfid: RfidModel = RfidModel()
    people: tuple[Person, ...] = ()
    route: tuple[tuple[float, float], ...] = ()
    route_speed_mps: float = 0.2
    errors: ErrorModel = ErrorModel()
    source: str | None = field(default=None, compare=False)
