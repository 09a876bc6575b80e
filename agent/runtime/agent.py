"""The agent process's runtime: device threads, the hot path, SLAM beside it, fusion, output, health.

Threads (each beats its own heartbeat; the critical ones gate the systemd watchdog)::

    camera   grab -> LatestMailbox ------------------------------+
    vlp      (hot path) take the newest frame -> VLP fix -> fuse -> pose bytes written
    laser    read scan -> BoundedQueue --------------------------+
    slam     scan + odometry at its time -> RBPF -> fuse the pose of each filter update
    servos   read wheels -> odometry -> fuse; send the velocity command (dead-man: zero when stale)
    imu      read -> gyro yaw rate -> fuse; accelerometer -> tilt for VLP
    rfid     read tags (kept for the status; person following and landmarks come later)
    output   keeps the pose stream at rate_hz when nothing else writes (camera stalled, no fix)
    monitor  heartbeats -> READY / WATCHDOG / STATUS / STOPPING

A device that fails is reported (pose flags, status, log) and its loop keeps trying: the drivers that
reconnect by themselves (laser, servos, RFID) are left to it, the others are closed and reopened. The
rest carry on. Nothing here prints, installs signal handlers or configures logging: the commands do.
"""

from __future__ import annotations

import collections
import contextlib
import gc
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from agent.config import AgentConfig, MountConfig
from agent.fusion import Estimate, FilterNoise, PoseFilter, Source
from agent.runtime.collector import IdleCollector
from agent.runtime.devices import Devices
from agent.runtime.health import HealthMonitor, Heartbeat, NotifierLike
from agent.runtime.hotpath import HotPath
from agent.runtime.localizer import FrameLocalizer
from agent.runtime.mailbox import BoundedQueue, LatestMailbox, MailboxClosed
from agent.runtime.mapper import ScanMapper
from agent.runtime.motion import DriveCommand, OdometryTrack, StillDetector, TiltEstimator, wheel_speeds
from agent.runtime.output import LatencyStats, PoseOutput
from agent.runtime.priority import CpuLatencyRequest, realtime_thread
from agent.runtime.recorder import Recorder
from agent.runtime.types import AbsoluteFix, NoFix, Prior
from drivers.device import Device
from drivers.errors import DeviceDisconnected, DeviceError, DeviceTimeout
from drivers.samples import Frame, Scan, TagRead, WheelState
from drivers.servos.odometry import WheelOdometry
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["Agent", "AgentStatus", "DeviceState"]

log = logging.getLogger(__name__)

_SOURCE_FLAGS = {
    Source.VLP: PoseFlags.VLP,
    Source.SLAM: PoseFlags.SLAM,
    Source.ODOMETRY: PoseFlags.ODOMETRY,
    Source.IMU: PoseFlags.IMU,
}
_POSITION_FLAGS = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY
_FAULT_FLAGS = PoseFlags.LASER_LOST | PoseFlags.CAMERA_STALLED | PoseFlags.SERVO_FAULT
# A VLP prior is never tighter than this: the filter may be confident and wrong.
_MIN_PRIOR_SIGMA_XY_M = 0.05
_MIN_PRIOR_SIGMA_YAW_RAD = math.radians(3.0)
# SLAM starts its map only once the fused pose is known this well (the map frame is the fused frame).
_SLAM_START_SIGMA_M = 0.25
# At most one VLP fix per this interval goes to SLAM: the filter multiplies every fix it is given into its
# weights at the next update, and thirty nearly identical fixes would count as thirty independent ones.
_SLAM_FIX_INTERVAL_NS = 500_000_000
_IMU_PERIOD_S = 0.01
# The IMU tilt is only learnt while odometry this recent says the base stands still.
_TILT_ODOMETRY_AGE_NS = 60_000_000
# Not localizing for this long (past start-up) before the first warning: the first fix after the devices
# open takes a few seconds.
_NOT_LOCALIZING_GRACE_S = 5.0


@dataclass(frozen=True, slots=True)
class DeviceState:
    name: str
    ok: bool
    reason: str
    since_ns: int
    failures: int
    recoveries: int


class _DeviceWatch:
    """One device's state as its loop sees it: transitions are logged once, not every failed read."""

    def __init__(self, name: str, clock_ns: Callable[[], int]) -> None:
        self.name = name
        self.clock_ns = clock_ns
        self.ok = False
        self.opened_once = False
        self.reason = "not opened yet"
        self.since_ns = clock_ns()
        self.last_good_ns = 0
        self.failures = 0
        self.recoveries = 0
        self._lock = threading.Lock()

    def good(self) -> bool:
        """A successful operation; True when this ends a fault (a recovery)."""
        now = self.clock_ns()
        with self._lock:
            self.last_good_ns = now
            if self.ok:
                return False
            recovered = self.opened_once
            self.ok, self.reason, self.since_ns = True, "", now
            self.opened_once = True
            if recovered:
                self.recoveries += 1
        if recovered:
            log.warning("%s: recovered", self.name)
        else:
            log.info("%s: up", self.name)
        return recovered

    def bad(self, reason: str) -> None:
        now = self.clock_ns()
        with self._lock:
            self.failures += 1
            first = self.ok or not self.reason or self.reason == "not opened yet"
            if self.ok:
                self.since_ns = now
            self.ok, self.reason = False, reason
        if first:
            log.warning("%s: %s", self.name, reason)
        else:
            log.debug("%s: %s", self.name, reason)

    def state(self) -> DeviceState:
        with self._lock:
            return DeviceState(self.name, self.ok, self.reason, self.since_ns, self.failures, self.recoveries)


