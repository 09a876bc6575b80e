"""The follow loop: person following on top of navigation (``docs/following.md``, "The follower").

* :meth:`FollowLoop.on_scan` (the laser loop, every scan): the scan's person-sized clusters off the static
  map (the navigation costmap's static layer, when there is one) update the person's track
  (``agent.following.person``), or start one inside the RFID layer's band when there is none;
* :meth:`FollowLoop.step` (its own thread, every ``period_s``): the follower's command
  (``agent.following.follower``) from the fused pose and the track, checked against the costmap (the point
  the robot would reach in ``lookahead_s`` must be free) and put through the collision monitor
  (``NavigationLoop.guard``), then sent as a velocity command (a local mission: the controller's commands
  take precedence, ``Agent.command_velocity``).

* :meth:`FollowLoop.on_frame` (a thread on the forward camera's newest frames, with ``fine``): the fine
  layer (``agent.following.fine``: pre-location in a band of columns round the laser track, itself taken
  inside the RFID band, then multi-feature mean shift) answers a head-and-shoulders box whose column is a
  bearing from the camera, fed to the track as a second measurement (``PersonTracker.update_bearing``): the
  person's estimate uses laser, RFID and camera.

With ``active`` (the agent's following on command, ``agent.runtime.follow_control``) the loop idles while it
says no: scans and frames are not looked at, nothing is sent (zero once when it turns off), and it starts
afresh when it turns on (:meth:`FollowLoop.restart`: no track, no memory of the last time). Without it the
loop follows from its start (``vlp-agent sim --follow``).

A track not measured by the last scan is *occluded* when the scan has returns nearer than the track on
its line of sight (a passer-by, a corner), *vanished* otherwise; the follower coasts through the first
and stops on the second at the first scan that misses them (``stop_after_s``; ``docs/following.md``,
"Losing the person").

Acquisition uses the coarse layer's window ahead (``within(0, acquire_half_width)``, the camera's view) as
``docs/following.md`` advises (the global maximum is often the mirror image behind the robot), and, when
that holds little, its ``bearing_rad``.
"""

from __future__ import annotations

import collections
import itertools
import logging
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from agent.following.fine import FineLayer, FineResult, FineState, Locator
from agent.following.follower import (
    FollowCommand,
    Follower,
    FollowState,
    WalkerMode,
    predicted_gaps,
    walker_candidates,
    walker_decision,
    walker_threat,
)
from agent.following.person import (
    DetectorConfig,
    PersonDetections,
    PersonEstimate,
    PersonTracker,
    detect_people,
)
from agent.following.prelocate import Detection
from agent.navigation.give_way import aside_target
from agent.navigation.navigator import Navigator
from agent.runtime.rfid_loop import CoarseLayer
from drivers.samples import Frame, Scan

__all__ = [
    "NO_CAMERA",
    "NO_POSE",
    "NO_SCAN",
    "CameraView",
    "FollowLoop",
    "FollowSnapshot",
    "ProjectedLocator",
]

NO_POSE = "no pose: stopped"
NO_CAMERA = "no frame from the forward camera: stopped"
NO_SCAN = "no laser scan: stopped"

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]


def distort(x: float, y: float, d: tuple[float, float, float, float, float]) -> tuple[float, float]:
    """OpenCV's plumb_bob model on normalised coordinates: with r^2 = x^2 + y^2,
    x' = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2), y' alike with p1 and p2 swapped."""
    k1, k2, p1, p2, k3 = d
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )


def undistort(
    xd: float, yd: float, d: tuple[float, float, float, float, float], iterations: int = 20
) -> tuple[float, float]:
    """The inverse of :func:`distort` by fixed-point iteration, as ``cv2.undistortPoints`` does it."""
    if not any(d):
        return xd, yd
    x, y = xd, yd
    for _ in range(iterations):
        fx, fy = distort(x, y, d)
        x, y = x + (xd - fx), y + (yd - fy)
    return x, y


