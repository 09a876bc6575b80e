"""The VLP pipeline: frame in, pose of the robot base (or the reason there is none) out.

Per frame: track the known LEDs in their windows (``agent.vlp.track``), look for new ones when needed
(``agent.vlp.detect``: the whole frame when no LED is held; while fewer than two are usable, and every
``redetect_interval`` frames, one band of rows a frame, the search spread over frames so that no frame pays
for all of it; and at the places the map says an LED should have come into view), decode the stripes of
every fully visible LED and vote for its id (``agent.vlp.decode``), turn the centres into level rays
(``agent.vlp.geometry``: the calibrated principal point, undistortion, tilt from the mount and the IMU), and
solve the pose (``agent.vlp.solve``: closed form, then Gauss-Newton with the rolling-shutter row times).
The lens pose is moved to the base with the mount, and the calibration's residual correction is applied.

A bad frame never raises: wrong size or type, black, saturated, no LED, one LED each give a ``NoFix`` with a
reason (or, with one LED and a yaw prior, a fix flagged ``degraded``).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from agent.vlp.calibration import VlpCalibration
from agent.vlp.decode import DecoderConfig, LedRequest, RowTiming, StripeDecoder
from agent.vlp.detect import (
    Blob,
    DetectorConfig,
    background_level,
    find_blobs,
    measure_blob,
    search_bands,
)
from agent.vlp.geometry import lens_offset_level, level_plane_points, level_rotation
from agent.vlp.integrity import ProtectionInputs
from agent.vlp.model import (
    NO_WORK,
    AssociationWork,
    CameraIntrinsics,
    CameraMount,
    LedMap,
    LedObservation,
    Motion,
    NoFix,
    PosePrior,
    StageTimings,
    Tilt,
    VlpFix,
    VlpResult,
)
from agent.vlp.signatures import check_signatures
from agent.vlp.solve import (
    LedRay,
    NoSolution,
    PoseSolution,
    SolverConfig,
    single_led_position,
    solve_pose,
)
from agent.vlp.track import FULL, LedTrack, LedTracker, TrackerConfig

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
Covariance3 = tuple[tuple[float, float, float], tuple[float, float, float], tuple[float, float, float]]

# The yaw error bound at the fault-free risk, for the lens-to-base part of the protection level (3.3 sigma:
# 1e-3 two-sided).
_K_YAW = 3.29
# Two signatures of the map within both of these are close (the world file warns of them; docs/world.md):
# the duty does not tell them apart, and a few per cent of frequency error (row time, drift) swaps them.
_CLOSE_FREQUENCY_HZ = 200.0
_CLOSE_DUTY = 0.1
# The stage timings of a result before the frame's are filled in (immutable, so one serves every frame).
_NO_TIMINGS = StageTimings()

__all__ = ["VlpConfig", "VlpPipeline"]


@dataclass(frozen=True, slots=True)
class VlpConfig:
    """``detector``: None derives it from the map (the smallest and largest LED disk the camera can see).
    ``redetect_interval``: frames between full-frame searches while tracking, each spread over
    ``search_bands`` frames (one band of rows a frame; also while fewer than two LEDs are usable, in a
    cycle; a frame with no LED tracked is searched whole); ``predict_interval``: frames
    between looks at where the map says an untracked LED should have come into view (0: never);
    ``verify_interval``: a fully visible LED whose settled id its last decoded frame confirmed is decoded
    every this many frames, every such LED on the same frame (1: every frame); one that is not settled, or
    whose stripes last disagreed, on every frame. ``fft_check_interval``: decoded frames between FFT
    cross-checks of a settled LED's period.
    ``prior_max_age_s``: how long the last fix (or a given prior) serves as the prior (its uncertainty grows
    at ``prior_growth_mps``).
    ``motion_max_gap_s``: the velocity for the rolling-shutter correction is taken from the last two fixes
    only when they are this close in time. ``saturated_fraction``: a frame with more pixels at 250+ is
    saturated. A centre's standard deviation is max(``measurement_sigma_px``, ``outline_sigma_px`` /
    sqrt(edge points)): on the renderer's frames 0.3 px with 8 outline points, under 0.1 px with 70.
    ``single_led_max_yaw_sigma_rad``: a one-LED fix is made only from a yaw prior at least this good (it is
    off by the yaw's error times the LED's horizontal distance)."""

    detector: DetectorConfig | None = None
    decoder: DecoderConfig = field(default_factory=DecoderConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    redetect_interval: int = 30
    search_bands: int = 4
    predict_interval: int = 4
    fft_check_interval: int = 4
    verify_interval: int = 3
    estimate_motion: bool = True
    motion_max_gap_s: float = 0.2
    max_speed_mps: float = 2.0
    max_yaw_rate_radps: float = 4.0
    prior_max_age_s: float = 1.0
    prior_growth_mps: float = 1.0
    saturated_fraction: float = 0.5
    measurement_sigma_px: float = 0.08
    single_led_max_yaw_sigma_rad: float = math.radians(5.0)
    outline_sigma_px: float = 0.85


@dataclass
class _LastFix:
    time_s: float
    lens: tuple[float, float, float]
    base: tuple[float, float, float]
    previous: tuple[float, tuple[float, float, float]] | None = field(default=None)


class VlpPipeline:
    """Frames of one camera -> VLP fixes. Not thread-safe: one pipeline per camera loop.

    Args:
        intrinsics: the camera as calibrated (output resolution); a ``calibration`` replaces its principal
            point.
        led_map: the surveyed LEDs.
        mount: where the lens is on the base (and its known tilt).
        config: tuning (defaults suit the MV-UB300 set-up of the reference system).
        calibration: rotation-centre and residual calibration (``agent.vlp.calibration``).
    """

    def __init__(
        self,
        intrinsics: CameraIntrinsics,
        led_map: LedMap,
        mount: CameraMount | None = None,
        config: VlpConfig | None = None,
        calibration: VlpCalibration | None = None,
    ) -> None:
        self.nominal = intrinsics
        self.calibration = calibration
        self.intrinsics = calibration.intrinsics(intrinsics) if calibration is not None else intrinsics
        self.led_map = led_map
        self.mount = mount if mount is not None else CameraMount()
        if calibration is not None:
            # The calibrated tilt turns the rays (with the IMU's), instead of a principal point moved for it.
            self.mount = calibration.mount(self.mount)
        self.config = config = config if config is not None else VlpConfig()
        self.signatures = led_map.signatures
        # For each signature, the map's others close to it (flag ``close-signature``).
        self._rivals = _close_rivals(
            np.array([sig.frequency_hz for sig in self.signatures], dtype=np.float64),
            np.array([sig.duty for sig in self.signatures], dtype=np.float64),
        )
        # Each LED's survey sigma where the map states it (else the solver's map_sigma_m); None: none does.
        self._map_sigmas_m = led_map.map_sigmas_m(config.solver.map_sigma_m)
        self.detector = config.detector if config.detector is not None else self._detector_for_map()
        self.decoder = StripeDecoder(config.decoder, RowTiming.of(self.intrinsics))
        # What this camera cannot tell apart in the map, said once, at load (agent.vlp.signatures).
        self.signature_warnings = check_signatures(led_map, self.intrinsics, self.mount.z_m)
        for warning in self.signature_warnings:
            log.warning("LED map: %s", warning.message)
        self.tracker = LedTracker(self.detector, config.tracker)
        self._frames = 0
        self._last: _LastFix | None = None
        self._given: tuple[float, PosePrior] | None = None
        self._r_level: tuple[Tilt | None, FloatArray] | None = None
        self._offset: tuple[Tilt | None, FloatArray] | None = None
        self._bands_for: tuple[int, list[tuple[int, int]]] | None = None

    def _detector_for_map(self) -> DetectorConfig:
        """Detection tuned to the map: disks from half the smallest the camera can see (a partial cover) to
        2.5 times the largest, stripes bridged over the longest dark run any signature draws."""
        f = min(self.intrinsics.fx_px, self.intrinsics.fy_px)
        sizes = [f * led.diameter_m / max(led.z_m - self.mount.z_m, 0.05) for led in self.led_map.leds]
        # Disk diameters the camera can see: f D / h for every LED at its height above the lens.
        smallest = min(sizes) if sizes else 20.0
        largest = max(sizes) if sizes else 200.0
        # The longest dark stripe any signature draws, (1 - D) / (f t_row_eff) rows, must be bridged.
        t_eff = self.intrinsics.t_row_eff_s
        dark = max(((1.0 - s.duty) / (s.frequency_hz * t_eff) for s in self.signatures), default=0.0)
        return DetectorConfig(
            min_diameter_px=max(0.5 * smallest, 4.0),
            max_diameter_px=2.5 * largest + 10,
            bridge_px=max(dark + 2.0, 0.3 * smallest),
            radius_range_px=(0.45 * smallest, 0.55 * largest),
        )

    def reset(self) -> None:
        """Forget tracks and the last fix (e.g. after the robot was carried elsewhere)."""
        self.tracker.reset()
        self._last = None
        self._given = None
        self._frames = 0

    @property
    def tracks(self) -> list[LedTrack]:
        return list(self.tracker.tracks)

    # -- the frame ---------------------------------------------------------------------------------------
    def process(
        self,
        image: object,
        time_s: float,
        *,
        tilt: Tilt | None = None,
        prior: PosePrior | None = None,
        motion: Motion | None = None,
    ) -> VlpResult:
        """One frame (uint8, height x width of the intrinsics) taken at ``time_s`` (mid-readout).

        ``tilt``: the base's roll and pitch from the IMU. ``prior``: where the base roughly is (needed to tell
        repeated ids apart without a recent fix, and for a one-LED fix). ``motion``: the base's velocity (by
        default estimated from the last fixes) for the rolling-shutter correction.
        """
        t_start = time.perf_counter()
        bad = self._check_frame(image)
        if bad is not None:
            return NoFix(time_s, bad, (), StageTimings(total_ms=_ms(t_start)))
        assert isinstance(image, np.ndarray)
        frame: npt.NDArray[np.uint8] = image
        try:
            return self._process(frame, time_s, tilt, prior, motion, t_start)
        except Exception as exc:  # the loop must go on; the traceback goes to the log
            log.exception("VLP pipeline failed on a frame")
            self.tracker.reset()
            return NoFix(time_s, f"internal error: {exc}", (), StageTimings(total_ms=_ms(t_start)))

    def _level_rotation(self, tilt: Tilt | None) -> FloatArray:
        """R_level for this frame's tilt, kept while the tilt does not change (no IMU: always)."""
        if self._r_level is None or self._r_level[0] != tilt:
            self._r_level = (tilt, level_rotation(self.mount, tilt))
        return self._r_level[1]

    def _check_frame(self, image: object) -> str | None:
        intr = self.intrinsics
        if not isinstance(image, np.ndarray):
            return f"not an image: {type(image).__name__}"
        if image.dtype != np.uint8:
            return f"wrong pixel type {image.dtype} (mono8 expected)"
        if image.ndim != 2:
            return f"wrong shape {image.shape} (one channel expected)"
        if image.shape != (intr.height_px, intr.width_px):
            return (
                f"wrong size {image.shape[1]}x{image.shape[0]} "
                f"(the calibration is for {intr.width_px}x{intr.height_px})"
            )
        return None

    def _process(
        self,
        image: npt.NDArray[np.uint8],
        time_s: float,
        tilt: Tilt | None,
        prior: PosePrior | None,
        motion: Motion | None,
        t_start: float,
    ) -> VlpResult:
        cfg = self.config
        # 1. Track.
        t0 = time.perf_counter()
        self.tracker.step(image, time_s)
        t_track = time.perf_counter() - t0

        # 2. Acquire new LEDs: a full search on start, when fewer than two are held, and now and then; the
        # map's predictions in between.
        t0 = time.perf_counter()
        usable = sum(1 for t in self.tracker.tracks if t.centre_ok)
        bands = max(cfg.search_bands, 1)
        phase = self._frames % max(cfg.redetect_interval, bands)
        reason_if_none = "no LED in view"
        if not self.tracker.tracks:
            reason_if_none = self._search(image, time_s) or reason_if_none
        elif usable < 2 or phase < bands:
            # New LEDs come into view while others are held: the search is spread over frames, one band of
            # rows each (so no frame pays for a whole search), continuously while fewer than two are usable.
            self._search(image, time_s, self._bands(image.shape[0])[self._frames % bands])
        elif cfg.predict_interval > 0 and self._last is not None and self._frames % cfg.predict_interval == 0:
            self._search_predicted(image, time_s)
        self._frames += 1
        t_acquire = time.perf_counter() - t0

        # 3. Decode the stripes of every fully visible LED and vote.
        t0 = time.perf_counter()
        t_eff = self.intrinsics.t_row_eff_s
        features: dict[int, tuple[float, float, int]] = {}
        chosen: list[tuple[LedTrack, Blob]] = []
        requests: list[LedRequest] = []
        verify = max(cfg.verify_interval, 1)
        for track in self.tracker.tracks:
            blob = track.blob
            if track.visibility != FULL or blob is None:
                continue
            # A settled id that the last decoded frame, at most a few frames ago, agreed with is verified
            # every few frames, every settled LED on the same frame: a decode batch costs ~0.2 ms of calls
            # whatever its size, so one batch for all of them, and the frames between decode nothing. A new
            # LED, one back from a cover, one whose id is not confirmed yet, or one whose stripes last said
            # otherwise, is decoded on every frame.
            last = track.frame
            agreed = (
                last is not None
                and track.age - track.voted_at < verify
                and last.id is not None
                and last.id == self._settled_id(track)
                and track.confirmed(cfg.tracker)
            )
            if agreed and self._frames % verify != 0:
                continue
            # The track's radius (smoothed over frames) places the profile rows better than one frame's fit.
            # The FFT cross-check of the period: on every frame until the id settles, then every few.
            check = track.id_index is None or track.votes % max(cfg.fft_check_interval, 1) == 0
            requests.append((blob.centre_px, track.radius_px, blob.background_dn, check))
            chosen.append((track, blob))
        if chosen:
            # All LEDs of the frame in one batch: features, then every LED's vote.
            decoded = self.decoder.decode_many(image, requests, self.signatures, t_eff)
            for (track, blob), (feat, cls) in zip(chosen, decoded, strict=True):
                features[track.track_id] = (feat.frequency_hz, feat.duty, blob.area_px)
                track.vote(cls, cfg.tracker)
        t_decode = time.perf_counter() - t0

        # 4. Solve.
        t0 = time.perf_counter()
        result = self._solve(time_s, tilt, prior, motion, features, reason_if_none)
        t_solve = time.perf_counter() - t0
        timings = StageTimings(
            acquire_ms=1e3 * t_acquire,
            track_ms=1e3 * t_track,
            decode_ms=1e3 * t_decode,
            solve_ms=1e3 * t_solve,
            total_ms=_ms(t_start),
        )
        if isinstance(result, VlpFix):
            return VlpFix(
                result.time_s,
                result.x_m,
                result.y_m,
                result.yaw_rad,
                result.covariance,
                result.ids,
                result.leds,
                result.residual_rms,
                result.degraded,
                result.flags,
                timings,
                result.work,
                result.chi2,
                result.chi2_threshold,
                result.protection,
            )
        return NoFix(result.time_s, result.reason, result.leds, timings, result.work)

    # -- acquisition ---------------------------------------------------------------------------------------
    def _bands(self, height: int) -> list[tuple[int, int]]:
        """The bands of rows a search spread over frames looks at, overlapping by the largest LED disk the
        map allows, a stripe gap on either side and the coarse pass's padding (so each LED lies whole in one
        band, away from its edges)."""
        if self._bands_for is None or self._bands_for[0] != height:
            det = self.detector
            largest = 2.0 * det.radius_range_px[1] if det.radius_range_px else det.max_diameter_px
            overlap = math.ceil(largest) + 2 * det.bridge + 4 * det.coarse_factor + 8
            self._bands_for = (height, search_bands(height, max(self.config.search_bands, 1), overlap))
        return self._bands_for[1]

    def _search(
        self, image: npt.NDArray[np.uint8], time_s: float, rows: tuple[int, int] | None = None
    ) -> str | None:
        """Search the frame (or the band ``rows`` of it) for LEDs not yet tracked; returns a reason when the
        frame itself is unusable."""
        held = [(*t.kf.position, t.radius_px) for t in self.tracker.tracks if t.missed == 0]
        blobs = find_blobs(image, self.detector, known=held, rows=rows)
        if not blobs and not self.tracker.tracks:
            bg, _ = background_level(image)
            hist_bright = float(np.count_nonzero(image[::4, ::4] >= 250)) / image[::4, ::4].size
            if hist_bright >= self.config.saturated_fraction:
                return "saturated frame"
            top = float(image[::2, ::2].max())
            if top - bg < self.detector.min_contrast_dn:
                return "dark frame: nothing brighter than the background"
            return "no LED found in the frame"
        self.tracker.add(image, blobs, time_s, len(self.signatures))
        return None

    def _search_predicted(self, image: npt.NDArray[np.uint8], time_s: float) -> None:
        """Look where the map says an LED not yet tracked should be, from the last fix (cheap, ROI only)."""
        last = self._last
        if last is None or time_s - last.time_s > self.config.prior_max_age_s:
            return
        intr = self.intrinsics
        x, y, yaw = last.lens
        c, s = math.cos(yaw), math.sin(yaw)
        xyz = self.led_map.xyz_m
        h = xyz[:, 2] - self.mount.z_m
        dx, dy = xyz[:, 0] - x, xyz[:, 1] - y
        # Level camera prediction q = R(-psi) d / h (tilt and distortion are small next to the search box).
        u = intr.cx_px + intr.fx_px * (c * dx + s * dy) / h
        v = intr.cy_px + intr.fy_px * (-s * dx + c * dy) / h
        radius = intr.fx_px * np.array([led.diameter_m for led in self.led_map.leds]) / (2.0 * h)
        margin = self.detector.border_fraction * intr.width_px
        visible = (u > margin) & (u < intr.width_px - margin) & (v > margin) & (v < intr.height_px - margin)
        blobs = []
        for k in np.flatnonzero(visible & (h > 0)):
            if any(
                math.dist(t.kf.position, (u[k], v[k])) < 2.0 * t.radius_px + 4 for t in self.tracker.tracks
            ):
                continue
            half = 1.6 * radius[k] + 8.0
            box = (int(u[k] - half), int(v[k] - half), int(u[k] + half) + 1, int(v[k] + half) + 1)
            bg = self.tracker.tracks[0].background_dn if self.tracker.tracks else background_level(image)[0]
            blob = measure_blob(image, box, bg, 1.0, self.detector)
            if blob is not None and not blob.at_border:
                blobs.append(blob)
        if blobs:
            self.tracker.add(image, blobs, time_s, len(self.signatures))

    # -- pose ----------------------------------------------------------------------------------------------
    def _lens_prior(
        self, time_s: float, prior: PosePrior | None
    ) -> tuple[float, float, float, float, float] | None:
        """The prior on the lens: the one given with this frame, else the more recent of the last full fix
        and the last given prior, its uncertainty grown with its age; None when both are too old."""
        m = self.mount
        if prior is not None:
            self._given = (time_s, prior)
        candidates: list[tuple[float, tuple[float, float, float, float, float]]] = []
        if self._given is not None:
            t_given, p = self._given
            c, s = math.cos(p.yaw_rad), math.sin(p.yaw_rad)
            lens = (p.x_m + c * m.x_m - s * m.y_m, p.y_m + s * m.x_m + c * m.y_m, p.yaw_rad + m.yaw_rad)
            candidates.append((t_given, (*lens, p.sigma_xy_m, p.sigma_yaw_rad)))
        if self._last is not None:
            candidates.append((self._last.time_s, (*self._last.lens, 0.05, math.radians(5.0))))
        if not candidates:
            return None
        t_prior, (x, y, yaw, sxy, syaw) = max(candidates, key=lambda c: c[0])
        age = time_s - t_prior
        if not 0 <= age <= self.config.prior_max_age_s:
            return None
        return (x, y, yaw, sxy + self.config.prior_growth_mps * age, syaw + 1.0 * age)

    def _lens_velocity(self, time_s: float, motion: Motion | None) -> tuple[float, float, float]:
        last = self._last
        if motion is not None:
            yaw = last.base[2] if last is not None else 0.0
            m = self.mount
            c, s = math.cos(yaw), math.sin(yaw)
            w = motion.yaw_rate_radps
            # Lens = base + R(psi) m: its velocity is v + omega R'(psi) m, R'(psi) = [[-s, -c], [c, -s]].
            return (
                motion.vx_mps + w * (-s * m.x_m - c * m.y_m),
                motion.vy_mps + w * (c * m.x_m - s * m.y_m),
                w,
            )
        if not self.config.estimate_motion or last is None or last.previous is None:
            return (0.0, 0.0, 0.0)
        t_prev, lens_prev = last.previous
        dt = last.time_s - t_prev
        if not 0 < dt <= self.config.motion_max_gap_s or time_s - last.time_s > self.config.motion_max_gap_s:
            return (0.0, 0.0, 0.0)
        vx = (last.lens[0] - lens_prev[0]) / dt
        vy = (last.lens[1] - lens_prev[1]) / dt
        w = math.remainder(last.lens[2] - lens_prev[2], 2.0 * math.pi) / dt
        # A difference of two fixes that no robot could drive is a bad fix, not motion.
        if math.hypot(vx, vy) > self.config.max_speed_mps or abs(w) > self.config.max_yaw_rate_radps:
            return (0.0, 0.0, 0.0)
        return (vx, vy, w)

    def _observation(
        self, track: LedTrack, feature: tuple[float, float, int] | None, map_index: int | None = None
    ) -> LedObservation:
        """What the frame says about one track; ``map_index``: the map LED the solver matched it to (the
        observation is then marked used)."""
        blob = track.blob
        # The frame's own classification, only when its stripes were decoded on this frame.
        frame = track.frame if track.visibility == FULL and feature is not None else None
        centre = blob.centre_px if blob is not None else track.kf.position
        settled = self._settled_id(track)
        freq, duty, area = feature if feature is not None else (math.nan, math.nan, 0)
        return LedObservation(
            track.track_id,
            centre,
            blob.radius_px if blob is not None else track.radius_px,
            track.visibility,
            track.rho,
            frame.id if frame is not None else None,
            frame.confidence if frame is not None else 0.0,
            settled,
            track.id_confidence,
            freq,
            duty,
            area,
            map_index,
            map_index is not None,
            frame.reason if frame is not None else None,
        )

    def _settled_id(self, track: LedTrack) -> str | None:
        return self.signatures[track.id_index].id if track.id_index is not None else None

    def _observations(
        self, features: dict[int, tuple[float, float, int]], matched: dict[int, int] | None = None
    ) -> list[LedObservation]:
        """Every track's observation; ``matched`` maps a track's index to the map LED it was matched to
        (unmatched tracks, and negative indices, are not used)."""
        tracks = self.tracker.tracks
        if not matched:
            return [self._observation(t, features.get(t.track_id)) for t in tracks]
        return [
            self._observation(t, features.get(t.track_id), _map_index(matched.get(k)))
            for k, t in enumerate(tracks)
        ]

    def _lens_offset(self, tilt: Tilt | None) -> FloatArray:
        """The lens offset in the level frame for this frame's tilt, kept while the tilt does not change."""
        if self._offset is None or self._offset[0] != tilt:
            self._offset = (tilt, lens_offset_level(self.mount, tilt))
        return self._offset[1]

    def _solve(
        self,
        time_s: float,
        tilt: Tilt | None,
        prior: PosePrior | None,
        motion: Motion | None,
        features: dict[int, tuple[float, float, int]],
        reason_if_none: str,
    ) -> VlpFix | NoFix:
        tracks = self.tracker.tracks
        # Settled ids, and provisional ones (one confident frame): a fix leaning on a provisional id is
        # flagged unless three LEDs or more check it (below, ``id-unconfirmed``).
        solve_ids = {k: t.provisional_index(self.config.tracker) for k, t in enumerate(tracks)}
        usable = [
            k for k, t in enumerate(tracks) if t.centre_ok and t.blob is not None and solve_ids[k] is not None
        ]
        empty = _NO_TIMINGS
        if not usable:
            seen = tuple(self._observations(features))
            if not tracks:
                return NoFix(time_s, reason_if_none, seen, empty)
            if not any(t.centre_ok for t in tracks):
                return NoFix(time_s, "no LED fully visible (covered or at the border)", seen, empty)
            return NoFix(time_s, "no LED identified yet", seen, empty)

        intr = self.intrinsics
        blobs = [b for b in (tracks[k].blob for k in usable) if b is not None]
        uv = [b.centre_px for b in blobs]
        q = level_plane_points(uv, intr, self._level_rotation(tilt))
        f_px = min(intr.fx_px, intr.fy_px)
        sigma_floor = self.config.measurement_sigma_px
        outline_sigma = self.config.outline_sigma_px
        rays = []
        for row, k in enumerate(usable):
            track = tracks[k]
            blob = track.blob
            index = solve_ids[k]
            led_id = self.signatures[index].id if index is not None else ""
            # The centre's standard deviation falls as 1/sqrt(edge points): a disk crossed by one or two
            # bright stripes (few points, all near its middle rows) is placed less well across them.
            points = max(blob.outline_points if blob is not None else 0, 1)
            sigma_px = max(sigma_floor, outline_sigma / math.sqrt(points))
            rays.append(
                LedRay(
                    q[row],
                    self.led_map.candidates(led_id),
                    sigma_px / f_px,
                    intr.row_time_from_mid_s(float(uv[row][1])),
                )
            )
        lens_offset = self._lens_offset(tilt)
        lens_z = float(lens_offset[2])
        lens_prior = self._lens_prior(time_s, prior)
        if len(rays) == 1:
            return self._single(time_s, rays[0], usable[0], features, lens_prior, lens_z, lens_offset)

        velocity = self._lens_velocity(time_s, motion)
        solution = solve_pose(
            rays,
            self.led_map.xyz_m,
            lens_z,
            velocity=velocity,
            prior=lens_prior,
            config=self.config.solver,
            map_sigmas_m=self._map_sigmas_m,
        )
        if isinstance(solution, NoSolution):
            return NoFix(time_s, solution.reason, tuple(self._observations(features)), empty, solution.work)

        flags: list[str] = []
        observations = self._observations(features, dict(zip(usable, solution.assignment, strict=True)))
        if any(not t.centre_ok for t in tracks):
            flags.append("leds-excluded")
        # Each reason the fix is weaker than a nominal one (every one makes it degraded).
        weak = [
            ("outlier-dropped", solution.dropped > 0),
            ("large-residual", solution.rms_residual > 3.0),
            # chi^2 over every fitted term (the height correction's prior too) past the test's limit.
            ("inconsistent", not solution.consistent),
            # The best of what the budget allowed: another placement may fit as well.
            ("association-truncated", solution.work.truncated),
            # Another placement far from this one fits about as well given the prior.
            ("ambiguous-placement", solution.alternatives > 0),
            # An id that fewer than confirm_frames frames in a row named, in a fix whose own redundancy
            # cannot check it (with three LEDs or more a misread id puts its LED far off the fitted pose,
            # which the chi-square test sees; with two nothing does).
            (
                "id-unconfirmed",
                solution.protection is None
                and any(
                    not tracks[k].confirmed(self.config.tracker)
                    for k, a in zip(usable, solution.assignment, strict=True)
                    if a >= 0
                ),
            ),
            # An id with a close rival in the map (a signature within 200 Hz and 0.1 duty), in a fix whose
            # redundancy cannot check it: a row time a few per cent off, or a drifting LED, shifts every
            # frequency, and close signatures then read as their neighbours frame after frame, each read
            # confident and confirmed (two LEDs misread together as a pair at the map's distance). No margin
            # on the measured frequency tells a shifted read from a right one; only the geometry of three
            # LEDs or more (or a calibrated row time) can.
            (
                "close-signature",
                solution.protection is None
                and any(
                    bool(self._rivals[solve_ids[k] or 0])
                    for k, a in zip(usable, solution.assignment, strict=True)
                    if a >= 0 and solve_ids[k] is not None
                ),
            ),
            (
                "prior-mismatch",
                solution.prior_ignored
                or _far_from_prior(solution, lens_prior, self.config.solver.prior_gate_sigmas),
            ),
        ]
        flags += [name for name, hit in weak if hit]
        degraded = any(hit for _, hit in weak)
        lens = (solution.x_m, solution.y_m, solution.yaw_rad)
        return self._finish(
            time_s,
            lens,
            solution.covariance,
            observations,
            lens_offset,
            degraded,
            flags,
            solution.rms_residual,
            solution.work,
            (solution.protection, solution.chi2, solution.chi2_threshold),
        )

    def _single(
        self,
        time_s: float,
        ray: LedRay,
        track_index: int,
        features: dict[int, tuple[float, float, int]],
        lens_prior: tuple[float, float, float, float, float] | None,
        lens_z: float,
        lens_offset: FloatArray,
    ) -> VlpFix | NoFix:
        """One LED: a degraded fix from the prior's yaw (the SLO-VLP solver), or no fix without a prior."""
        empty = _NO_TIMINGS
        observations = tuple(self._observations(features))
        if lens_prior is None:
            return NoFix(time_s, "one LED in view and no yaw prior", observations, empty)
        px, py, yaw, sxy, syaw = lens_prior
        own = self._last
        if own is not None and 0.0 <= time_s - own.time_s <= self.config.prior_max_age_s:
            # The pipeline's own last fix, its yaw carried forward at the yaw rate of the last two fixes:
            # uncertain by 0.2 deg, plus 0.05 rad/s of yaw-rate error and 0.5 rad/s^2 of unmodelled angular
            # acceleration over the age. Used when it is surer than the prior's yaw.
            age = time_s - own.time_s
            own_sigma = math.radians(0.2) + 0.05 * age + 0.5 * age * age
            if own_sigma < syaw:
                yaw = own.lens[2] + self._lens_velocity(time_s, None)[2] * age
                syaw = own_sigma
        if syaw > self.config.single_led_max_yaw_sigma_rad:
            limit = math.degrees(self.config.single_led_max_yaw_sigma_rad)
            return NoFix(
                time_s,
                f"one LED in view and the yaw not known to {limit:.0f} deg",
                observations,
                empty,
            )
        xyz = self.led_map.xyz_m
        best = min(
            ray.candidates,
            key=lambda i: math.hypot(
                *np.subtract(single_led_position(ray.q, tuple(xyz[i]), lens_z, yaw), (px, py))
            ),
            default=None,
        )
        if best is None:
            return NoFix(time_s, "one LED in view, not in the map", observations, empty)
        x, y = single_led_position(
            ray.q, (float(xyz[best, 0]), float(xyz[best, 1]), float(xyz[best, 2])), lens_z, yaw
        )
        if math.hypot(x - px, y - py) > 4.0 * sxy + 0.1:
            return NoFix(time_s, "one LED in view, far from the prior", observations, empty)
        h = float(xyz[best, 2]) - lens_z
        reach = h * math.hypot(*ray.q)
        map_sigma = (
            self._map_sigmas_m[best] if self._map_sigmas_m is not None else self.config.solver.map_sigma_m
        )
        var_xy = (h * ray.sigma) ** 2 + map_sigma**2 + (reach * syaw) ** 2
        cov = np.diag([var_xy, var_xy, syaw**2])
        matched = self._observations(features, {track_index: best})
        return self._finish(time_s, (x, y, yaw), cov, matched, lens_offset, True, ["single-led"], 0.0)

    def _finish(
        self,
        time_s: float,
        lens: tuple[float, float, float],
        cov_lens: FloatArray,
        observations: list[LedObservation],
        lens_offset: FloatArray,
        degraded: bool,
        flags: list[str],
        rms: float,
        work: AssociationWork = NO_WORK,
        integrity: tuple[ProtectionInputs | None, float, float] = (None, math.nan, math.inf),
    ) -> VlpFix:
        """Lens pose -> base pose (base = lens - R(psi_base) offset), residual correction, bookkeeping.
        ``integrity``: what the lens fix's protection level is computed from, its chi^2 and the test's
        threshold."""
        yaw_base = math.remainder(lens[2] - self.mount.yaw_rad, 2.0 * math.pi)
        c, s = math.cos(yaw_base), math.sin(yaw_base)
        ox, oy = float(lens_offset[0]), float(lens_offset[1])
        x = lens[0] - (c * ox - s * oy)
        y = lens[1] - (s * ox + c * oy)
        # d base / d psi = -R'(psi) o, R'(psi) = [[-s, -c], [c, -s]].
        cov_t = _moved_covariance(cov_lens, s * ox + c * oy, -c * ox + s * oy)
        if self.calibration is not None and self.calibration.residual is not None:
            x, y = self.calibration.residual.apply(x, y)
        protection, chi2, chi2_limit = integrity
        if protection is not None and (ox or oy):
            # The base is |o| from the lens: its position also moves with the yaw's error (bounded at the
            # same risk as the fault-free part of the protection level).
            protection = protection.with_margin(
                math.hypot(ox, oy) * _K_YAW * math.sqrt(max(float(cov_lens[2][2]), 0.0))
            )
        if not degraded:
            # Only full fixes feed the next frames' prior and velocity (a one-LED fix leans on its prior).
            previous = (self._last.time_s, self._last.lens) if self._last is not None else None
            self._last = _LastFix(time_s, lens, (x, y, yaw_base), previous)
        # The ids the fix used (a provisional one too: the map LED it was matched to).
        ids = tuple(
            self.led_map.leds[o.map_index].id for o in observations if o.used and o.map_index is not None
        )
        return VlpFix(
            time_s,
            x,
            y,
            yaw_base,
            cov_t,
            ids,
            tuple(observations),
            rms,
            degraded,
            tuple(flags),
            _NO_TIMINGS,
            work,
            chi2,
            chi2_limit,
            protection,
        )


