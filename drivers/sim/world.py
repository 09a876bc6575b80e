"""The description of a simulated world: plain frozen dataclasses (and a door's schedule read off one).

Units are in the names. Angles are counter-clockwise, radians; the world frame is x east, y north, z up,
the frame of the building's LED survey. ``worldfile`` builds these from TOML (documented in docs/world.md).
"""

from __future__ import annotations

import math
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
    # Light output relative to ``CameraModel.led_peak_dn`` (a dimmer or brighter fitting).
    brightness: float = 1.0
    # In the map but dark (a failed LED): the renderer draws nothing for it.
    dead: bool = False
    # False: lit but missing from the LED map the agent is given (an LED fitted after the survey).
    mapped: bool = True
    # The true PWM frequency drifts from ``frequency_hz`` (its value at the renderer's first frame, and what
    # the map says): linearly, and as a random walk (standard deviation sqrt(t) times this after t seconds).
    frequency_drift_hz_per_s: float = 0.0
    frequency_walk_hz_per_sqrt_s: float = 0.0


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
    # JPEG-like compression of every output frame (cv2.imencode / imdecode at this quality); 0: none.
    jpeg_quality: int = 0

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
class Clothing:
    """How a person looks to the forward camera: colours as (red, green, blue) 0-255, the shirt's
    texture (``plain``, ``stripes``: horizontal bands, ``checks``) in ``pattern_rgb`` with a period of
    ``pattern_period_m``, and the body's height."""

    shirt_rgb: tuple[float, float, float] = (40.0, 90.0, 170.0)
    trousers_rgb: tuple[float, float, float] = (50.0, 50.0, 60.0)
    skin_rgb: tuple[float, float, float] = (205.0, 160.0, 130.0)
    hair_rgb: tuple[float, float, float] = (60.0, 40.0, 30.0)
    pattern: str = "plain"
    pattern_rgb: tuple[float, float, float] = (230.0, 230.0, 230.0)
    pattern_period_m: float = 0.1
    height_m: float = 1.72


@dataclass(frozen=True, slots=True)
class Person:
    """Someone walking a path (looped, or once and then standing at its end), carrying an RFID tag."""

    name: str
    tag_id: str
    path: tuple[tuple[float, float], ...]
    speed_mps: float = 0.8
    radius_m: float = 0.2
    # A pedestrian stops for the robot's body in their way ahead (``drivers/sim/pedestrians.py``).
    yields: bool = True
    reaction_s: float = 0.4
    loop: bool = True
    # Seconds the person stands at the path's first point before walking (a passer-by's cue).
    start_s: float = 0.0
    clothing: Clothing = Clothing()


@dataclass(frozen=True, slots=True)
class ForwardCameraModel:
    """The forward-looking colour camera of person following: a level pinhole camera (no roll or pitch;
    ``cy_px`` above the centre looks upwards as a tilted camera would, with verticals kept vertical), global
    shutter, BGR8 frames. ``mount``: its place on the base (x forward, y left, z up; yaw only).

    The scene: walls ``wall_height_m`` high in ``wall_rgb`` (each wall a little lighter or darker, flat
    shaded by its orientation to the light), floor and ceiling, people as bodies in their clothing. The
    lighting gain is 1 + ``light_variation`` sin(2 pi t / ``light_period_s``) (lamps dimming, a cloud over a
    window); sensor noise is Gaussian with ``noise_dn`` per channel."""

    width_px: int = 640
    height_px: int = 480
    hfov_rad: float = 1.2217304763960306  # 70 degrees
    cx_px: float | None = None
    cy_px: float | None = None
    frame_rate_hz: float = 15.0
    mount: Mount = Mount(0.1, 0.0, 1.3)
    wall_height_m: float = 2.5
    wall_rgb: tuple[float, float, float] = (200.0, 195.0, 180.0)
    floor_rgb: tuple[float, float, float] = (120.0, 110.0, 100.0)
    ceiling_rgb: tuple[float, float, float] = (225.0, 225.0, 220.0)
    light_variation: float = 0.15
    light_period_s: float = 11.0
    noise_dn: float = 3.0

    @property
    def focal_length_px(self) -> float:
        return (self.width_px / 2.0) / math.tan(self.hfov_rad / 2.0)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        cx = (self.width_px - 1) / 2.0 if self.cx_px is None else self.cx_px
        cy = (self.height_px - 1) / 2.0 if self.cy_px is None else self.cy_px
        return cx, cy