@dataclass(frozen=True, slots=True)
class CameraView:
    """The forward camera's geometry, enough to turn image points into bearings and a person's place into
    a box: a pinhole camera ``width_px`` x ``height_px`` with horizontal field of view ``hfov_rad`` (the
    focal length ``f_px`` along rows; ``fy_px`` down columns, None: the same), principal point ``cx_px``,
    ``cy_px``, at ``mount`` (x forward, y left, z up, yaw) on the base, its optical axis tilted up by
    ``pitch_rad`` (0: level; no roll). Tilted, a column is no longer one bearing: :meth:`bearing` takes the
    row too. ``distortion``: OpenCV's (k1, k2, p1, p2, k3) of the calibrated lens (``vlp-agent calibrate
    forward-camera``), applied to the normalised coordinates as ``cv2.projectPoints`` does."""

    width_px: int
    height_px: int
    hfov_rad: float
    cx_px: float
    cy_px: float
    mount: tuple[float, float, float, float]  # x, y, z (m), yaw (rad)
    fy_px: float | None = None
    pitch_rad: float = 0.0
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)

    @property
    def f_px(self) -> float:
        return (self.width_px / 2.0) / math.tan(self.hfov_rad / 2.0)

    @property
    def fv_px(self) -> float:
        return self.f_px if self.fy_px is None else self.fy_px

    def scaled(self, width_px: int, height_px: int) -> CameraView:
        """The same camera delivering frames of another size (the intrinsics scale with it)."""
        sx, sy = width_px / self.width_px, height_px / self.height_px
        hfov = 2.0 * math.atan((width_px / 2.0) / (self.f_px * sx))
        return CameraView(
            width_px,
            height_px,
            hfov,
            (self.cx_px + 0.5) * sx - 0.5,
            (self.cy_px + 0.5) * sy - 0.5,
            self.mount,
            self.fv_px * sy,
            self.pitch_rad,
            self.distortion,
        )

    def origin(self, pose: Pose) -> tuple[float, float, float]:
        """The camera's (x, y, yaw) in the map frame with the base at ``pose``."""
        mx, my, _, myaw = self.mount
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return pose[0] + c * mx - s * my, pose[1] + s * mx + c * my, pose[2] + myaw

    def project(self, forward_m: float, left_m: float, height_m: float) -> tuple[float, float] | None:
        """The pixel (column, row) of a point ``forward_m`` ahead of and ``left_m`` left of the camera
        (its yawed, level frame), ``height_m`` above the floor; None behind it."""
        z = height_m - self.mount[2]
        c, s = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        depth = c * forward_m + s * z
        if depth <= 0.05:
            return None
        up = -s * forward_m + c * z
        x, y = distort(-left_m / depth, -up / depth, self.distortion)
        return self.cx_px + self.f_px * x, self.cy_px + self.fv_px * y

    def column(self, bearing_rad: float, range_m: float = 2.0, height_m: float = 1.45) -> float:
        """The image column of a bearing in the camera's frame (left positive); tilted, of the point at
        ``range_m`` and ``height_m`` (a person's shoulders by default)."""
        if self.pitch_rad == 0.0 and not any(self.distortion):
            return self.cx_px - self.f_px * math.tan(bearing_rad)
        uv = self.project(range_m * math.cos(bearing_rad), range_m * math.sin(bearing_rad), height_m)
        return self.cx_px - self.f_px * math.tan(bearing_rad) if uv is None else uv[0]

    def bearing(self, column: float, row: float | None = None) -> float:
        """The bearing (camera frame, left positive) of the image point (``column``, ``row``); ``row``
        None: the principal point's (the same for every row of a level camera)."""
        x, y = undistort(
            (column - self.cx_px) / self.f_px,
            0.0 if row is None else (row - self.cy_px) / self.fv_px,
            self.distortion,
        )
        left, up = -x, -y
        forward = math.cos(self.pitch_rad) - math.sin(self.pitch_rad) * up
        return math.atan2(left, forward)

    def head_shoulder_box(
        self,
        range_m: float,
        bearing_rad: float,
        top_m: float = 1.75,
        bottom_m: float = 1.15,
        width_m: float = 0.45,
    ) -> np.ndarray | None:
        """The head and shoulders of a person standing ``range_m`` away at ``bearing_rad`` (camera frame),
        x, y, w, h in pixels, clipped to the image; None when not in view."""
        if range_m <= 0.2 or abs(bearing_rad) >= self.hfov_rad / 2.0:
            return None
        cb, sb = math.cos(bearing_rad), math.sin(bearing_rad)
        corners = []
        for side in (-0.5, 0.5):
            fwd = range_m * cb - side * width_m * sb
            left = range_m * sb + side * width_m * cb
            for h in (top_m, bottom_m):
                uv = self.project(fwd, left, h)
                if uv is None:
                    return None
                corners.append(uv)
        us, vs = [c[0] for c in corners], [c[1] for c in corners]
        x0, x1 = max(0.0, min(us)), min(self.width_px - 1.0, max(us))
        v0, v1 = max(0.0, min(vs)), min(self.height_px - 1.0, max(vs))
        if x1 - x0 < 8.0 or v1 - v0 < 8.0:
            return None
        return np.array([x0, v0, x1 - x0, v1 - v0], dtype=np.float64)


class ProjectedLocator:
    """The fine layer's pre-locator (``fine.Locator``) on the robot: the image detector
    (``prelocate.HeadShoulderLocator``, when given) inside the band, and, when it finds nobody there, the
    laser track's person projected into the image (:meth:`CameraView.head_shoulder_box`): the laser has
    already said where a person-sized body stands inside the RFID band. ``target`` (range, bearing in the
    camera's frame) is set by the follow loop before each frame."""

    def __init__(self, view: CameraView, detector: Locator | None = None) -> None:
        self.view = view
        self.detector = detector
        self.target: tuple[float, float] | None = None
        self.counts: collections.Counter[str] = collections.Counter()

    def locate(self, frame: np.ndarray, band: tuple[int, int] | None = None) -> list[Detection]:
        if self.detector is not None:
            found = self.detector.locate(frame, band)
            if found:
                self.counts["detector"] += 1
                return list(found)
        if self.target is None:
            return []
        box = self.view.head_shoulder_box(*self.target)
        if box is None:
            return []
        self.counts["projected"] += 1
        return [Detection(box, box, 0.0)]


@dataclass(frozen=True, slots=True)
class FollowSnapshot:
    t_s: float
    command: FollowCommand
    person: PersonEstimate | None
    sent: tuple[float, float]  # what went to the wheels after the safety checks
    aside: bool = False  # stepping out of a walker's way (the sent command is that, not the follower's)


