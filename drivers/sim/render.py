"""The physical rolling-shutter camera: one 8-bit frame of the ceiling LEDs, as the real camera node makes it.

Pure numpy/OpenCV, no I/O. The model, in the order light goes through it (``reference/vlp.md`` §1.5 and §3):

* **Geometry.** The camera frame is right-handed with z up along the optical axis; image u grows along the
  camera x axis and v (down in the image) along the camera y axis. With no tilt, x_c = (cos psi, sin psi),
  y_c = (-sin psi, cos psi), psi = base yaw + mount yaw, and an LED at horizontal offset d and height H above
  the lens lands at u = cx + f_px (d . x_c) / H, v = cy + f_px (d . y_c) / H: exactly the model the
  reference 2-LED solver inverts (the mirrored one gives ~0.7 m errors). Roll and pitch (mount plus the
  world's tilt error) generalise it: R_world_camera = Rz(psi) Ry(pitch) Rx(roll). OpenCV's
  (k1, k2, p1, p2, k3) distortion is applied in normalised coordinates. Each LED is a horizontal disk
  facing down.
* **Rolling shutter.** Sensor row i integrates over [t0 + i t_row, t0 + i t_row + T_exp]; the LED's PWM
  square wave is integrated over that window in closed form (a box filter, not sampling), and the row's
  geometry uses the robot pose at the row's own time (motion during readout).
* **Optics and sensor.** Radial fall-off across the disk I0 (1 - a (r/R)^2), cos^4 vignetting, Gaussian lens
  blur (sigma in sensor px, plus the pixel's own box), optional opaque covers over parts of an LED
  (occlusion, :class:`LedCover`), full-well saturation with a small vertical spill
  (blooming), Poisson shot noise, Gaussian read noise, black level, 8-bit rounding and clipping.
* **Downsampling as the reference node does it:** ``cv2.resize(..., INTER_NEAREST)`` from sensor size to
  output size, i.e. output pixel x shows sensor column floor(x * src/dst) (OpenCV ``resizeNN``).

Speed comes from computing only what survives that resize: just the sensor rows and columns that the
nearest-neighbour selection keeps, and only inside each LED's bounding box plus the blur margin. The lens
blur is applied analytically to the disk outline (a Gaussian-blurred edge), not to the stripes: the blur acts
on the light before the sensor, while the stripes come from when each row integrates, so they stay sharp
apart from the exposure's own box filter. The dark background with its read noise is drawn on the output
grid from a pool of pre-drawn noise that is partly renewed every frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.world import CameraModel, Led, Mount, Pose2D, Scene, World

FloatArray = npt.NDArray[np.float64]
Float32Array = npt.NDArray[np.float32]
IndexArray = npt.NDArray[np.intp]
ImageU8 = npt.NDArray[np.uint8]

__all__ = [
    "CameraPose",
    "FrameTruth",
    "LedCover",
    "LedTruth",
    "OutputIntrinsics",
    "RenderedFrame",
    "RollingShutterRenderer",
    "nearest_indices",
    "pwm_exposure_fraction",
]

# Points on each LED rim projected to find its bounding box; 16 keeps the box within 2 % of the ellipse.
_RIM_POINTS = 16
# The blur margin around each LED, in sigmas of the effective blur: the edge profile is < 1e-9 beyond it.
_BLUR_SIGMAS = 6.0
# Fixed-point iterations for the row an LED centre is imaged on; each shrinks the error by the image's
# speed in rows per row time (< 1e-2 for any robot), so three leave far less than 1e-4 rows.
_CENTRE_ITERATIONS = 3
# Fraction of the background-noise pool redrawn per frame: the whole pool is new every 32 frames.
_POOL_REFRESH_FRACTION = 1.0 / 32.0


@dataclass(frozen=True, slots=True)
class LedCover:
    """An opaque cover over part of one LED's disk (tape, a cable, a hand), in the LED's own plane.

    It hides the points p of the disk of LED ``led_index`` (an index into the renderer's LEDs) with
    (p - centre) . n > R (1 - 2 ``fraction``), n = (cos ``angle_rad``, sin ``angle_rad``) in the world
    frame: ``fraction`` 0.5 covers the half facing n, 1 the whole disk. Its edge is blurred like the rim.
    """

    led_index: int
    angle_rad: float
    fraction: float


@dataclass(frozen=True, slots=True)
class CameraPose:
    """The true pose of the camera (its lens centre) in the world frame."""

    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float
    roll_rad: float
    pitch_rad: float


@dataclass(frozen=True, slots=True)
class LedTruth:
    """Where one LED is in a frame, in output pixels.

    ``centre_px`` is where the rolling-shutter image shows the LED centre: its projection with the pose at
    the time the row through it was exposed. ``centre_mid_px`` is its projection with the mid-readout pose,
    what a global shutter at ``FrameTruth.t_mid_s`` would see; the two differ when the robot moves.
    """

    index: int
    id: str
    centre_px: tuple[float, float]
    centre_mid_px: tuple[float, float]
    radius_px: float
    row_time_s: float
    in_image: bool


@dataclass(frozen=True, slots=True)
class FrameTruth:
    """Ground truth of one frame. Times are on the clock ``pose_at`` was given in."""

    t0_s: float
    t_mid_s: float
    base_pose: Pose2D
    camera_pose: CameraPose
    leds: tuple[LedTruth, ...]


@dataclass(frozen=True, slots=True)
class RenderedFrame:
    image: ImageU8
    truth: FrameTruth


@dataclass(frozen=True, slots=True)
class OutputIntrinsics:
    """The true pinhole intrinsics at output resolution: what an ideal calibration of the resized images
    finds. ``fx_px = f_px / a_x`` and ``cx_px = (cx_sensor - b_x) / a_x`` where sensor column = a_x * x + b_x
    is the least-squares line through the nearest-neighbour selection (rows alike)."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int


def nearest_indices(src_size: int, dst_size: int) -> IndexArray:
    """The source index each destination pixel takes in ``cv2.resize(..., interpolation=INTER_NEAREST)``.

    OpenCV's ``resizeNN`` computes ``inv_scale = dst/src`` and ``ifx = 1/inv_scale`` in double precision and
    takes ``min(floor(x * ifx), src - 1)``; the same IEEE operations here give the same indices bit for bit.
    """
    if src_size <= 0 or dst_size <= 0:
        raise ValueError(f"sizes must be positive, got {src_size} -> {dst_size}")
    ifx = 1.0 / (dst_size / src_size)
    chosen: IndexArray = np.minimum(np.floor(np.arange(dst_size) * ifx).astype(np.intp), src_size - 1)
    return chosen


def pwm_exposure_fraction(
    t_start_s: FloatArray, exposure_s: float, frequency_hz: float, duty: float, phase_cycles: float = 0.0
) -> FloatArray:
    """Mean of the LED's on/off square wave over [t, t + exposure] for each start time t (0..1).

    The wave is on while frac(f t + phase) < duty. With u = f t + phase counted in cycles, the time it has
    been on since u = 0 is G(u) / f, G(u) = floor(u) * duty + min(frac(u), duty); so the mean over the
    window is (G(u_b) - G(u_a)) / (f * exposure): the box filter in closed form.
    """
    u_a = frequency_hz * t_start_s + phase_cycles
    u_b = u_a + frequency_hz * exposure_s
    whole_a, whole_b = np.floor(u_a), np.floor(u_b)
    on_a = whole_a * duty + np.minimum(u_a - whole_a, duty)
    on_b = whole_b * duty + np.minimum(u_b - whole_b, duty)
    fraction: FloatArray = (on_b - on_a) / (frequency_hz * exposure_s)
    return np.clip(fraction, 0.0, 1.0)


def _gauss_tail(z: FloatArray) -> FloatArray:
    """P(N(0, 1) > z): the share of a Gaussian blur kernel that falls beyond a straight edge z sigmas away.

    0.5 erfc(x), x = |z| / sqrt(2), by Abramowitz & Stegun 7.1.26 (absolute error < 1.5e-7); numpy has no
    erf and scipy is not a dependency of the drivers.
    """
    x = np.abs(z) * (1.0 / math.sqrt(2.0))
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    upper = 0.5 * poly * np.exp(-x * x)
    result: FloatArray = np.where(z >= 0.0, upper, 1.0 - upper)
    return result


def _mount_rotation(roll_rad: float, pitch_rad: float) -> FloatArray:
    """Ry(pitch) Rx(roll): the camera's tilt relative to a level frame turned by the yaw."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    result: FloatArray = ry @ rx
    return result


def _quadratic_weights(s: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Lagrange weights on nodes s = -1, 0, 1 (exact for constant acceleration over the readout)."""
    return 0.5 * s * (s - 1.0), 1.0 - s * s, 0.5 * s * (s + 1.0)


def readout_time_s(camera: CameraModel) -> float:
    """From the first row's exposure start to the last row's exposure end."""
    return (camera.sensor_height_px - 1) * camera.t_row_s + camera.exposure_s


def row_time_s(camera: CameraModel, t0_s: float, v_sensor: float) -> float:
    """Exposure centre of (continuous) sensor row ``v_sensor`` in a frame starting at ``t0_s``."""
    return t0_s + v_sensor * camera.t_row_s + 0.5 * camera.exposure_s


def pose_times_s(camera: CameraModel, t0_s: float) -> tuple[float, float, float]:
    """The times the renderer takes the robot's pose at: the exposure centres of the first, middle and last
    sensor rows (rows in between are interpolated quadratically)."""
    rows = camera.sensor_height_px
    return (
        row_time_s(camera, t0_s, 0.0),
        row_time_s(camera, t0_s, (rows - 1) / 2.0),
        row_time_s(camera, t0_s, rows - 1.0),
    )


class RollingShutterRenderer:
    """Renders frames of one camera looking at one set of LEDs.

    Args:
        camera: the true camera (its principal point and distortion are the truth, not the agent's belief).
        leds: the true LED positions and modulations.
        mount: where the camera sits on the robot base; its roll and pitch are the mounting tilt.
        tilt_rad: extra (roll, pitch) on top of the mount's, e.g. the world's ``errors.camera_tilt_rad``.
        gain_db: analog gain ahead of the ADC: it scales signal and shot noise in DN, not read noise.
        seed: seeds the LEDs' free-running PWM phases and all noise, so a sequence of frames is repeatable.
        scene: ambient light, stray bright objects and occluders (``World.scene``); none by default.

    Each LED's ``brightness`` scales its light, a ``dead`` one is not drawn, and its PWM frequency drifts
    by ``frequency_drift_hz_per_s`` (from the first frame on) and a random walk of
    ``frequency_walk_hz_per_sqrt_s``; the camera's ``jpeg_quality`` compresses every frame.

    Not thread-safe: one renderer per camera thread. It keeps its scratch buffers between frames.
    """

    def __init__(
        self,
        camera: CameraModel,
        leds: Sequence[Led],
        mount: Mount | None = None,
        *,
        tilt_rad: tuple[float, float] = (0.0, 0.0),
        gain_db: float = 0.0,
        seed: int = 0,
        scene: Scene | None = None,
    ) -> None:
        self.camera = camera
        self.leds = tuple(leds)
        self.scene = scene = Scene() if scene is None else scene
        self.mount = mount = Mount() if mount is None else mount
        self.roll_rad = mount.roll_rad + tilt_rad[0]
        self.pitch_rad = mount.pitch_rad + tilt_rad[1]
        self._rng = np.random.default_rng(seed)
        self._phases = self._rng.uniform(0.0, 1.0, len(self.leds))
        # Emitters: the LEDs, then the stray lights (indices from len(leds) on); the stray lights' flicker
        # phases come after the LEDs' so that a world without them draws the same noise as before.
        stray = scene.stray_lights
        self._stray_phases = self._rng.uniform(0.0, 1.0, len(stray)) if stray else np.zeros(0)
        self._led_x = np.array([e.x_m for e in self.leds] + [e.x_m for e in stray], dtype=np.float64)
        self._led_y = np.array([e.y_m for e in self.leds] + [e.y_m for e in stray], dtype=np.float64)
        self._led_z = np.array([e.z_m for e in self.leds] + [e.z_m for e in stray], dtype=np.float64)
        self._led_r = np.array(
            [led.diameter_m / 2.0 for led in self.leds] + [s.extent_m for s in stray], dtype=np.float64
        )
        self._lit = np.array([not led.dead for led in self.leds] + [True] * len(stray), dtype=bool)
        self._t_epoch: float | None = None
        # Frequency drift: each LED's random-walk offset (Hz), its integral (cycles) and when it was last
        # advanced (s from the epoch), from a generator of its own (the noise stays as without drift).
        self._walk_rng = np.random.default_rng([seed, 19])
        self._walk_hz = np.zeros(len(self.leds))
        self._walk_cycles = np.zeros(len(self.leds))
        self._walk_at_s = np.zeros(len(self.leds))

        sw, sh = camera.sensor_width_px, camera.sensor_height_px
        ow, oh = camera.output_width_px, camera.output_height_px
        self._cols = nearest_indices(sw, ow)
        self._rows = nearest_indices(sh, oh)
        # Sensor coordinate = a * output coordinate + b, the least-squares line through the selection.
        self._ax, self._bx = (float(v) for v in np.polyfit(np.arange(ow), self._cols, 1))
        self._ay, self._by = (float(v) for v in np.polyfit(np.arange(oh), self._rows, 1))

        self._f_px = camera.focal_length_px
        self._cx, self._cy = camera.principal_point_px
        self._dist = np.asarray(camera.distortion, dtype=np.float64)
        self._distorted = bool(np.any(self._dist != 0.0))
        self._tilt = _mount_rotation(self.roll_rad, self.pitch_rad)
        self._tilt_t = self._tilt.T.copy()
        self._ray_x, self._ray_y, self._ray_z, self._vignette = self._ray_grid()

        # Photo-electrons <-> DN: the ADC spans the full well above the black level at 0 dB.
        self._dn_per_e = (255.0 - camera.black_level_dn) / camera.full_well_e * 10.0 ** (gain_db / 20.0)
        self._peak_e = camera.led_peak_dn / ((255.0 - camera.black_level_dn) / camera.full_well_e)
        # Ambient light: photo-electrons every pixel collects besides the LEDs.
        self._ambient_e = scene.ambient_dn / ((255.0 - camera.black_level_dn) / camera.full_well_e)
        # Pixel box (variance 1/12 px^2) and lens PSF add; the edge profile uses the total.
        self._sigma_px = math.sqrt(camera.blur_sigma_px**2 + 1.0 / 12.0)

        # Expected photo-electrons of the kept pixels, and of the sensor rows just above and below them (for
        # blooming); only LED boxes are ever non-zero, and they are zeroed again after each frame.
        self._signal = np.zeros((oh, ow), dtype=np.float32)
        self._signal_up = np.zeros((oh, ow), dtype=np.float32)
        self._signal_down = np.zeros((oh, ow), dtype=np.float32)
        npix = oh * ow
        self._pool = self._background(npix + max(npix // 4, 1024))
        self._pool_cursor = 0

    @classmethod
    def for_world(cls, world: World, *, gain_db: float = 0.0, seed: int = 0) -> RollingShutterRenderer:
        """The world's true camera: its mount plus the tilt error the world carries, and its scene."""
        return cls(
            world.camera,
            world.leds,
            world.robot.camera_mount,
            tilt_rad=world.errors.camera_tilt_rad,
            gain_db=gain_db,
            seed=seed,
            scene=world.scene,
        )

    # -- what the renderer knows -----------------------------------------------------------------------
    @property
    def output_intrinsics(self) -> OutputIntrinsics:
        cam = self.camera
        return OutputIntrinsics(
            self._f_px / self._ax,
            self._f_px / self._ay,
            (self._cx - self._bx) / self._ax,
            (self._cy - self._by) / self._ay,
            cam.output_width_px,
            cam.output_height_px,
        )

    @property
    def readout_s(self) -> float:
        """From the first row's exposure start to the last row's exposure end."""
        return readout_time_s(self.camera)

    @property
    def selected_rows(self) -> IndexArray:
        return self._rows.copy()

    @property
    def selected_cols(self) -> IndexArray:
        return self._cols.copy()

    def sensor_to_output(self, u_s: float, v_s: float) -> tuple[float, float]:
        return (u_s - self._bx) / self._ax, (v_s - self._by) / self._ay

    def row_time_s(self, t0_s: float, v_sensor: float) -> float:
        """Exposure centre of (continuous) sensor row ``v_sensor`` in a frame starting at ``t0_s``."""
        return row_time_s(self.camera, t0_s, v_sensor)

    # -- set-up ----------------------------------------------------------------------------------------
    def _ray_grid(self) -> tuple[Float32Array, Float32Array, Float32Array, Float32Array]:
        """Viewing ray of every surviving pixel in the level camera frame (tilt applied, yaw not), and its
        cos^4 vignetting. Only the pixels the resize keeps are ever looked at, so only they are stored."""
        cols = self._cols.astype(np.float64)
        rows = self._rows.astype(np.float64)
        if self._distorted:
            grid = np.stack(np.meshgrid(cols, rows), axis=-1).reshape(-1, 1, 2)
            k = np.array([[self._f_px, 0.0, self._cx], [0.0, self._f_px, self._cy], [0.0, 0.0, 1.0]])
            criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-12)
            # R = I, P = I: the result stays in normalised coordinates (x/z, y/z).
            eye = np.eye(3)
            norm = np.asarray(cv2.undistortPointsIter(grid, k, self._dist, eye, eye, criteria))
            xn = norm[:, 0, 0].reshape(rows.size, cols.size)
            yn = norm[:, 0, 1].reshape(rows.size, cols.size)
        else:
            xn, yn = np.meshgrid((cols - self._cx) / self._f_px, (rows - self._cy) / self._f_px)
        vignette = 1.0 / (1.0 + xn * xn + yn * yn) ** 2
        t = self._tilt
        ray_x = t[0, 0] * xn + t[0, 1] * yn + t[0, 2]
        ray_y = t[1, 0] * xn + t[1, 1] * yn + t[1, 2]
        ray_z = t[2, 0] * xn + t[2, 1] * yn + t[2, 2]
        # float32 halves the memory; its 6e-8 relative error is a micrometre on the LED plane.
        return (
            ray_x.astype(np.float32),
            ray_y.astype(np.float32),
            ray_z.astype(np.float32),
            vignette.astype(np.float32),
        )

    def _background(self, n: int) -> ImageU8:
        cam = self.camera
        noise = self._rng.standard_normal(n, dtype=np.float32)
        if self._ambient_e > 0.0:
            # Ambient light: its level above black, and its shot noise (Poisson, as a Gaussian) with the
            # read noise.
            ambient_dn = self._ambient_e * self._dn_per_e
            noise *= math.sqrt(cam.read_noise_dn**2 + ambient_dn * self._dn_per_e)
            noise += cam.black_level_dn + ambient_dn
        else:
            noise *= cam.read_noise_dn
            noise += cam.black_level_dn
        return np.clip(np.rint(noise), 0, 255).astype(np.uint8)

    # -- projection ------------------------------------------------------------------------------------
    def _distort(self, xn: FloatArray, yn: FloatArray) -> tuple[FloatArray, FloatArray]:
        """OpenCV's radial-tangential model (y alike):
        x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)."""
        if not self._distorted:
            return xn, yn
        k1, k2, p1, p2, k3 = self._dist
        r2 = xn * xn + yn * yn
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
        yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
        return xd, yd

    def project(
        self,
        px: FloatArray,
        py: FloatArray,
        pz: FloatArray,
        cam_x: FloatArray | float,
        cam_y: FloatArray | float,
        yaw: FloatArray | float,
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Sensor (u, v) of world points seen from camera positions (x, y, mount height) and yaws
        (arrays broadcast together), and each point's depth along the optical axis (<= 0: behind)."""
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy, dz = px - cam_x, py - cam_y, pz - self.mount.z_m
        # Undo the yaw, then the tilt: p_camera = T^T Rz(-yaw) (p - c).
        lx, ly = c * dx + s * dy, -s * dx + c * dy
        t = self._tilt_t
        xc = t[0, 0] * lx + t[0, 1] * ly + t[0, 2] * dz
        yc = t[1, 0] * lx + t[1, 1] * ly + t[1, 2] * dz
        zc = t[2, 0] * lx + t[2, 1] * ly + t[2, 2] * dz
        with np.errstate(divide="ignore", invalid="ignore"):
            xn, yn = xc / zc, yc / zc
        xd, yd = self._distort(xn, yn)
        return self._cx + self._f_px * xd, self._cy + self._f_px * yd, zc

    # -- one frame -------------------------------------------------------------------------------------
    def render(
        self,
        pose_at: Callable[[float], Pose2D],
        t0_s: float,
        out: ImageU8 | None = None,
        covers: Sequence[LedCover] = (),
    ) -> RenderedFrame:
        """Render the frame whose first row starts exposing at ``t0_s``.

        ``pose_at(t)`` gives the robot base's true pose at time ``t`` (three calls per frame: first, middle
        and last row; rows in between are interpolated quadratically). ``out``, if given, receives the image
        (shape (output height, output width), uint8) and is returned in the result. ``covers`` hide parts
        of LEDs in this frame (occlusion), besides the scene's occluders that hide them at ``t0_s``.
        """
        cam = self.camera
        oh, ow = cam.output_height_px, cam.output_width_px
        if out is None:
            out = np.empty((oh, ow), dtype=np.uint8)
        elif out.shape != (oh, ow) or out.dtype != np.uint8:
            raise ValueError(f"out must be uint8 of shape {(oh, ow)}, got {out.dtype} {out.shape}")
        if self._t_epoch is None:
            # PWM phase is computed relative to this epoch so large clock values keep float precision.
            self._t_epoch = t0_s

        t_first, t_mid, t_last = pose_times_s(cam, t0_s)
        p_first, p_mid, p_last = pose_at(t_first), pose_at(t_mid), pose_at(t_last)
        knots = self._camera_knots(p_first, p_mid, p_last)

        covers = [
            *covers,
            *(
                LedCover(o.led_index, o.angle_rad, o.fraction)
                for o in self.scene.occluders
                if o.hides_at(t0_s)
            ),
        ]
        self._draw_background(out)
        truths, placed = self._place_leds(t0_s, knots)
        for index, box in placed:
            self._accumulate(index, t0_s, knots, *box, covers=[c for c in covers if c.led_index == index])
        for r0, r1, c0, c1 in _merge_rects([box for _, box in placed]):
            self._expose(out, r0, r1, c0, c1)
        if cam.jpeg_quality > 0:
            _compress(out, cam.jpeg_quality)

        mid_cam = knots[1]
        camera_pose = CameraPose(
            mid_cam[0], mid_cam[1], self.mount.z_m, _wrap(mid_cam[2]), self.roll_rad, self.pitch_rad
        )
        return RenderedFrame(out, FrameTruth(t0_s, t_mid, p_mid, camera_pose, tuple(truths)))

    def _camera_knots(self, *poses: Pose2D) -> tuple[tuple[float, float, float], ...]:
        """Camera (x, y, yaw) at the first, middle and last row; yaw unwrapped about the middle one."""
        m = self.mount
        knots = []
        for p in poses:
            c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
            knots.append(
                (p.x_m + c * m.x_m - s * m.y_m, p.y_m + s * m.x_m + c * m.y_m, p.yaw_rad + m.yaw_rad)
            )
        mid_yaw = knots[1][2]
        return tuple((x, y, mid_yaw + _wrap(yaw - mid_yaw)) for x, y, yaw in knots)

    def _camera_at_rows(
        self, knots: tuple[tuple[float, float, float], ...], v_sensor: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        half = (self.camera.sensor_height_px - 1) / 2.0
        s = (v_sensor - half) / half if half > 0 else np.zeros_like(v_sensor)
        w0, w1, w2 = _quadratic_weights(s)
        (x0, y0, a0), (x1, y1, a1), (x2, y2, a2) = knots
        return w0 * x0 + w1 * x1 + w2 * x2, w0 * y0 + w1 * y1 + w2 * y2, w0 * a0 + w1 * a1 + w2 * a2

    def _place_leds(
        self, t0_s: float, knots: tuple[tuple[float, float, float], ...]
    ) -> tuple[list[LedTruth], list[tuple[int, tuple[int, int, int, int]]]]:
        """Truth of every lit LED with at least one kept pixel, and the surviving-pixel box
        (r0, r1, c0, c1) of every emitter (lit LEDs and stray lights) with one, by emitter index.

        Vectorised over LEDs: a frame costs a fixed handful of numpy calls whatever the LED count.
        """
        cam = self.camera
        if self._led_x.size == 0:
            return [], []
        px, py, pz, radius_m = self._led_x, self._led_y, self._led_z, self._led_r
        mid = knots[1]
        u_mid, v_mid, depth = self.project(px, py, pz, mid[0], mid[1], mid[2])
        # Cheap cull with the mid pose; generous (a fifth of the frame) for motion and distortion.
        slack = 0.2 * max(cam.sensor_width_px, cam.sensor_height_px) + np.where(
            depth > 1e-3, radius_m * self._f_px / np.maximum(depth, 1e-3), 0.0
        )
        with np.errstate(invalid="ignore"):
            keep = (
                self._lit
                & (depth > 1e-3)
                & (u_mid > -slack)
                & (u_mid < cam.sensor_width_px - 1 + slack)
                & (v_mid > -slack)
                & (v_mid < cam.sensor_height_px - 1 + slack)
            )
        idx = np.flatnonzero(keep)
        if idx.size == 0:
            return [], []
        px, py, pz, radius_m = px[idx], py[idx], pz[idx], radius_m[idx]
        u_mid, v_mid = u_mid[idx], v_mid[idx]

        # The row through each LED centre fixes when its image was taken: v = v(pose(t(v))) is a
        # contraction (the image moves far less than a row per row time), so a few iterations converge.
        u_c, v_c = u_mid, v_mid
        for _ in range(_CENTRE_ITERATIONS):
            xs, ys, yaws = self._camera_at_rows(knots, v_c)
            u_c, v_c, _ = self.project(px, py, pz, xs, ys, yaws)

        # Bounding boxes: the rim projected with the pose of the centre row, widened by how far the image
        # moves between that row and the rim's top and bottom rows, and by the blur margin.
        xs, ys, yaws = self._camera_at_rows(knots, v_c)
        angles = np.linspace(0.0, 2.0 * math.pi, _RIM_POINTS, endpoint=False)
        ru, rv, rdepth = self.project(
            px[:, None] + radius_m[:, None] * np.cos(angles),
            py[:, None] + radius_m[:, None] * np.sin(angles),
            pz[:, None],
            xs[:, None],
            ys[:, None],
            yaws[:, None],
        )
        xs2, ys2, yaws2 = self._camera_at_rows(knots, np.concatenate([v_c - 64.0, v_c + 64.0]))
        n = idx.size
        du, dv, _ = self.project(np.tile(px, 2), np.tile(py, 2), np.tile(pz, 2), xs2, ys2, yaws2)
        drift_per_row = np.hypot(du[n:] - du[:n], dv[n:] - dv[:n]) / 128.0
        half_height = (rv.max(axis=1) - rv.min(axis=1)) / 2.0
        margin = _BLUR_SIGMAS * self._sigma_px + 2.0 + 1.5 * drift_per_row * (half_height + 2.0)
        r0s = np.searchsorted(self._rows, rv.min(axis=1) - margin, side="left")
        r1s = np.searchsorted(self._rows, rv.max(axis=1) + margin, side="left")
        c0s = np.searchsorted(self._cols, ru.min(axis=1) - margin, side="left")
        c1s = np.searchsorted(self._cols, ru.max(axis=1) + margin, side="left")
        valid = (
            (rdepth > 1e-3).all(axis=1)
            & np.isfinite(ru).all(axis=1)
            & np.isfinite(rv).all(axis=1)
            & np.isfinite(u_c)
            & np.isfinite(v_c)
            & (r1s > r0s)
            & (c1s > c0s)
        )

        truths: list[LedTruth] = []
        boxes: list[tuple[int, tuple[int, int, int, int]]] = []
        height = pz - self.mount.z_m
        for k in np.flatnonzero(valid):
            index = int(idx[k])
            boxes.append((index, (int(r0s[k]), int(r1s[k]), int(c0s[k]), int(c1s[k]))))
            if index >= len(self.leds):
                continue  # a stray light: drawn, but no LED of the world
            centre = self.sensor_to_output(float(u_c[k]), float(v_c[k]))
            centre_mid = self.sensor_to_output(float(u_mid[k]), float(v_mid[k]))
            in_image = (
                -0.5 <= centre[0] <= cam.output_width_px - 0.5
                and -0.5 <= centre[1] <= cam.output_height_px - 0.5
            )
            radius_px = float(radius_m[k]) * self._f_px / float(height[k]) / self._ax
            truths.append(
                LedTruth(
                    index,
                    self.leds[index].id,
                    centre,
                    centre_mid,
                    radius_px,
                    self.row_time_s(t0_s, float(v_c[k])),
                    in_image,
                )
            )
        return truths, boxes

    def _draw_background(self, out: ImageU8) -> None:
        npix = out.size
        pool = self._pool
        chunk = max(int(pool.size * _POOL_REFRESH_FRACTION), 1)
        start = self._pool_cursor
        stop = min(start + chunk, pool.size)
        pool[start:stop] = self._background(stop - start)
        self._pool_cursor = 0 if stop >= pool.size else stop
        offset = int(self._rng.integers(0, pool.size - npix + 1))
        np.copyto(out.reshape(-1), pool[offset : offset + npix])

    def _accumulate(
        self,
        index: int,
        t0_s: float,
        knots: tuple[tuple[float, float, float], ...],
        r0: int,
        r1: int,
        c0: int,
        c1: int,
        covers: Sequence[LedCover] = (),
    ) -> None:
        """Add emitter ``index``'s expected photo-electrons (an LED, or from ``len(leds)`` on a stray light)
        to the surviving pixels of its box (and, for blooming, what the sensor rows just above and below
        them collect)."""
        cam = self.camera
        if any(cover.fraction >= 1.0 for cover in covers):
            return  # hidden whole (its blurred rim too: the cover is wider than the disk)
        stray = self.scene.stray_lights[index - len(self.leds)] if index >= len(self.leds) else None
        rows = self._rows[r0:r1].astype(np.float64)
        cam_x, cam_y, yaw = self._camera_at_rows(knots, rows)
        led_x, led_y = float(self._led_x[index]), float(self._led_y[index])
        height = float(self._led_z[index]) - self.mount.z_m
        radius_m = float(self._led_r[index])

        # Where each pixel's ray meets the LED plane, relative to the LED centre, in the camera's yaw frame:
        # rho = | lambda m_xy - Rz(-psi)(L - c) |, lambda = H / m_z (m: the tilted ray, c: the row's camera).
        dx, dy = led_x - cam_x, led_y - cam_y
        cos_y, sin_y = np.cos(yaw), np.sin(yaw)
        ex = (cos_y * dx + sin_y * dy)[:, None]
        ey = (-sin_y * dx + cos_y * dy)[:, None]
        ray_z = self._ray_z[r0:r1, c0:c1]
        lam = height / np.maximum(ray_z, 1e-9)
        ox = lam * self._ray_x[r0:r1, c0:c1] - ex
        oy = lam * self._ray_y[r0:r1, c0:c1] - ey

        if stray is not None and stray.shape == "rectangle":
            # Signed distance to the rectangle's outline, in its own frame (turned by its yaw less the row's).
            turn = stray.yaw_rad - yaw
            ct, st = np.cos(turn)[:, None], np.sin(turn)[:, None]
            qx = np.abs(ct * ox + st * oy) - stray.width_m / 2.0
            qy = np.abs(-st * ox + ct * oy) - stray.length_m / 2.0
            outside = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0))
            signed = outside + np.minimum(np.maximum(qx, qy), 0.0)
            coverage = _gauss_tail(signed * (self._f_px / lam) / self._sigma_px)
            shape = coverage * self._vignette[r0:r1, c0:c1]
        else:
            # Blurred outline: signed distance to the rim in image pixels, through the Gaussian edge profile.
            rho = np.sqrt(ox * ox + oy * oy)
            edge_px = (rho - radius_m) * (self._f_px / lam)
            coverage = _gauss_tail(edge_px / self._sigma_px)
            for cover in covers:
                # The cover's edge is the line (p - centre) . n = R (1 - 2 fraction) in the LED plane; n
                # turned into each row's yaw frame like (ox, oy). Visible where the signed distance is < 0.
                nx, ny = math.cos(cover.angle_rad), math.sin(cover.angle_rad)
                ncx = (cos_y * nx + sin_y * ny)[:, None]
                ncy = (-sin_y * nx + cos_y * ny)[:, None]
                beyond = ox * ncx + oy * ncy - radius_m * (1.0 - 2.0 * cover.fraction)
                coverage = coverage * _gauss_tail(beyond * (self._f_px / lam) / self._sigma_px)
            if stray is None:
                rel = np.minimum(rho / radius_m, 1.0)
                shape = coverage * (1.0 - cam.radial_falloff * rel * rel) * self._vignette[r0:r1, c0:c1]
            else:
                shape = coverage * self._vignette[r0:r1, c0:c1]

        t_start = t0_s - (self._t_epoch or 0.0) + rows * cam.t_row_s
        if stray is None:
            led = self.leds[index]
            brightness = led.brightness
            frequency, duty = led.frequency_hz, led.duty
            phase = float(self._phases[index])
            if led.frequency_drift_hz_per_s or led.frequency_walk_hz_per_sqrt_s:
                frequency, phase = self._drifted(index, t0_s - (self._t_epoch or 0.0))
                t_start = rows * cam.t_row_s
        else:
            brightness = stray.brightness
            frequency, duty = stray.flicker_hz, stray.flicker_duty
            phase = float(self._stray_phases[index - len(self.leds)])
        if frequency > 0.0:
            on_here = pwm_exposure_fraction(t_start, cam.exposure_s, frequency, duty, phase)
            on_up = pwm_exposure_fraction(t_start - cam.t_row_s, cam.exposure_s, frequency, duty, phase)
            on_down = pwm_exposure_fraction(t_start + cam.t_row_s, cam.exposure_s, frequency, duty, phase)
        else:
            on_here = on_up = on_down = np.ones_like(rows)  # a steady light
        signal = (self._peak_e * brightness) * shape
        self._signal[r0:r1, c0:c1] += signal * on_here[:, None]
        self._signal_up[r0:r1, c0:c1] += signal * on_up[:, None]
        self._signal_down[r0:r1, c0:c1] += signal * on_down[:, None]

    def _drifted(self, index: int, tau_s: float) -> tuple[float, float]:
        """LED ``index``'s true PWM frequency at ``tau_s`` seconds from the epoch, and its phase then in
        cycles (0..1): f(t) = f0 + a t + w(t), w a random walk; the phase is the integral of f. Within one
        frame's readout the frequency is taken as constant (a drift of even 100 Hz/s moves it 5 Hz in 50 ms,
        far below what one frame resolves)."""
        led = self.leds[index]
        if led.frequency_walk_hz_per_sqrt_s > 0.0 and tau_s > self._walk_at_s[index]:
            dt = tau_s - self._walk_at_s[index]
            before = self._walk_hz[index]
            step = led.frequency_walk_hz_per_sqrt_s * math.sqrt(dt) * self._walk_rng.standard_normal()
            after = before + step
            self._walk_cycles[index] += 0.5 * (before + after) * dt
            self._walk_hz[index] = after
            self._walk_at_s[index] = tau_s
        a = led.frequency_drift_hz_per_s
        frequency = led.frequency_hz + a * tau_s + float(self._walk_hz[index])
        cycles = (
            float(self._phases[index])
            + led.frequency_hz * tau_s
            + 0.5 * a * tau_s * tau_s
            + float(self._walk_cycles[index])
        )
        return max(frequency, 1.0), cycles - math.floor(cycles)

    def _expose(self, out: ImageU8, r0: int, r1: int, c0: int, c1: int) -> None:
        """Turn expected electrons into DN over one box: blooming, shot noise, full well, read noise, ADC."""
        cam = self.camera
        full_well = cam.full_well_e
        box = np.s_[r0:r1, c0:c1]
        signal = self._signal[box]
        spill = cam.bloom_fraction * (
            np.maximum(self._signal_up[box] - full_well, 0.0)
            + np.maximum(self._signal_down[box] - full_well, 0.0)
        )
        if self._ambient_e > 0.0:
            spill = spill + self._ambient_e
        electrons = self._rng.poisson(signal + spill).astype(np.float64)
        np.minimum(electrons, full_well, out=electrons)
        dn = cam.black_level_dn + self._dn_per_e * electrons
        if cam.read_noise_dn > 0:
            dn += cam.read_noise_dn * self._rng.standard_normal(dn.shape)
        out[box] = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
        self._signal[box] = 0.0
        self._signal_up[box] = 0.0
        self._signal_down[box] = 0.0


def _compress(image: ImageU8, quality: int) -> None:
    """JPEG-compress ``image`` in place at ``quality`` (1..100), as a camera or a network link that sends
    JPEG frames does: 8x8 block artefacts, ringing at the stripes' edges, smoothed noise."""
    ok, encoded = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("cv2.imencode could not encode the frame as JPEG")
    decoded = cv2.imdecode(encoded, cv2.IMREAD_GRAYSCALE)
    if decoded is None:
        raise RuntimeError("cv2.imdecode could not decode the JPEG frame")
    np.copyto(image, decoded)


def _merge_rects(rects: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Merge overlapping (r0, r1, c0, c1) boxes until none overlap, so every pixel is exposed once."""
    merged = list(rects)
    changed = True
    while changed:
        changed = False
        for i in range(len(merged)):
            for j in range(i + 1, len(merged)):
                a, b = merged[i], merged[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    merged[i] = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    del merged[j]
                    changed = True
                    break
            if changed:
                break
    return merged


def _wrap(angle_rad: float) -> float:
    return math.atan2(math.sin(angle_rad), math.cos(angle_rad))