@dataclass(frozen=True, slots=True)
class RfidModel:
    """The reader on the robot: which protocol it speaks, and how far it reads.

    With ``antenna_yaws_rad`` (Mercury only) the reader has one antenna per yaw (ports 1, 2, ...), each
    on a circle of ``antenna_radius_m`` round the base centre at its yaw, and RSSI comes from the channel
    model of ``drivers/sim/rfid_channel.py`` (path loss, antenna pattern, wall reflections, scatterers,
    body loss, noise); a tag is read on a port when within ``range_m`` and its RSSI there is at least
    ``sensitivity_dbm``. Without it, the legacy model: one read per cycle on the forward (or, with two
    ports, the rear) antenna, free-space loss and a cosine pattern.
    """

    protocol: str = "id12la"
    range_m: float = 1.5
    repeat_s: float = 0.25
    antenna_yaws_rad: tuple[float, ...] = ()
    antenna_radius_m: float = 0.1
    beamwidth_rad: float = 1.2217304763960306  # 70 degrees, a circular patch
    front_to_back_db: float = 15.0
    rssi_at_1m_dbm: float = -50.0
    sensitivity_dbm: float = -80.0
    # Multipath strong enough that the left/right cue is as weak as measured indoors (reference/eco.md §3:
    # corr(RSSI difference, sin bearing) 0.45-0.75 spinning in place): 0.54-0.74 on the calibration walks
    # of benchmarks/rfid_coarse.py and the follow worlds.
    wall_reflection: float = 0.6
    scatterers: int = 24
    scatter_amplitude: float = 0.6
    scatter_seed: int = 0  # where the scatterers stand: part of the world, the same in every run
    body_loss_db: float = 8.0
    noise_db: float = 1.0


@dataclass(frozen=True, slots=True)
class ErrorModel:
    """Realistic errors, part of the world: what the agent believes differs from the truth by these.

    The true principal point is offset from the nominal one by ``principal_point_error_px``; the LED map
    the agent is given is off by ``led_survey_error_m`` (standard deviation, per axis) and
    ``led_height_error_m``; the camera is tilted on its mount by ``camera_tilt_rad`` (roll, pitch); its
    true row time, focal length and distortion differ from the configured ones by the last three.
    """

    principal_point_error_px: tuple[float, float] = (0.0, 0.0)
    led_survey_error_m: float = 0.0
    led_height_error_m: float = 0.0
    camera_tilt_rad: tuple[float, float] = (0.0, 0.0)
    # The true row time, focal length and distortion against the configured (nominal) ones: true =
    # nominal x (1 + error) for the first two, true = nominal + error for the distortion.
    t_row_error_fraction: float = 0.0
    focal_length_error_fraction: float = 0.0
    distortion_error: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    seed: int = 0


@dataclass(frozen=True, slots=True)
class StrayLight:
    """A bright object on the ceiling that is not an LED of the map: a lamp (``disk``) or a window or light
    panel (``rectangle``), steady or flickering at ``flicker_hz`` (not an LED signature)."""

    x_m: float
    y_m: float
    z_m: float
    shape: str = "disk"
    diameter_m: float = 0.3
    width_m: float = 1.0
    length_m: float = 0.5
    yaw_rad: float = 0.0
    brightness: float = 1.0
    flicker_hz: float = 0.0
    flicker_duty: float = 0.5

    @property
    def extent_m(self) -> float:
        """The radius of the smallest circle about its centre that holds it."""
        if self.shape == "disk":
            return self.diameter_m / 2.0
        return 0.5 * float((self.width_m**2 + self.length_m**2) ** 0.5)


@dataclass(frozen=True, slots=True)
class Occluder:
    """Something that hides part or all of LED ``led_index`` (an index into ``World.leds``) at times: for
    ``hidden_s`` of every ``period_s`` from ``phase_s`` on (always when ``period_s`` is 0). ``fraction`` of
    the disk is covered from the side ``angle_rad`` points to (1: all of it)."""

    led_index: int
    fraction: float = 1.0
    angle_rad: float = 0.0
    period_s: float = 0.0
    hidden_s: float = 0.0
    phase_s: float = 0.0

    def hides_at(self, t_s: float) -> bool:
        if self.period_s <= 0.0:
            return True
        return (t_s - self.phase_s) % self.period_s < self.hidden_s


@dataclass(frozen=True, slots=True)
class Scene:
    """What else the camera sees: ambient light over the whole frame (DN above black at 0 dB gain), stray
    bright objects, occluders."""

    ambient_dn: float = 0.0
    stray_lights: tuple[StrayLight, ...] = ()
    occluders: tuple[Occluder, ...] = ()


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
    forward_camera: ForwardCameraModel = ForwardCameraModel()
    people: tuple[Person, ...] = ()
    route: tuple[tuple[float, float], ...] = ()
    route_speed_mps: float = 0.2
    errors: ErrorModel = ErrorModel()
    scene: Scene = Scene()
    source: str | None = field(default=None, compare=False)