class FollowLoop:
    def __init__(
        self,
        follower: Follower,
        tracker: PersonTracker,
        laser_mount: Pose,
        pose: Callable[[], Pose | None],
        coarse: Callable[[], CoarseLayer | None],
        send: Callable[[float, float], None],
        clock_s: Callable[[], float],
        *,
        guard: Callable[[float, float, float], tuple[float, float]] | None = None,
        pose_at: Callable[[float], Pose | None] | None = None,
        pose_epoch: Callable[[], int] | None = None,
        navigator: Callable[[], Navigator | None] = lambda: None,
        detector: DetectorConfig | None = None,
        acquire_half_width_rad: float = math.radians(35.0),
        acquire_min_mass: float = 0.2,
        acquire_sure: float = 0.3,
        acquire_sure_s: float = 1.0,
        lookahead_s: float = 1.0,
        decel_mps2: float = 1.0,
        person_clear_m: float = 0.5,
        walker_clear_m: float = 0.55,
        walker_is_person_m: float = 0.8,
        aside_reach_m: float = 0.8,
        aside_speed_mps: float = 0.3,
        close_up_m: float = 0.77,
        walker_horizon_s: float = 4.0,
        walker_smoothing: float = 0.7,
        walker_hold_s: float = 0.6,
        aside_walker_m: float = 1.5,
        walker_keep_m: float = 0.40,
        walker_resume_m: float = 0.65,
        walker_match_m: float = 0.6,
        occluder_margin_m: float = 0.3,
        fine: FineLayer | None = None,
        locator: ProjectedLocator | None = None,
        bearing_sd_rad: float = 0.05,
        bearing_only_after_s: float = 0.3,
        fine_reset_after: int = 5,
        camera_stale_s: float = 1.0,
        scan_stale_s: float = 0.5,
        scan_late_s: float = 0.25,
        period_s: float = 0.05,
    ) -> None:
        self.follower = follower
        self.tracker = tracker
        self.laser_mount = laser_mount
        self.pose = pose
        self.coarse = coarse
        self.send = send
        self.clock_s = clock_s
        self.guard = guard
        self.pose_at = pose_at
        self.pose_epoch = pose_epoch  # the fusion's reset counter: a change is a jump of the map frame
        self._epoch: tuple[int, Pose] | None = None  # the last step's counter and pose
        self.navigator = navigator
        self.detector = detector or DetectorConfig()
        self.acquire_half_width_rad = acquire_half_width_rad
        self.acquire_min_mass = acquire_min_mass
        self.acquire_sure = acquire_sure
        self.acquire_sure_s = acquire_sure_s
        self._window_since_s: float | None = None  # since when the RFID window has held acquire_min_mass
        self.absent = follower.config.absent_probability
        self.lookahead_s = lookahead_s
        self.decel_mps2 = decel_mps2
        self.person_clear_m = person_clear_m
        self.walker_clear_m = walker_clear_m
        self.walker_is_person_m = walker_is_person_m
        self.aside_reach_m = aside_reach_m
        self.aside_speed_mps = aside_speed_mps
        self.close_up_m = close_up_m
        self.walker_horizon_s = walker_horizon_s
        self.walker_smoothing = walker_smoothing
        self._walker_memory: dict[int, tuple[float, float, float]] = {}
        self.walker_hold_s = walker_hold_s
        self.aside_walker_m = aside_walker_m  # a step aside never heads toward a walker this near
        self._walker_held: dict[int, tuple[float, float, float, float, float]] = {}
        # The walker check's decision kept from step to step (``walker_decision``): a crossing in front
        # goes on while its predicted gap stays above walker_keep_m; a stop for a walker holds until a
        # speed keeps walker_resume_m. Without it the decision flipped 0.95/0 step by step (issue 23).
        self.walker_keep_m = walker_keep_m
        self.walker_resume_m = walker_resume_m
        self.walker_mode = WalkerMode.GO
        self.walker_match_m = walker_match_m  # a new track this near a known walker carries their velocity
        self._check: dict[str, object] = {}  # this step's walker check, for the DEBUG log
        self.occluder_margin_m = occluder_margin_m
        self.fine = fine
        self.locator = locator
        self.bearing_sd_rad = bearing_sd_rad
        self.bearing_only_after_s = bearing_only_after_s
        self._fine_started_s = -math.inf
        self.fine_reset_after = fine_reset_after
        self.camera_stale_s = camera_stale_s
        self.scan_stale_s = scan_stale_s
        self.scan_late_s = scan_late_s
        self.last_frame_s: float | None = None  # the loop's clock when the last forward frame came
        self.last_scan_s: float | None = None  # the last scan's time: the person was last looked for then
        self._poses: collections.deque[tuple[float, Pose]] = collections.deque(maxlen=40)  # 2 s of steps
        self.period_s = period_s
        self.counts: collections.Counter[str] = collections.Counter()
        self._lock = threading.Lock()
        self._wake = threading.Event()  # a scan missed the person: step at once (run)
        self.latest: FollowSnapshot | None = None
        self.occluded = False  # the last scan: something nearer than the unmeasured track in its way
        self.fine_state: FineState | None = None
        self._fine_track = 0  # the track id the fine layer's target was started on
        self._fine_rejected = 0
        self._blind = False
        self.vanished_at_s: float | None = None  # when the person was last hidden (``blind``)
        self.vanish_stops_s: list[float] = []  # per hiding: from it to the first zero speed sent
        self.vanishings_s: list[float] = []  # when each hiding began
        # Following on command: whether to follow now (None: always). Read by each step, scan and frame.
        self.active: Callable[[], bool] | None = None
        self._was_active = False
        # Told each step's snapshot while following (the follow control reports the state from it).
        self.on_step: Callable[[FollowSnapshot], None] | None = None

    def sync_active(self) -> bool:
        """Whether to step now (``active``; always without it). When it turns on the loop starts afresh
        (:meth:`restart`); when it turns off, zero speed goes out once: the last velocity this loop sent
        must not outlive the following."""
        if self.active is None:
            return True
        active = self.active()
        if active != self._was_active:
            if active:
                self.restart()
                log.info("following: on")
            else:
                self.send(0.0, 0.0)
                log.info("following: off")
            self._was_active = active
        return active

    def restart(self) -> None:
        """Start afresh: no track, no last scan or frame, no memory of a lost person or of the poses (the
        robot may have been driven anywhere since the last following)."""
        with self._lock:
            self.tracker.drop()
            self.follower.lost_since_s = None
            self.follower.vanished = False
            self.last_scan_s = None
            self.last_frame_s = None
            self.occluded = False
            self._window_since_s = None
            self._poses.clear()
            self._epoch = None
            self._walker_memory = {}
            self._walker_held = {}
            self.walker_mode = WalkerMode.GO
            self.latest = None
            self._fine_rejected = 0
        if self.fine is not None:
            self.fine.reset()
        self.counts["restarts"] += 1

    @property
    def blind(self) -> bool:
        """Drop the scans' detections and the camera's bearings (``vlp-agent sim --fault person``: the
        person hidden); the time it turns on is kept to measure the stop."""
        return self._blind

    @blind.setter
    def blind(self, on: bool) -> None:
        if on and not self._blind:
            self.vanished_at_s = self.clock_s()
            self.vanishings_s.append(self.vanished_at_s)
        self._blind = on

    # -- the RFID layer's word -------------------------------------------------------------------------

    def _coarse(self) -> tuple[float | None, float | None, tuple[float, float, float] | None]:
        """(p_absent, bearing to search toward, acquisition window (centre, half width,
        probability the person is in it)) in the robot frame; Nones without an RFID answer."""
        coarse = self.coarse()
        if coarse is None:
            return 0.0, None, (0.0, self.acquire_half_width_rad, 0.0)  # no reader: look ahead
        latest = coarse.latest
        if latest is None:
            return None, None, None
        est = latest.estimate
        ahead = coarse.filter.within(0.0, self.acquire_half_width_rad)
        # Only ahead (the camera's view): the global maximum is often the mirror image behind the robot.
        ok = ahead.probability >= self.acquire_min_mass
        window = (0.0, self.acquire_half_width_rad, ahead.probability) if ok else None
        return est.p_absent, est.bearing_rad, window

    # -- scans --------------------------------------------------------------------------------------

    def on_scan(self, scan: Scan) -> None:
        if self.active is not None and not self._was_active:  # idle: following is off
            return
        now = self.pose()
        if now is None:
            return
        t_s = scan.host_time_ns * 1e-9
        # The robot where it was when the scan was taken: a scan handled a few tenths of a second late on a
        # busy machine, placed with the pose of *now* while the robot turns, puts the person far enough off
        # for the track's gate to refuse them, scan after scan, until the track is dropped.
        pose = self._pose_at(t_s, now)
        mx, my, myaw = self.laser_mount
        c, s = math.cos(pose[2]), math.sin(pose[2])
        laser = (pose[0] + c * mx - s * my, pose[1] + s * mx + c * my, pose[2] + myaw)
        angles = scan.angles_rad()
        ranges = scan.ranges_mm.astype(np.float64) / 1000.0
        ranges[(ranges < scan.min_range_mm / 1000.0) | (ranges > scan.max_range_mm / 1000.0)] = np.nan
        static = self._static(laser, angles, ranges)
        # A new track only off the static map; a track keeps its person even where the map has taken them in
        # (SLAM maps a person who stands still).
        fresh = detect_people(angles, ranges, laser, static, self.detector)
        detections = (
            detect_people(angles, ranges, laser, None, self.detector) if static is not None else fresh
        )
        if self.blind:
            fresh = detections = PersonDetections(np.zeros((0, 2)), np.zeros(0))
        p_absent, _, window = self._coarse()
        with self._lock:
            if self.last_scan_s is not None and t_s <= self.last_scan_s:
                self.counts["scans_out_of_order"] += 1
                return
            previous, self.last_scan_s = self.last_scan_s, t_s
            self.counts["scans"] += 1
            self.counts["detections"] += len(fresh)
            if self.tracker.tracking:
                before = self.tracker.estimate()
                seen = self.tracker.update_detections(t_s, detections, previous)
                if not self.tracker.tracking and before is not None:
                    self._log_drop(before, t_s, detections)
                elif not seen and before is not None and log.isEnabledFor(logging.DEBUG):
                    near = np.hypot(*(detections.centres - np.array(before.xy)).T) if len(detections) else []
                    log.debug(
                        "following: scan t=%.2f (%.2f s late) missed the track at %.2f,%.2f: candidates at "
                        "%s m; robot then %s, now %s",
                        t_s,
                        self.clock_s() - t_s,
                        before.xy[0],
                        before.xy[1],
                        [round(float(x), 2) for x in near],
                        tuple(round(v, 2) for v in pose),
                        tuple(round(v, 2) for v in now),
                    )
                self.occluded = not seen and self._occluded(laser, angles, ranges)
                self.counts["occluded_scans"] += int(self.occluded)
                if not seen and not self.occluded:
                    # Nothing in front explains the miss: the follower stops on it; step now rather than
                    # at the next period (up to period_s later: a tenth of the half second allowed).
                    self._wake.set()
            elif window is not None and (
                p_absent is None or p_absent < self.follower.config.absent_probability
            ):
                if self._window_since_s is None:
                    self._window_since_s = t_s
                # Off the static map first; then a person-sized cluster the map has taken in (a user who
                # stood still while SLAM mapped them) where the RFID layer is sure they are ahead, or has
                # held them ahead for acquire_sure_s and that cluster is the only one there: a standing
                # user with their back to the antennas gives the window 0.26-0.31 of the mass, so a
                # threshold of 0.3 alone left the start to the fading (seconds of waiting, at random).
                got = self.tracker.acquire(t_s, fresh, pose, window[0], window[1])
                if not got:
                    held = t_s - self._window_since_s >= self.acquire_sure_s
                    ahead = self._in_window(detections, pose, window)
                    if window[2] >= self.acquire_sure or (held and ahead == 1):
                        got = self.tracker.acquire(t_s, detections, pose, window[0], window[1])
                        self.counts["acquired_on_map"] += int(got)
                    elif ahead:
                        self.counts["acquire_waits_on_map"] += 1
                if got:
                    self._window_since_s = None
                    log.info(
                        "following: person acquired (track %d) on the scan of t=%.2f, %.2f s old",
                        self.tracker.track_id,
                        t_s,
                        self.clock_s() - t_s,
                    )
            else:
                self._window_since_s = None

    def _in_window(
        self, detections: PersonDetections, robot: Pose, window: tuple[float, float, float]
    ) -> int:
        """How many candidates stand inside the acquisition window (bearing and range, robot frame)."""
        if len(detections) == 0:
            return 0
        d = detections.centres - np.array(robot[:2])
        bearing = np.arctan2(d[:, 1], d[:, 0]) - robot[2] - window[0]
        off = np.abs(np.remainder(bearing + np.pi, 2 * np.pi) - np.pi)
        near = np.hypot(d[:, 0], d[:, 1]) <= self.tracker.config.max_acquire_range_m
        return int(np.count_nonzero((off <= window[1]) & near))

    def _occluded(self, laser: Pose, angles: np.ndarray, ranges: np.ndarray) -> bool:
        """Whether the scan has returns nearer than the track (by ``occluder_margin_m``) within its body's
        width round its line of sight: something stands between (a passer-by, a corner)."""
        est = self.tracker.estimate()
        if est is None:
            return False
        dx, dy = est.xy[0] - laser[0], est.xy[1] - laser[1]
        rng = math.hypot(dx, dy)
        if rng < 0.3:
            return False
        off = np.abs(np.remainder(angles + laser[2] - math.atan2(dy, dx) + np.pi, 2 * np.pi) - np.pi)
        beams = off <= math.atan2(0.3, rng)
        near = ranges[beams]
        near = near[np.isfinite(near)]
        return bool(np.any(near < rng - self.occluder_margin_m))

    # -- the forward camera -------------------------------------------------------------------------

    def on_frame(self, frame: Frame) -> FineResult | None:
        """One forward camera frame through the fine layer; its bearing to the track. None when there is
        no fine layer, no pose or no track to look for (a new track restarts the fine layer's target)."""
        fine, locator = self.fine, self.locator
        if self.active is not None and not self._was_active:
            return None
        self.last_frame_s = self.clock_s()
        pose = self.pose()
        if fine is None or locator is None or pose is None:
            return None
        t_s = frame.host_time_ns * 1e-9
        view = locator.view
        height, width = frame.image.shape[:2]
        if (width, height) != (view.width_px, view.height_px):
            # The device gives another size than the intrinsics are for: the same lens, scaled.
            log.info(
                "forward camera: frames of %dx%d, its intrinsics are for %dx%d: scaled",
                width,
                height,
                view.width_px,
                view.height_px,
            )
            view = locator.view = view.scaled(width, height)
        # The robot where it was when the frame was taken: a frame a tenth of a second old, taken while
        # turning at 1.5 rad/s, would otherwise put the person 0.15 rad off.
        cam = view.origin(self._pose_at(t_s, pose))
        with self._lock:
            est = self.tracker.estimate()
            track_id = self.tracker.track_id
        if est is None or self._blind:
            self.fine_state = None
            return None
        if track_id != self._fine_track:
            fine.reset()
            self._fine_track = track_id
            self._fine_rejected = 0
            self._fine_started_s = self.clock_s()
        dx, dy = est.xy[0] - cam[0], est.xy[1] - cam[1]
        rng = math.hypot(dx, dy)
        bearing = math.remainder(math.atan2(dy, dx) - cam[2], math.tau)
        if abs(bearing) >= view.hfov_rad / 2.0 or rng < 0.3:
            self.counts["fine_out_of_view"] += 1
            return None
        # The band: the track's body (0.6 m) round its column, inside the RFID band it was taken in.
        u = view.column(bearing, rng)
        half = max(40.0, view.f_px * 0.6 / max(rng, 0.5))
        band = (int(max(0.0, u - half)), int(min(view.width_px, u + half)))
        locator.target = (rng, bearing)
        result = fine.update(frame.image, band)
        self.fine_state = result.state
        self.counts[f"fine_{result.state.value}"] += 1
        if result.state is FineState.LOST:
            # Hidden too long for the tracker: start again on the track (the laser still has the person).
            fine.reset()
            self.counts["fine_resets"] += 1
        if result.state is not FineState.TRACKING or result.box is None:
            return result
        column = float(result.box[0] + result.box[2] / 2.0)
        row = float(result.box[1] + result.box[3] / 2.0)
        measured = cam[2] + view.bearing(column, row)
        if est.t_s - t_s > self.bearing_only_after_s:
            # A frame older than the track by more than that (a camera's first frames, delivered late, or
            # a stalled USB transfer) says where the person was, not where they are: not used.
            self.counts["fine_old_frames"] += 1
            return result
        scan_seen = est.last_seen_s if est.scan_seen_s is None else est.scan_seen_s
        if est.t_s - scan_seen > self.bearing_only_after_s or self.clock_s() - self._fine_started_s < 1.0:
            # The camera refines a track the laser holds; it does not keep one alive on its own (a box
            # drifting onto the wall would), nor steer one it has followed for less than a second.
            self.counts["fine_unused"] += 1
            return result
        with self._lock:
            if self.tracker.track_id != track_id:
                return result
            ok = self.tracker.update_bearing(t_s, cam[:2], measured, self.bearing_sd_rad)
        self.counts["fine_bearings" if ok else "fine_rejected"] += 1
        self._fine_rejected = 0 if ok else self._fine_rejected + 1
        if self._fine_rejected >= self.fine_reset_after:
            # The box has left the track (onto a passer-by or the wall): start again on the track.
            fine.reset()
            self._fine_rejected = 0
            self.counts["fine_resets"] += 1
        return result

    def _reframe(self, epoch: int | None, pose: Pose) -> None:
        """A relocalization (the fusion's reset counter moved) jumps the robot's pose and the map frame
        under it: carry the track along (where the person is relative to the robot holds over a step), and
        forget the poses before it. Without this the scans after the jump put the person off the gate and
        the track was dropped and taken again mid-walk. Called with the lock held."""
        if epoch is None:
            return
        last, self._epoch = self._epoch, (epoch, pose)
        if last is None or last[0] == epoch:
            return
        self.tracker.reframe(last[1], pose)
        self._poses.clear()
        self.counts["reframes"] += 1
        log.info(
            "following: the fused pose jumped %.2f m, %.1f deg (relocalized): the track moved with it",
            math.dist(last[1][:2], pose[:2]),
            math.degrees(math.remainder(pose[2] - last[1][2], math.tau)),
        )

    def _log_drop(self, est: PersonEstimate, t_s: float, detections: PersonDetections) -> None:
        near = (
            float(np.min(np.hypot(*(detections.centres - np.array(est.xy)).T))) if len(detections) else None
        )
        log.info(
            "following: track %d dropped at t=%.2f: last measured %.2f s before, at %.2f,%.2f moving "
            "%.2f,%.2f; nearest candidate %s m from it; last scan t=%s",
            est.track_id,
            t_s,
            t_s - est.last_seen_s,
            est.xy[0],
            est.xy[1],
            est.velocity[0],
            est.velocity[1],
            "none" if near is None else f"{near:.2f}",
            "none" if self.last_scan_s is None else f"{self.last_scan_s:.2f}",
        )

    def _pose_at(self, t_s: float, now: Pose) -> Pose:
        """The fused pose at ``t_s``: the fusion's own (``pose_at``, its buffered measurements up to then)
        when given, else from the poses the steps saw (linear between the two round it; the nearest end
        outside them)."""
        if self.pose_at is not None:
            at = self.pose_at(t_s)
            if at is not None:
                return at
        with self._lock:
            poses = list(self._poses)
        if not poses:
            return now
        if t_s <= poses[0][0]:
            return poses[0][1]
        if t_s >= poses[-1][0]:
            return poses[-1][1]
        for (t0, p0), (t1, p1) in itertools.pairwise(poses):
            if t0 <= t_s <= t1:
                a = (t_s - t0) / max(t1 - t0, 1e-9)
                yaw = p0[2] + a * math.remainder(p1[2] - p0[2], math.tau)
                return (p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), yaw)
        return now

    def run_camera(self, frames: Callable[[float], Frame | None], stop: threading.Event) -> None:
        """Take the forward camera's newest frames (``frames(timeout_s)``) through :meth:`on_frame` until
        ``stop``; a frame the fine layer fails on is counted and skipped."""
        while not stop.is_set():
            try:
                frame = frames(0.2)
            except Exception:  # the mailbox closed: the agent is stopping
                return
            if frame is None:
                continue
            try:
                self.on_frame(frame)
            except Exception:
                log.exception("fine layer failed on a frame")
                self.counts["fine_errors"] += 1

    def _static(self, laser: Pose, angles: np.ndarray, ranges: np.ndarray) -> np.ndarray | None:
        nav = self.navigator()
        if nav is None:
            return None
        spec = nav.costmap.spec
        occupied = nav.costmap.static_occupied
        theta = angles + laser[2]
        ok = np.isfinite(ranges)
        r = np.where(ok, ranges, 0.0)
        xy = np.stack([laser[0] + r * np.cos(theta), laser[1] + r * np.sin(theta)], axis=1)
        cells = spec.to_cell(xy)
        inside = spec.inside(cells) & ok
        static = np.zeros(len(ranges), dtype=bool)
        rows, cols = cells[inside, 0], cells[inside, 1]
        # A return on or next to an occupied cell of the static map is the map's (one cell of slack).
        hit = np.zeros(int(np.count_nonzero(inside)), dtype=bool)
        shape = occupied.shape
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr = np.clip(rows + dr, 0, shape[0] - 1)
                cc = np.clip(cols + dc, 0, shape[1] - 1)
                hit |= occupied[rr, cc]
        static[inside] = hit
        return static

    # -- the command --------------------------------------------------------------------------------

    def step(self) -> FollowSnapshot:
        t_s = self.clock_s()
        pose = self.pose()
        p_absent, bearing, _ = self._coarse()
        epoch = self.pose_epoch() if self.pose_epoch is not None else None
        with self._lock:
            if pose is not None:
                self._reframe(epoch, pose)
                self._poses.append((t_s, pose))
            before = self.tracker.estimate()
            self.tracker.predict(t_s, self.last_scan_s)
            person = self.tracker.estimate()
            if person is None and before is not None:
                self._log_drop(before, t_s, PersonDetections(np.zeros((0, 2)), np.zeros(0)))
            # The last look and what it showed, with the track they belong to: read apart, a scan handled
            # between them made the track look a scan old ("vanished"), and a loaded machine stopped the
            # robot over and over.
            looked_s, occluded = self.last_scan_s, self.occluded
        stale = self.fine is not None and (
            self.last_frame_s is None or t_s - self.last_frame_s > self.camera_stale_s
        )
        blind = looked_s is not None and t_s - looked_s > self.scan_stale_s
        if pose is None:
            command = FollowCommand(0.0, 0.0, FollowState.LOST, NO_POSE)
        elif blind:
            # No scan for a while (the laser stalled, or the machine is starved): nothing to follow on.
            command = FollowCommand(0.0, 0.0, FollowState.LOST, NO_SCAN)
        elif stale:
            self.counts["fine_camera_stale"] += int(
                self.last_frame_s is not None
            )  # frames came, then stopped
            # The estimate uses the camera: without it, stop (flagged) until it is back.
            command = FollowCommand(0.0, 0.0, FollowState.NO_CAMERA, NO_CAMERA)
        else:
            command = self.follower.step(t_s, pose, person, p_absent, bearing, occluded, looked_s=looked_s)
        v, w = command.v_mps, command.omega_radps
        age = None if looked_s is None else t_s - looked_s
        if v > 0.0 and age is not None and age > self.scan_late_s:
            # The last scan is late (a scan is due every 0.1 s and handled about 0.08 s after it was taken):
            # whether the person is still there is older news than usual, so brake ahead of the miss the
            # next scan may bring, down to standing at scan_stale_s (the "no laser scan" stop). On a
            # loaded machine this keeps the stop on a vanished person within its half second.
            v *= max(0.0, (self.scan_stale_s - age) / (self.scan_stale_s - self.scan_late_s))
            self.counts["late_scan_slowdowns"] += 1
        stepping_aside = False
        self._check = {}
        if pose is not None:
            v = self._safe(pose, v, person)
            if v <= 0.0:
                aside = self._aside(pose, person)
                if aside is not None:
                    v, w = aside
                    stepping_aside = True
        checked = v
        if self.guard is not None:
            v, w = self.guard(v, w, t_s)
        if self._check and log.isEnabledFor(logging.DEBUG):
            # Every step with a walker in sight: the check's inputs and each stage's answer (issue 23).
            log.debug(
                "walker check t=%.3f pose=%s follower=%.2f %s aside=%s checked=%.2f sent=%.2f",
                t_s,
                tuple(round(x, 3) for x in pose) if pose is not None else None,
                command.v_mps,
                " ".join(f"{k}={val}" for k, val in self._check.items()),
                stepping_aside,
                checked,
                v,
            )
        self.send(v, w)
        if self._blind and self.vanished_at_s is not None and v <= 0.0:
            self.vanish_stops_s.append(t_s - self.vanished_at_s)
            self.vanished_at_s = None
        self.counts[f"state_{command.state.value}"] += 1
        last = self.latest
        if last is None or last.command.state is not command.state:
            log.info("following: %s at t=%.2f: %s", command.state.value, t_s, command.reason)
        snap = FollowSnapshot(t_s, command, person, (v, w), stepping_aside)
        self.latest = snap
        if self.counts["steps"] % 20 == 0:
            log.debug(
                "follow t=%.1f pose=%s person=%s %s v=%.2f w=%.2f sent=%.2f,%.2f: %s",
                t_s,
                pose,
                person.xy if person is not None else None,
                command.state.value,
                command.v_mps,
                command.omega_radps,
                v,
                w,
                command.reason,
            )
        self.counts["steps"] += 1
        return snap

    def _walkers(self, nav: Navigator, person: PersonEstimate | None, pose: Pose | None = None) -> np.ndarray:
        """The navigation's moving tracks (x, y, vx, vy) but the followed person's, their velocities
        smoothed further (``walker_smoothing``, per track, once per scan): the navigation's are a quick
        half-and-half blend of each scan's step, noisy by a few tenths of a m/s, and whether the robot can
        cross in front of a walker hangs on when they get there."""
        memory: dict[int, tuple[float, float, float]] = {}
        held: dict[int, tuple[float, float, float, float, float]] = {}
        walkers = []
        for w in nav.moving.moving():
            vx, vy = w.vx_mps, w.vy_mps
            old = self._walker_memory.get(id(w))
            if old is None:
                # A track new to the loop where a walker was: the navigation re-tracks a passer-by (a
                # track dropped, or a body split in two) with the velocity started from 0 and halved
                # toward theirs scan by scan (1 m/s read as 0.6-0.85 for its first scans), which made
                # the crossing look clear and the check flip to it (issue 23): the walker's velocity
                # goes on.
                prior = self._walker_prior(w.x_m, w.y_m, w.t_s)
                if prior is not None:
                    old = (prior[0], prior[1], w.t_s)
                    self.counts["walker_velocity_carried"] += 1
            if old is not None:
                if old[2] == w.t_s:
                    vx, vy = old[0], old[1]
                else:
                    a = self.walker_smoothing
                    vx, vy = a * old[0] + (1 - a) * vx, a * old[1] + (1 - a) * vy
            memory[id(w)] = (vx, vy, w.t_s)
            held[id(w)] = (w.x_m, w.y_m, vx, vy, w.t_s)
            if person is None or math.dist((w.x_m, w.y_m), person.xy) > self.walker_is_person_m:
                walkers.append((w.x_m, w.y_m, vx, vy))
        # A walker the navigation stopped reporting (its track dropped, or split and young again, as they
        # came within half a metre of the robot) walks on for walker_hold_s: steps that saw the passer-by
        # and steps that did not alternated 0 and full speed, and the robot drove into them.
        now = self.clock_s()
        current = [(w[0], w[1]) for w in walkers]
        for key, (x, y, vx, vy, t) in self._walker_held.items():
            age = max(0.0, now - t)
            if key in held or age > self.walker_hold_s:
                continue
            px, py = x + vx * age, y + vy * age
            if any(math.dist((px, py), c) < self.walker_is_person_m for c in current):
                continue  # tracked again (under a new track)
            if (
                pose is not None
                and (px - pose[0]) * math.cos(pose[2]) + (py - pose[1]) * math.sin(pose[2]) < 0
            ):
                continue  # behind the robot: it cannot drive into them (it steps aside only from a stand)
            held[key] = (x, y, vx, vy, t)
            if person is None or math.dist((px, py), person.xy) > self.walker_is_person_m:
                walkers.append((px, py, vx, vy))
        self._walker_memory = memory
        self._walker_held = held
        return np.array(walkers, dtype=np.float64).reshape(-1, 4)

    def _walker_prior(self, x: float, y: float, t_s: float) -> tuple[float, float] | None:
        """The velocity of the walker the loop knew (tracked or held at its last call) whose position,
        walked on to ``t_s``, is nearest (x, y) within ``walker_match_m``; None when none is."""
        best, best_d = None, self.walker_match_m
        for px, py, vx, vy, t in self._walker_held.values():
            age = max(0.0, t_s - t)
            d = math.dist((px + vx * age, py + vy * age), (x, y))
            if d < best_d:
                best, best_d = (vx, vy), d
        return best

    def _aside(self, pose: Pose, person: PersonEstimate | None) -> tuple[float, float] | None:
        """Standing in a walker's way (they do not yield): a velocity toward the nearest free cell out of it
        (``give_way.aside_target``), or None when no walker threatens or there is nowhere to go."""
        nav = self.navigator()
        if nav is None or not walker_threat(pose, self._walkers(nav, person, pose), self.walker_clear_m):
            return None
        target = aside_target(nav.costmap, pose, self.aside_reach_m, True)
        if log.isEnabledFor(logging.DEBUG):
            log.debug(
                "following: aside from %s to %s; walkers %s",
                tuple(round(x, 2) for x in pose),
                target,
                np.round(self._walkers(nav, person, pose), 2).tolist(),
            )
        if target is None:
            return None
        walkers = self._walkers(nav, person, pose)
        if len(walkers):
            # Never toward a walker near the robot: the cell out of the walkers' predicted sweeps can lie
            # on their real path (their velocities are a few scans' guess; one just crossed behind the
            # robot seemed to follow it, and the robot backed toward them to 0.085 m).
            away = walkers[:, :2] - np.array(pose[:2])
            near = np.hypot(away[:, 0], away[:, 1]) <= self.aside_walker_m
            step = np.array([target[0] - pose[0], target[1] - pose[1]])
            if np.any(near & (away @ step > 0.0)):
                self.counts["asides_refused"] += 1
                return None
        self.counts["steps_aside"] += 1
        bearing = math.remainder(math.atan2(target[1] - pose[1], target[0] - pose[0]) - pose[2], math.tau)
        w = max(-1.5, min(1.5, 2.5 * bearing))
        # Forward when the target is ahead, backward when behind, turning toward the nearer of the two.
        if abs(bearing) > math.pi / 2:
            back = math.remainder(bearing + math.pi, math.tau)
            w = max(-1.5, min(1.5, 2.5 * back))
            return (-self.aside_speed_mps * math.cos(back) ** 2 if abs(back) < 0.6 else 0.0), w
        return (self.aside_speed_mps * math.cos(bearing) ** 2 if abs(bearing) < 0.6 else 0.0), w

    def _safe(self, pose: Pose, v: float, person: PersonEstimate | None) -> float:
        """``v`` as the costmap and the walkers allow it: the straight line ahead (``lookahead_s`` of
        driving plus the stopping distance at ``decel_mps2``, short of the followed person by
        ``person_clear_m``: they are the target, the collision monitor keeps the robot off them) must keep
        the footprint off the scanned obstacles, and the robot must keep ``walker_clear_m`` from every
        other walker the navigation tracks over their next seconds (:func:`walker_decision`, its decision
        kept from step to step in ``walker_mode``); those within ``walker_is_person_m`` of the followed
        person's track are them (the navigation's tracks sit on a body's near surface, and lag). The
        static layer is left to the scan: SLAM maps a person who stood still, and a wall ahead is in the
        scan."""
        nav = self.navigator()
        if nav is None or v <= 0.0:
            return v
        costmap = nav.costmap
        reach = v * self.lookahead_s + v * v / (2.0 * self.decel_mps2)
        if person is not None:
            reach = min(reach, math.dist(pose[:2], person.xy) - self.person_clear_m)
        spec = costmap.spec
        res = spec.resolution_m
        d = np.arange(0.5 * res, reach, 0.5 * res)
        if len(d):
            xy = np.stack([pose[0] + d * math.cos(pose[2]), pose[1] + d * math.sin(pose[2])], axis=1)
            cells = spec.to_cell(xy)
            r = math.ceil(costmap.config.inscribed_m / res)
            here = spec.to_cell(np.array([pose[:2]]))[0]
            for dr in range(-r, r + 1):
                for dc in range(-r, r + 1):
                    if dr * dr + dc * dc > r * r:
                        continue
                    near = cells + np.array([dr, dc])
                    ok = spec.inside(near) & np.any(near != here, axis=1)
                    if np.any(costmap.obstacles[near[ok, 0], near[ok, 1]]):
                        self.counts["costmap_stops"] += 1
                        self._check["costmap_stop"] = round(float(reach), 2)
                        return 0.0
        lead = None
        faster: tuple[float, ...] = ()
        if person is not None:
            c, s = math.cos(pose[2]), math.sin(pose[2])
            ahead = (person.xy[0] - pose[0]) * c + (person.xy[1] - pose[1]) * s
            pace = person.velocity[0] * c + person.velocity[1] * s
            lead = (ahead, pace, self.close_up_m)
            top = self.follower.config.max_speed_mps
            faster = tuple(float(x) for x in np.linspace(v, top, 4)[1:])
        walkers = self._walkers(nav, person, pose)
        if not len(walkers):
            self.walker_mode = WalkerMode.GO
            return v
        speeds = walker_candidates(v, faster)
        gaps = predicted_gaps(pose, speeds, walkers, self.walker_horizon_s, lead=lead)
        previous = self.walker_mode
        safe, self.walker_mode = walker_decision(
            speeds,
            gaps.tolist(),
            v_mps=v,
            faster=faster,
            previous=previous,
            clearance_m=self.walker_clear_m,
            keep_m=self.walker_keep_m,
            resume_m=self.walker_resume_m,
        )
        if safe < v:
            self.counts["walker_slowdowns"] += 1
        if self.walker_mode is not previous:
            self.counts[f"walker_{self.walker_mode.value}"] += 1
        if log.isEnabledFor(logging.DEBUG):
            self._check["lead"] = None if lead is None else tuple(round(x, 3) for x in lead)
            self._check["walkers"] = np.round(walkers, 3).tolist()
            self._check["gaps"] = " ".join(f"{a:.2f}:{g:.2f}" for a, g in zip(speeds, gaps, strict=True))
            self._check["mode"] = f"{previous.value}->{self.walker_mode.value}"
            self._check["safe"] = round(safe, 3)
        return safe

    def run(self, stop: threading.Event) -> None:
        """Step every ``period_s`` (and at once when a scan misses the person) until ``stop``; stop the
        wheels when it ends."""
        try:
            while not stop.is_set():
                self._wake.wait(self.period_s)
                self._wake.clear()
                if stop.is_set():
                    break
                if not self.sync_active():
                    continue
                try:
                    snap = self.step()
                    if self.on_step is not None:
                        self.on_step(snap)
                except Exception:  # a bad step stops the robot, it does not end following
                    log.exception("follow step failed")
                    self.send(0.0, 0.0)
        finally:
            self.send(0.0, 0.0)


def follow_summary(loop: FollowLoop) -> dict[str, Any]:
    """The follow loop's last state and counts, for the final status."""
    latest = loop.latest
    return {
        "state": None if latest is None else latest.command.state.value,
        "reason": None if latest is None else latest.command.reason,
        "person": None if latest is None or latest.person is None else list(latest.person.xy),
        "counts": dict(loop.counts),
        "tracker": dict(loop.tracker.counts),
        "fine": dict(loop.locator.counts) if loop.locator is not None else None,
    }