@dataclass(frozen=True)
class AgentStatus:
    """A snapshot for the status line, the sim's summary and tests."""

    t_ns: int
    estimate: Estimate
    flags: PoseFlags
    devices: dict[str, DeviceState]
    counts: dict[str, int]
    drops: dict[str, int]
    latency_ms: tuple[float, float]  # frame captured (handed over by its driver) -> last pose byte: p50, p99
    exposure_age_ms: tuple[float, float]  # the frame's mid-exposure -> last pose byte: p50, p99
    vlp_ms: tuple[float, float]  # VLP processing per frame: p50, p99
    no_fix_reasons: dict[str, int]
    fusion: dict[str, int]
    mapper: dict[str, int]
    output: dict[str, int]
    unavailable: dict[str, str] = field(default_factory=dict)
    ready: bool = False
    # The hot path's own work per frame (frame taken -> pose written), in its thread's CPU time: p50, p99.
    # The latency less this is waiting: for the interpreter lock, for a core, for the hypervisor.
    hot_path_cpu_ms: tuple[float, float] = (math.nan, math.nan)


class Agent:
    """The whole loop, on injected devices. ``start()`` then ``stop()``; everything in between is threads.

    Args:
        config: the robot's config.
        devices: built, not necessarily opened (the loops open them).
        localizer: VLP (None: no VLP; ``unavailable`` says why, for the status).
        mapper: SLAM (None: no SLAM).
        output: the pose stream (None: none, e.g. a test that reads poses directly).
        notifier: systemd's (``agent.sdnotify.Notifier``) or None.
        initial_pose: where the base starts (x_m, y_m, yaw_rad) when the config does not say.
        laser_mount: where the laser sits (SLAM), when the config does not say.
    """

    def __init__(
        self,
        config: AgentConfig,
        devices: Devices,
        *,
        localizer: FrameLocalizer | None = None,
        mapper: ScanMapper | None = None,
        output: PoseOutput | None = None,
        notifier: NotifierLike | None = None,
        initial_pose: tuple[float, float, float] | None = None,
        unavailable: dict[str, str] | None = None,
        recorder: Recorder | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.config = config
        self.devices = devices
        self.localizer = localizer
        self.mapper = mapper
        self.output = output
        self.clock_ns = clock_ns
        self.unavailable = dict(unavailable or {})
        self.recorder = recorder
        fc = config.fusion
        x0 = fc.initial_pose or initial_pose or (0.0, 0.0, 0.0)
        P0 = np.diag([fc.initial_sigma_xy_m**2, fc.initial_sigma_xy_m**2, fc.initial_sigma_yaw_rad**2])
        self.fusion = PoseFilter(
            np.asarray(x0, dtype=np.float64),
            P0,
            clock_ns(),
            FilterNoise(
                odometry_sigma_m_per_m=fc.odometry_sigma_m_per_m,
                odometry_yaw_rate_sigma_radps=fc.odometry_yaw_rate_sigma_radps,
                odometry_time_sigma_s=fc.odometry_time_sigma_s,
                gyro_sigma_radps=fc.gyro_sigma_radps,
                yaw_rate_walk_radps2=fc.yaw_rate_walk_radps2,
                gyro_bias_walk_radps=fc.gyro_bias_walk_radps,
            ),
            gate_probability=fc.gate_probability,
            history_s=fc.history_s,
            odometry_hold_s=fc.odometry_timeout_s,
            observer=recorder.record_input if recorder is not None else None,
        )
        self.timeouts_ns = {
            Source.VLP: int(fc.vlp_timeout_s * 1e9),
            Source.SLAM: int(fc.slam_timeout_s * 1e9),
            Source.ODOMETRY: int(fc.odometry_timeout_s * 1e9),
            Source.IMU: int(fc.imu_timeout_s * 1e9),
        }
        self.frames: LatestMailbox[tuple[Frame, int]] = LatestMailbox()
        # SLAM gives way (between particles) while a frame waits for or is on the hot path.
        frames = self.frames
        self.hot_path = HotPath(lambda: frames.pending)
        # Off until settle_heap(): the collector then runs between frames on the hot path's thread.
        self.collector = IdleCollector()
        self.scans: BoundedQueue[Scan] = BoundedQueue(config.slam.queue_size)
        self.slam_fixes: BoundedQueue[AbsoluteFix] = BoundedQueue(4)
        self.odometry_track = OdometryTrack(hold_s=fc.odometry_timeout_s)
        cc = config.control
        self.drive = DriveCommand(
            cc.deadman_timeout_s, cc.recovery_hold_s, cc.max_speed_mps, cc.max_turn_radps
        )
        self.tilt = TiltEstimator()
        self.health = HealthMonitor(
            notifier,
            self.status_line,
            status_interval_s=config.health.status_interval_s,
            watchdog=config.health.watchdog,
        )
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._watch: dict[str, _DeviceWatch] = {name: _DeviceWatch(name, clock_ns) for name in devices.all()}
        self._counts: collections.Counter[str] = collections.Counter()
        self._counts_lock = threading.Lock()
        self._no_fix: collections.Counter[str] = collections.Counter()
        self._vlp_ms = LatencyStats()
        self._hot_cpu_ms = LatencyStats()
        self._last_frame_ns = 0
        self._last_scan_ns = 0
        self._slam_good = False  # the last SLAM filter update matched and was fused
        self._last_slam_fix_ns = 0
        self._hardware_error = (0, 0)
        # When the wheel read in progress started (agent clock), 0 between reads: a read that hangs is a
        # servo fault, a loop that is merely late (the machine stalled) is not.
        self._servo_read_since_ns = 0
        self.still = StillDetector()
        self._tags: collections.deque[TagRead] = collections.deque(maxlen=64)
        self._started_ns = 0
        self._stopped = False
        self._cpu_latency: CpuLatencyRequest | None = None

    # -- public -------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start every loop. Devices are opened by their loops; the output is opened now if it can be."""
        self._started_ns = self.clock_ns()
        self._hold_cpu_latency()
        if self.recorder is not None:
            self.recorder.start(self.fusion.parameters)
        if self.output is not None:
            try:
                self.output.open()
            except DeviceError as exc:
                log.warning("%s (retrying as poses come)", exc)
        d = self.devices
        timeout = self.config.health.loop_timeout_s
        if d.camera is not None:
            self._spawn("camera", self._critical("camera"), timeout, self._camera_loop)
            self._spawn("vlp", self._critical("camera"), timeout, self._vlp_loop)
        if d.laser is not None:
            self._spawn("laser", self._critical("laser"), timeout, self._laser_loop)
            self._spawn("slam", self._critical("laser"), max(timeout, 5.0), self._slam_loop)
        if d.servos is not None:
            self._spawn("servos", self._critical("servos"), timeout, self._servo_loop)
        if d.imu is not None:
            self._spawn("imu", self._critical("imu"), timeout, self._imu_loop)
        if d.rfid is not None:
            self._spawn("rfid", self._critical("rfid"), timeout, self._rfid_loop)
        if self.output is not None:
            self._spawn("output", True, timeout, self._output_loop)
        monitor = threading.Thread(target=self._monitor_loop, name="agent-monitor", daemon=True)
        monitor.start()
        self._threads.append(monitor)

    def settle_heap(self) -> None:
        """Once started: collect, freeze what survived (``gc.freeze``: later full passes skip the long-lived
        objects), and, when there is a hot path, run the collector between its frames from now on instead
        of in whichever thread allocates (``agent.runtime.collector``) until :meth:`stop`."""
        if self.devices.camera is not None:
            self.collector.start()
        else:
            gc.collect()
            gc.freeze()

    def stop(self, timeout_s: float = 1.5) -> None:
        """Stop the loops, command zero, close the devices and the output. Safe to call twice."""
        if self._stopped:
            return
        self._stopped = True
        self.health.stopping("stopping: wheels to zero, closing devices")
        self._stop.set()
        self.hot_path.close()
        self.frames.close()
        self.scans.close()
        self.slam_fixes.close()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                log.warning("thread %s did not stop in time", thread.name)
        self.collector.stop()
        servos = self.devices.servos
        if servos is not None and servos.is_open:
            try:
                servos.stop()
            except DeviceError as exc:
                log.warning("could not command zero velocity while stopping: %s", exc)
        for name, device in self.devices.all().items():
            try:
                device.close()
            except DeviceError as exc:
                log.warning("%s: close failed: %s", name, exc)
        if self.output is not None:
            self.output.close()
        if self.recorder is not None:
            self.recorder.close()
        if self._cpu_latency is not None:
            self._cpu_latency.release()

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def command_velocity(self, v_mps: float, omega_radps: float) -> None:
        """A velocity command for the base; it must be repeated within the dead-man timeout."""
        self.drive.set(v_mps, omega_radps, self.clock_ns())

    def pose(self) -> tuple[Estimate, PoseFlags]:
        """The fused pose after the newest measurement, and the status word."""
        now = self.clock_ns()
        return self.fusion.estimate(), self.flags(now)

    def flags(self, now_ns: int | None = None) -> PoseFlags:
        """The status word: live sources (bits 0-7) and faults (bits 8-15)."""
        now = self.clock_ns() if now_ns is None else now_ns
        flags = PoseFlags(0)
        live = self.fusion.live(now, self.timeouts_ns)
        for source in (Source.VLP, Source.ODOMETRY):
            if source in live:
                flags |= _SOURCE_FLAGS[source]
        if self._slam_live(now):
            flags |= PoseFlags.SLAM
        # The IMU gives yaw rate (and tilt), never position: alone it turns a frozen position, which is a
        # stale hold (docs/wire-format.md), so its bit is set only beside a live position source.
        if Source.IMU in live and flags & _POSITION_FLAGS:
            flags |= PoseFlags.IMU
        hc = self.config.health
        d = self.devices
        if d.laser is not None and (
            now - self._last_scan_ns > hc.laser_lost_s * 1e9 or not self._watch["laser"].ok
        ):
            flags |= PoseFlags.LASER_LOST
        if d.camera is not None and now - self._last_frame_ns > hc.camera_stall_s * 1e9:
            flags |= PoseFlags.CAMERA_STALLED
        if d.servos is not None and self._servo_fault(now):
            flags |= PoseFlags.SERVO_FAULT
        if (flags & _FAULT_FLAGS) or (self._expected_sources() & ~flags):
            flags |= PoseFlags.DEGRADED
        return flags

    def _servo_fault(self, now_ns: int) -> bool:
        """The servos, not the machine, are at fault: the last wheel read (or the port's opening) failed, a
        servo reports hardware error bits, a wheel read has been hanging for ``health.servo_fault_s``, or
        the servo loop itself has stopped (its heartbeat past the loop timeout). A loop that is only late
        (the whole agent stalled for a moment) is not a servo fault: the ODOMETRY bit going off says that."""
        watch = self._watch["servos"]
        if not watch.ok or any(self._hardware_error):
            return True
        since = self._servo_read_since_ns
        if since and now_ns - since > self.config.health.servo_fault_s * 1e9:
            return True
        beat = self.health.heartbeat("servos")
        return beat is not None and not beat.alive()

    def status(self) -> AgentStatus:
        now = self.clock_ns()
        with self._counts_lock:
            counts = dict(self._counts)
            no_fix = dict(self._no_fix.most_common(8))
        # How often background loops waited for the hot path, and waits cut at the bound (a hot path
        # stuck for longer than max_wait_s).
        counts["hot_path_waits"] = self.hot_path.waits
        counts["hot_path_wait_timeouts"] = self.hot_path.timeouts
        # Garbage collections run between frames (agent.runtime.collector), by generation.
        for generation, n in enumerate(self.collector.collections):
            counts[f"gc_between_frames_{generation}"] = n
        drops = {
            "camera_mailbox": self.frames.dropped,
            "scan_queue": self.scans.dropped,
            "slam_fix_queue": self.slam_fixes.dropped,
        }
        for name, device in self.devices.all().items():
            counters = device.health().counters
            for key in ("dropped", "scans_dropped"):
                if counters.get(key):
                    drops[f"{name}_{key}"] = counters[key]
        latency = exposure_age = (math.nan, math.nan)
        output: dict[str, int] = {}
        if self.output is not None:
            p50, p99 = self.output.latency.percentiles(50, 99)
            latency = (p50, p99)
            q50, q99 = self.output.exposure_age.percentiles(50, 99)
            exposure_age = (q50, q99)
            output = dict(self.output.counts)
            if output.get("write_timeouts"):
                drops["output_write_timeouts"] = output["write_timeouts"]
        vlp_ms = self._vlp_ms.percentiles(50, 99)
        cpu_ms = self._hot_cpu_ms.percentiles(50, 99)
        return AgentStatus(
            now,
            self.fusion.estimate(),
            self.flags(now),
            {name: w.state() for name, w in self._watch.items()},
            counts,
            drops,
            latency,
            exposure_age,
            (vlp_ms[0], vlp_ms[1]),
            no_fix,
            self.fusion.counters(),
            self.mapper.counters() if self.mapper is not None else {},
            output,
            dict(self.unavailable),
            self.health.is_ready,
            (cpu_ms[0], cpu_ms[1]),
        )

    def status_line(self) -> str:
        """One line for STATUS= and logs; it starts with ``NOT LOCALIZING`` and why while no position source
        is live (the pose is a stale hold)."""
        est = self.fusion.estimate()
        flags = self.flags()
        names = [f.name for f in PoseFlags if f & flags and f.name] or ["no source"]
        prefix = "" if flags & _POSITION_FLAGS else f"NOT LOCALIZING: {self.not_localizing_reason()}; "
        latency = ""
        if self.output is not None and len(self.output.latency):
            p50, p99 = self.output.latency.percentiles(50, 99, last=300)
            latency = f" latency p50 {p50:.1f} ms p99 {p99:.1f} ms"
        return (
            f"{prefix}pose ({est.x_m:.3f}, {est.y_m:.3f}, {math.degrees(est.yaw_rad):.1f} deg) "
            f"+-{100 * est.sigma_xy_m:.1f} cm [{' '.join(names)}]{latency}"
        )

    def tags(self) -> list[TagRead]:
        return list(self._tags)

    # -- helpers -----------------------------------------------------------------------------------
    def _count(self, what: str, n: int = 1) -> None:
        with self._counts_lock:
            self._counts[what] += n

    def _critical(self, name: str) -> bool:
        """Whether the watchdog waits for this device's loops (the config says; an injected device the
        config does not list: the default for its kind)."""
        device = self.config.devices.get(_kind(name))
        return device.critical if device is not None else name in ("camera", "laser", "servos")

    def _expected_sources(self) -> PoseFlags:
        expected = PoseFlags(0)
        if self.localizer is not None:
            expected |= PoseFlags.VLP
        if self.mapper is not None:
            expected |= PoseFlags.SLAM
        if self.devices.servos is not None:
            expected |= PoseFlags.ODOMETRY
        if self.devices.imu is not None:
            expected |= PoseFlags.IMU
        return expected

    def _slam_live(self, now_ns: int) -> bool:
        """SLAM counts as live while scans reach it and its last filter update matched and was fused
        (between updates, every 0.25 m, it has nothing new to say; that is not a fault)."""
        if self.mapper is None or not self._slam_good:
            return False
        return now_ns - self._last_scan_ns <= self.timeouts_ns[Source.SLAM] and self._watch["laser"].ok

    def _spawn(self, name: str, critical: bool, timeout_s: float, body: Callable[[Heartbeat], None]) -> None:
        beat = self.health.register(name, critical, timeout_s)

        def run() -> None:
            try:
                body(beat)
            except MailboxClosed:
                pass
            except Exception:  # a bug: log it; the stopped heartbeat withholds the watchdog
                log.exception("loop %r died", name)

        thread = threading.Thread(target=run, name=f"agent-{name}", daemon=True)
        thread.start()
        self._threads.append(thread)

    def _open(self, name: str, device: Device, after: Callable[[], None] | None = None) -> bool:
        """Open ``device`` if it is closed; False (and reported) when it cannot be yet."""
        if device.is_open:
            return True
        try:
            device.open()
            if after is not None:
                after()
        except DeviceError as exc:
            self._watch[name].bad(f"cannot open: {exc}")
            with contextlib.suppress(DeviceError):
                device.close()
            return False
        self._watch[name].good()
        return True

    def _retry_wait(self, beat: Heartbeat, seconds: float) -> None:
        """Wait before the next attempt, beating while waiting."""
        end = time.monotonic() + seconds
        while not self._stop.is_set():
            beat.beat()
            remaining = end - time.monotonic()
            if remaining <= 0:
                return
            self._stop.wait(min(remaining, 0.25))

    def _prior(self, t_ns: int) -> Prior:
        est = self.fusion.estimate_at(t_ns)
        c, s = math.cos(est.yaw_rad), math.sin(est.yaw_rad)
        return Prior(
            est.x_m,
            est.y_m,
            est.yaw_rad,
            max(est.sigma_xy_m, _MIN_PRIOR_SIGMA_XY_M),
            max(est.sigma_yaw_rad, _MIN_PRIOR_SIGMA_YAW_RAD),
            est.v_mps * c,
            est.v_mps * s,
            est.omega_radps,
        )

    def _vlp_covariance(self, fix: AbsoluteFix) -> np.ndarray:
        """The fix's covariance plus the floor the config sets for what it leaves out (the LED survey's and
        the calibration's errors, the same for every frame under the same LEDs)."""
        vc = self.config.vlp
        cov = np.array(fix.covariance, dtype=np.float64)
        cov[0, 0] += vc.sigma_floor_m**2
        cov[1, 1] += vc.sigma_floor_m**2
        if fix.yaw_rad is not None and cov.shape[0] == 3:
            cov[2, 2] += vc.sigma_floor_yaw_rad**2
        return cov

    def _publish(self, trigger_ns: int | None, arrival_ns: int | None = None) -> None:
        if self.output is None:
            return
        estimate, flags = self.fusion.estimate(), self.flags()
        written = self.output.publish(estimate, flags, trigger_ns, arrival_ns)
        if written is not None and self.recorder is not None:
            self.recorder.record_output(estimate, int(flags))

    # -- camera and the hot path --------------------------------------------------------------------
    def _hold_cpu_latency(self) -> None:
        """Ask the kernel to keep idle cores out of deep sleep while the agent runs, when configured: a
        frame that has to wake a sleeping core starts cold (``agent.runtime.priority.CpuLatencyRequest``)."""
        latency_us = self.config.scheduling.cpu_latency_us
        if latency_us < 0 or self.devices.camera is None:
            return
        request = CpuLatencyRequest(latency_us)
        refused = request.acquire()
        with self._counts_lock:
            self._counts["cpu_latency_held"] = int(refused is None)
        if refused is None:
            self._cpu_latency = request
            log.info("CPU wake-up latency limited to %d us while running (PM QoS)", latency_us)
        else:
            log.warning("CPU wake-up latency not limited: %s", refused)

    def _realtime(self, loop: str) -> None:
        """Put the calling loop's thread under real-time scheduling when configured and permitted."""
        priority = self.config.scheduling.realtime_priority
        refused = realtime_thread(priority)
        with self._counts_lock:
            self._counts[f"{loop}_realtime"] = int(refused is None)
        if refused is None:
            log.info("%s thread at SCHED_FIFO priority %d", loop, priority)
        elif priority:
            log.warning("%s thread time-shared: real-time scheduling %s", loop, refused)

    def _camera_loop(self, beat: Heartbeat) -> None:
        camera = self.devices.camera
        assert camera is not None
        self._realtime("camera")
        timeout_s = self.config.health.camera_stall_s
        while not self._stop.is_set():
            beat.beat()
            if not self._open("camera", camera):
                self._retry_wait(beat, 1.0)
                continue
            try:
                frame = camera.grab(timeout_s=timeout_s)
            except DeviceTimeout as exc:
                self._watch["camera"].bad(f"stalled: {exc}")
                continue
            except DeviceError as exc:
                self._watch["camera"].bad(f"failed: {exc}; reopening")
                with contextlib.suppress(DeviceError):
                    camera.close()
                self._retry_wait(beat, 0.5)
                continue
            self._watch["camera"].good()
            arrival = self.clock_ns()
            self._last_frame_ns = arrival
            self._count("frames")
            self.hot_path.frame_queued()
            self.frames.put((frame, arrival))

    def _vlp_loop(self, beat: Heartbeat) -> None:
        self._realtime("hot_path")
        while not self._stop.is_set():
            beat.beat()
            item = self.frames.take(0.25)
            if item is None or self.localizer is None:
                self.hot_path.settle()
                self.collector.collect_if_due()
                continue
            with self.hot_path.busy():
                c0 = time.thread_time()
                try:
                    self._locate(*item)
                finally:
                    self._hot_cpu_ms.add(1e3 * (time.thread_time() - c0))
            # The pose is written: the garbage of this frame (and of every other thread) goes now.
            self.collector.collect_if_due()

    def _locate(self, frame: Frame, arrival_ns: int) -> None:
        """The hot path: frame -> fix -> fusion -> pose bytes written."""
        t = frame.host_time_ns
        tilt = self.tilt.tilt() if self.devices.imu is not None else None
        assert self.localizer is not None
        t0 = time.perf_counter()
        result = self.localizer.process(frame, tilt, self._prior(t))
        elapsed_ms = 1e3 * (time.perf_counter() - t0)
        self._vlp_ms.add(elapsed_ms)
        with self._counts_lock:
            if isinstance(result, NoFix):
                self._no_fix[result.reason] += 1
                self._counts["no_fix"] += 1
                return
            self._counts["fixes"] += 1
        fused = self.fusion.add_pose(
            Source.VLP,
            result.t_ns,
            result.x_m,
            result.y_m,
            result.yaw_rad,
            self._vlp_covariance(result),
            arrival_ns=self.clock_ns(),
            relocalize=True,
        )
        if fused.relocalized:
            log.warning("fusion relocalized on VLP (reset counter %d)", self.fusion.reset_counter)
            self._count("relocalizations")
        if not fused.accepted:
            self._count("fixes_rejected")
            return
        self._count("fixes_fused")
        self._publish(trigger_ns=t, arrival_ns=arrival_ns)
        if self.mapper is not None and t - self._last_slam_fix_ns >= _SLAM_FIX_INTERVAL_NS:
            self._last_slam_fix_ns = t
            with contextlib.suppress(MailboxClosed):
                self.slam_fixes.put(result)

    # -- laser and SLAM -----------------------------------------------------------------------------
    def _laser_loop(self, beat: Heartbeat) -> None:
        laser = self.devices.laser
        assert laser is not None
        watch = self._watch["laser"]
        while not self._stop.is_set():
            beat.beat()
            if not self._open("laser", laser, laser.start):
                self._retry_wait(beat, 1.0)
                continue
            try:
                scan = laser.read(timeout_s=0.25)
            except DeviceDisconnected as exc:
                # The driver reconnects by itself while it is open; wait for it.
                watch.bad(f"lost: {exc}")
                self._slam_good = False
                self._retry_wait(beat, 0.1)
                continue
            except DeviceTimeout:
                if self.clock_ns() - self._last_scan_ns > self.config.health.laser_lost_s * 1e9:
                    watch.bad("no scan within the timeout")
                continue
            except DeviceError as exc:
                watch.bad(f"failed: {exc}")
                self._retry_wait(beat, 0.25)
                continue
            watch.good()
            self._last_scan_ns = self.clock_ns()
            self._count("scans")
            if self.mapper is not None:
                self.scans.put(scan)

    def _odometry_at(self, t_ns: int) -> tuple[float, float, float] | None:
        if self.devices.servos is not None:
            return self.odometry_track.at(t_ns)
        est = self.fusion.estimate_at(t_ns)  # no wheels: the fused pose is the best motion guess
        return (est.x_m, est.y_m, est.yaw_rad)

    def slam_start_pose(self, t_ns: int) -> tuple[float, float, float] | None:
        """Where SLAM starts its map: the fused pose at ``t_ns`` once it is known well enough, else None."""
        est = self.fusion.estimate_at(t_ns)
        if est.sigma_xy_m > _SLAM_START_SIGMA_M:
            return None
        return (est.x_m, est.y_m, est.yaw_rad)

    def _slam_loop(self, beat: Heartbeat) -> None:
        mapper = self.mapper
        while not self._stop.is_set():
            beat.beat()
            scan = self.scans.get(0.25)
            if scan is None or mapper is None:
                continue
            self.hot_path.give_way()
            for fix in self.slam_fixes.drain():
                odom = self._odometry_at(fix.t_ns)
                if odom is not None:
                    mapper.add_fix(fix, odom)
            odom = self._odometry_at(scan.host_time_ns)
            if odom is None:
                self._count("slam_scans_without_odometry")
                continue
            step = mapper.update(scan, odom)
            self._count(f"slam_{step.kind}")
            if step.kind == "updated":
                if step.fix is None:
                    self._slam_good = False
                    continue
                fix = step.fix
                result = self.fusion.add_pose(
                    Source.SLAM,
                    fix.t_ns,
                    fix.x_m,
                    fix.y_m,
                    fix.yaw_rad,
                    fix.covariance,
                    arrival_ns=self.clock_ns(),
                )
                self._slam_good = result.accepted
                self._count("slam_fused" if result.accepted else "slam_rejected")

    # -- servos: odometry in, velocity out ------------------------------------------------------------
    def _servo_loop(self, beat: Heartbeat) -> None:
        servos = self.devices.servos
        assert servos is not None
        watch = self._watch["servos"]
        period_s = 1.0 / self.config.control.loop_rate_hz
        radius = float(getattr(servos, "wheel_radius_m", 0.0))
        track = float(getattr(servos, "track_m", 0.0))
        if not (radius > 0 and track > 0):
            raise DeviceError("the servo backend does not say its wheel radius and track", "servos")
        odometry = WheelOdometry(radius, track)
        previous: WheelState | None = None
        merged = False
        # Twice what the base can do, plus slack: beyond this an odometry interval's timing is wrong.
        cc = self.config.control
        max_ds_per_s = 2.0 * cc.max_speed_mps + 0.1
        max_dyaw_per_s = 2.0 * cc.max_turn_radps + 0.5
        t_next = time.monotonic()
        while not self._stop.is_set():
            beat.beat()
            if not self._open("servos", servos):
                previous = None
                self._retry_wait(beat, 1.0)
                continue
            self.hot_path.give_way()
            self._servo_read_since_ns = self.clock_ns()
            try:
                state = servos.read()
            except DeviceError as exc:
                self._servo_read_since_ns = 0
                watch.bad(f"silent: {exc}")
                previous = None
                merged = False
                # Whatever still listens stops; a silent servo keeps its last goal until it hears again.
                with contextlib.suppress(DeviceError):
                    servos.set_velocity(0.0, 0.0)
                self._stop.wait(period_s)
                continue
            self._servo_read_since_ns = 0
            now = self.clock_ns()
            if watch.good():
                # Back from a fault: zero first, and hold zero a moment whatever the command says.
                self.drive.hold(now)
                self._count("servo_recoveries")
                try:
                    servos.set_velocity(0.0, 0.0)
                    self._count("zero_on_recovery")
                    log.warning("servos answer again: zero velocity commanded")
                except DeviceError as exc:
                    watch.bad(f"zero velocity after recovery failed: {exc}")
                    continue
            self._hardware_error = state.hardware_error
            if any(state.hardware_error):
                self._count("servo_hardware_error_reads")
            deferred = False
            if previous is not None and state.host_time_ns > previous.host_time_ns:
                dl = state.position_rad[0] - previous.position_rad[0]
                dr = state.position_rad[1] - previous.position_rad[1]
                # ds = r (dphi_l + dphi_r) / 2, dyaw = r (dphi_r - dphi_l) / track
                ds = radius * (dl + dr) / 2.0
                dyaw = radius * (dr - dl) / track
                dt = (state.host_time_ns - previous.host_time_ns) * 1e-9
                if not merged and (abs(ds) > max_ds_per_s * dt or abs(dyaw) > max_dyaw_per_s * dt):
                    # Faster than the base can go: the read's host time is earlier than when the servos
                    # sampled (a reply that waited for a busy bus or CPU). The distance is right, the stamp
                    # is not: leave this sample out and let the next interval span both.
                    deferred = merged = True
                    self._count("odometry_merged")
                else:
                    merged = False
                    self.fusion.add_odometry(
                        previous.host_time_ns, state.host_time_ns, ds, dyaw, arrival_ns=now
                    )
            elif previous is None and odometry.odom is not None:
                # A new reference after a fault: the odometry frame continues from where it was.
                last = odometry.odom
                odometry.reset(last.x_m, last.y_m, last.yaw_rad)
            odom = odometry.update(state)
            if previous is None:
                self.still.reset()
            self.still.update(state.host_time_ns, (odom.x_m, odom.y_m, odom.yaw_rad))
            self.odometry_track.add(state.host_time_ns, (odom.x_m, odom.y_m, odom.yaw_rad))
            if not deferred:
                previous = state
            self._count("wheel_reads")
            command = self.drive.current(self.clock_ns())
            left, right = wheel_speeds(command.v_mps, command.omega_radps, radius, track)
            try:
                servos.set_velocity(left, right)
            except DeviceError as exc:
                watch.bad(f"velocity command failed: {exc}")
            t_next += period_s
            now_s = time.monotonic()
            if t_next < now_s:
                t_next = now_s
            self._stop.wait(t_next - now_s)

    # -- IMU, RFID ------------------------------------------------------------------------------------
    def _imu_loop(self, beat: Heartbeat) -> None:
        imu = self.devices.imu
        assert imu is not None
        watch = self._watch["imu"]
        t_next = time.monotonic()
        while not self._stop.is_set():
            beat.beat()
            if not self._open("imu", imu):
                self._retry_wait(beat, 1.0)
                continue
            self.hot_path.give_way()
            try:
                sample = imu.read()
            except DeviceError as exc:
                watch.bad(f"failed: {exc}")
                self._retry_wait(beat, 0.1)
                continue
            watch.good()
            self._count("imu_samples")
            now = self.clock_ns()
            self.fusion.add_gyro(sample.host_time_ns, sample.gyro_radps[2], arrival_ns=now)
            if self.still.still_at(sample.host_time_ns, _TILT_ODOMETRY_AGE_NS):
                # Only a base that stands still feels gravity alone (see TiltEstimator).
                self.tilt.update(sample.host_time_ns, sample.accel_mps2)
            t_next += _IMU_PERIOD_S
            now_s = time.monotonic()
            if t_next < now_s:
                t_next = now_s
            self._stop.wait(t_next - now_s)

    def _rfid_loop(self, beat: Heartbeat) -> None:
        rfid = self.devices.rfid
        assert rfid is not None
        watch = self._watch["rfid"]
        while not self._stop.is_set():
            beat.beat()
            if not self._open("rfid", rfid):
                self._retry_wait(beat, 1.0)
                continue
            try:
                tag = rfid.read(timeout_s=0.25)
            except DeviceError as exc:
                watch.bad(f"failed: {exc}")
                self._retry_wait(beat, 0.5)
                continue
            if rfid.health().connected:
                watch.good()
            if tag is not None:
                self._tags.append(tag)
                self._count("tag_reads")

    # -- the pose stream's floor rate, and the monitor ------------------------------------------------
    def _output_loop(self, beat: Heartbeat) -> None:
        output = self.output
        assert output is not None
        period_ns = int(1e9 / self.config.output.rate_hz)
        while not self._stop.is_set():
            beat.beat()
            # Asleep until the floor rate calls for a pose (the camera's poses keep moving that time on):
            # a thread that wakes takes the interpreter lock, from the hot path if a frame is on it.
            due_ns = output.last_publish_ns + period_ns - self.clock_ns()
            self._stop.wait(min(max(due_ns, period_ns // 8), period_ns) * 1e-9)
            if self._stop.is_set():
                return
            if self.clock_ns() - output.last_publish_ns >= period_ns:
                self._publish(trigger_ns=None)

    def _monitor_loop(self) -> None:
        grace_s = self.config.health.ready_grace_s
        warn = _NotLocalizingWarning(self.config.health.not_localizing_log_s)
        while not self._stop.wait(0.25):
            if not self.health.is_ready:
                critical = [w for name, w in self._watch.items() if self._critical(name)]
                if all(w.opened_once for w in critical):
                    self._ready(self.missing(opened_once=True), None)
                elif self.clock_ns() - self._started_ns > grace_s * 1e9:
                    self._ready(self.missing(opened_once=True), grace_s)
            else:
                now = self.clock_ns()
                why = None if self.flags(now) & _POSITION_FLAGS else self.not_localizing_reason()
                warn.update(why, now * 1e-9)
            self.health.tick()
            self.collector.check()

    def _ready(self, missing: list[str], after_s: float | None) -> None:
        if missing:
            when = "" if after_s is None else f" after {after_s:.0f} s"
            log.warning("ready without %s%s (each is retried; see the status line)", ", ".join(missing), when)
        self.health.ready()

    def missing(self, *, opened_once: bool = False) -> list[str]:
        """What is not there: each device whose loop cannot use it now (``opened_once``: that has never been
        opened), then the pose output port when it is not open."""
        out = [name for name, w in self._watch.items() if not (w.opened_once if opened_once else w.ok)]
        if self.output is not None and not self.output.is_open:
            out.append(f"output {self.output.url}")
        return out

    def not_localizing_reason(self) -> str:
        """Why no position source is live: what is missing, else that the sources there give nothing."""
        missing = self.missing()
        sources = [
            name
            for name, present in (
                ("VLP", self.localizer is not None and self.devices.camera is not None),
                ("SLAM", self.mapper is not None and self.devices.laser is not None),
                ("odometry", self.devices.servos is not None),
            )
            if present
        ]
        text = f"no position source ({', '.join(sources) or 'none configured'} silent)"
        return f"{text}; missing: {', '.join(missing)}" if missing else text


class _NotLocalizingWarning:
    """The journal's side of "not localizing": a warning once it has lasted ``_NOT_LOCALIZING_GRACE_S``,
    repeated every ``every_s`` (or when the reason changes) while it lasts, and a line when it ends."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.since_s: float | None = None
        self.next_s = 0.0
        self.last_reason = ""
        self.warned = False

    def update(self, reason: str | None, now_s: float) -> None:
        """``reason``: why the agent is not localizing now, None while it is."""
        if reason is None:
            if self.warned:
                log.warning("localizing again after %.0f s", now_s - (self.since_s or now_s))
            self.since_s, self.warned, self.last_reason = None, False, ""
            return
        if self.since_s is None:
            self.since_s, self.next_s = now_s, now_s + _NOT_LOCALIZING_GRACE_S
        if now_s >= self.next_s or (self.warned and reason != self.last_reason):
            log.warning("not localizing for %.0f s: %s", now_s - self.since_s, reason)
            self.next_s, self.last_reason, self.warned = now_s + self.every_s, reason, True


def _kind(name: str) -> Any:
    from drivers.registry import DeviceKind

    return DeviceKind(name)


def laser_mount_for(config: AgentConfig, world: Any | None) -> MountConfig:
    """Where the laser sits: the config's, else the simulated world's, else on the base's centre."""
    if config.slam.laser_mount is not None:
        return config.slam.laser_mount
    if world is not None:
        m = world.robot.laser_mount
        return MountConfig(m.x_m, m.y_m, m.z_m, m.yaw_rad, m.roll_rad, m.pitch_rad)
    return MountConfig()