def _close_rivals(frequency_hz: FloatArray, duty: FloatArray) -> tuple[tuple[int, ...], ...]:
    """For each signature, the others close to it: within ``_CLOSE_FREQUENCY_HZ`` and ``_CLOSE_DUTY``, where
    the duty does not tell them apart and only the frequency does."""
    return tuple(
        tuple(
            j
            for j in range(frequency_hz.size)
            if j != k
            and abs(frequency_hz[j] - frequency_hz[k]) < _CLOSE_FREQUENCY_HZ
            and abs(duty[j] - duty[k]) < _CLOSE_DUTY
        )
        for k in range(frequency_hz.size)
    )


def _far_from_prior(
    solution: PoseSolution, prior: tuple[float, float, float, float, float] | None, gate_sigmas: float
) -> bool:
    """The lens fix lies outside the prior's gate (its position or yaw more than ``gate_sigmas`` of the
    prior's uncertainty away, + 5 cm and 0.05 rad): a misread id, or a prior that is wrong; either way the
    fix is not to be trusted as nominal."""
    if prior is None:
        return False
    px, py, pyaw, sxy, syaw = prior
    far = math.hypot(solution.x_m - px, solution.y_m - py) > gate_sigmas * sxy + 0.05
    turned = abs(math.remainder(solution.yaw_rad - pyaw, 2.0 * math.pi)) > gate_sigmas * syaw + 0.05
    return far or turned


def _map_index(index: int | None) -> int | None:
    """The solver's map index of a ray, None when it was not used (-1) or not solved for."""
    return index if index is not None and index >= 0 else None


def _moved_covariance(cov_lens: FloatArray, jx: float, jy: float) -> Covariance3:
    """J C J^T for J = [[1, 0, jx], [0, 1, jy], [0, 0, 1]] (the pose moved from the lens to the base,
    whose position depends on the yaw by (jx, jy)), written out for plain floats: J C adds jx, jy times
    C's last row to its first two, and (J C) J^T does the same with the columns."""
    (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = np.asarray(cov_lens, dtype=np.float64).tolist()
    m00, m01, m02 = c00 + jx * c20, c01 + jx * c21, c02 + jx * c22
    m10, m11, m12 = c10 + jy * c20, c11 + jy * c21, c12 + jy * c22
    return (
        (m00 + m02 * jx, m01 + m02 * jy, m02),
        (m10 + m12 * jx, m11 + m12 * jy, m12),
        (c20 + c22 * jx, c21 + c22 * jy, c22),
    )


def _ms(t_start: float) -> float:
    return 1e3 * (time.perf_counter() - t_start)
