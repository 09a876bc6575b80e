"""The agent process's runtime: it builds the state the loops share, composes the loops, and answers for
the whole (pose, status word, status, stop).

Loops (one module each; each thread beats its own heartbeat; the critical ones gate the systemd watchdog)::

    camera    camera_loop    grab -> LatestMailbox -----------------------------+
    vlp       vlp_loop       (hot path) the newest frame -> VLP fix -> fuse -> pose bytes written
    laser     laser_loop     read scan -> BoundedQueue -------------------------+
    slam      slam_loop      scan + odometry at its time -> RBPF -> fuse the pose of each filter update
    servos    servo_loop     read wheels -> odometry -> fuse; send the velocity command (dead-man)
    imu       imu_loop       read -> gyro yaw rate -> fuse; accelerometer -> tilt for VLP
    forward_camera  forward_camera_loop  grab the forward camera's colour frames (person following), newest
                    kept in memory
    rfid      rfid_loop      read tags (kept for the status; person following and landmarks come later)
    output    output_loop    keeps the pose stream at rate_hz when nothing else writes
    commands  command_loop   the controller's commands on the pose port -> CommandArbiter -> statuses back;
              drive_loop     then what the arbiter says drives the base -> the velocity command
              follow_control a follow frame -> the arbiter -> the follow loop on/off; its state -> statuses
    monitor   monitor_loop   heartbeats -> READY / WATCHDOG / STATUS / STOPPING

A device that fails is reported (pose flags, status, log) and its loop keeps trying: the drivers that
reconnect by themselves (laser, servos, RFID) are left to it, the others are closed and reopened. The
rest carry on. Nothing here prints, installs signal handlers or configures logging: the commands do.
"""

from __future__ import annotations

import gc
import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import TYPE_CHECKING, Any

import numpy as np

from agent.config import AgentConfig, MountConfig
from agent.following.coarse import Antenna, CoarseFilter, RadioModel, default_table
from agent.fusion import Estimate, FilterNoise, IntegrityPolicy, PoseFilter, Source
from agent.recording.messages import FusedSample, SlamStartSample, fusion_record_time
from agent.recording.writer import McapRecorder
from agent.runtime.arbiter import CommandArbiter
from agent.runtime.camera_loop import camera_loop
from agent.runtime.collector import IdleCollector
from agent.runtime.command_loop import CommandLoop
from agent.runtime.devices import Devices
from agent.runtime.drive_loop import DirectiveDrive, Navigator
from agent.runtime.fleet_loop import FleetLoop
from agent.runtime.forward_camera_loop import FORWARD_CAMERA, forward_camera_loop
from agent.runtime.health import HealthMonitor, Heartbeat, NotifierLike
from agent.runtime.hotpath import HotPath
from agent.runtime.imu_loop import imu_loop
from agent.runtime.laser_loop import laser_loop
from agent.runtime.localizer import FrameLocalizer
from agent.runtime.loop_state import DeviceState, LoopState
from agent.runtime.mailbox import BoundedQueue, LatestMailbox, MailboxClosed
from agent.runtime.map_saver import MapSaver
from agent.runtime.mapper import ScanMapper
from agent.runtime.mission_loop import MissionLoop, NamedPlace
from agent.runtime.monitor_loop import MonitorLoop
from agent.runtime.motion import DriveCommand, OdometryTrack, StillDetector, TiltEstimator
from agent.runtime.navigation_loop import NavigationLoop
from agent.runtime.output import PoseOutput
from agent.runtime.output_loop import output_loop
from agent.runtime.priority import CpuLatencyRequest
from agent.runtime.recorder import Recorder
from agent.runtime.rfid_loop import CoarseLayer, rfid_loop
from agent.runtime.servo_loop import servo_loop
from agent.runtime.slam_loop import SlamLoop
from agent.runtime.types import AbsoluteFix
from agent.runtime.vlp_loop import VlpLoop
from drivers.errors import DeviceError
from drivers.samples import Frame, Scan, TagRead
from firmware_protocol.command_frame import GoalCommand, GoalReason, GoalStatus
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["Agent", "AgentStatus", "DeviceState"]

if TYPE_CHECKING:
    from agent.runtime.follow_control import FollowControl
    from agent.runtime.follow_loop import FollowLoop

log = logging.getLogger(__name__)

_SOURCE_FLAGS = {
    Source.VLP: PoseFlags.VLP,
    Source.SLAM: PoseFlags.SLAM,
    Source.ODOMETRY: PoseFlags.ODOMETRY,
    Source.IMU: PoseFlags.IMU,
}
_POSITION_FLAGS = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY
_FAULT_FLAGS = PoseFlags.LASER_LOST | PoseFlags.CAMERA_STALLED | PoseFlags.SERVO_FAULT
# SLAM starts its map only once the fused pose is known this well (the map frame is the fused frame).
_SLAM_START_SIGMA_M = 0.25
# Goal statuses kept for the status snapshot.
_LAST_STATUSES = 16


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
    # The controller's commands (``agent.runtime.command_loop``, the arbiter's answers by state and reason,
    # the driving step's passes by source) and the last goal statuses sent back, oldest first.
    commands: dict[str, int] = field(default_factory=dict)
    command_statuses: tuple[GoalStatus, ...] = ()
    # Person following's coarse layer (``[following] tag_id``): bearing, spread, range, confidence, ...
    following: dict[str, float | int] | None = None


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
        unavailable: what is not there and why (for the status).
        recorder: records the fusion's inputs and outputs as JSON lines (None: nothing recorded).
        flight_recorder: the MCAP flight recorder (``agent.recording``) every loop hands its samples to.
        clock_ns: the agent's clock.

    With a pose output, the controller's commands on its line go through a :class:`CommandArbiter`
    (``commands`` loop) and what it says drives the base (``agent.runtime.drive_loop``).
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
        flight_recorder: McapRecorder | None = None,
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
        self.flight_recorder = flight_recorder
        # The map saved as the robot goes (``create_agent`` sets it when there is a map folder).
        self.map_saver: MapSaver | None = None
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
            observer=_fusion_observer(recorder, flight_recorder),
            integrity=IntegrityPolicy(
                config.vlp.alert_limit_m, config.vlp.guarded_sigma_scale, config.vlp.fuse_degraded
            ),
        )
        self.timeouts_ns = {
            Source.VLP: int(fc.vlp_timeout_s * 1e9),
            Source.SLAM: int(fc.slam_timeout_s * 1e9),
            Source.ODOMETRY: int(fc.odometry_timeout_s * 1e9),
            Source.IMU: int(fc.imu_timeout_s * 1e9),
        }
        self.frames: LatestMailbox[tuple[Frame, int]] = LatestMailbox()
        # Person following's RFID layer, made by start() when [following] names a tag.
        self.coarse: CoarseLayer | None = None
        # The forward camera's newest frame, for person following (never leaves the process).
        self.forward_frames: LatestMailbox[Frame] = LatestMailbox()
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
        self.state = LoopState(config, devices, clock_ns)
        self._threads: list[threading.Thread] = []
        self.still = StillDetector()
        self._started_ns = 0
        self._stopped = False
        self._cpu_latency: CpuLatencyRequest | None = None
        # The navigation (``enable_navigation``): called with the controller's or a mission's goal while it
        # is in force. None: nothing navigates, and the controller's goals are answered NOT_LOCALIZED.
        self.navigator: Navigator | None = None
        self.navigation: NavigationLoop | None = None
        # Local missions, exploring and going to places (``enable_missions``); None: none.
        self.missions: MissionLoop | None = None
        # Called with every scan in the laser loop after the navigation (person following); before start().
        self.scan_listeners: list[Callable[[Scan], None]] = []
        self.arbiter: CommandArbiter | None = None
        # Following on command (``enable_following``); None: the controller cannot start following.
        self.follow_control: FollowControl | None = None
        self.fleet: FleetLoop | None = None  # the bridge's Unix socket ([fleet] socket)
        self.commands: CommandLoop | None = None
        self.drive_step: DirectiveDrive | None = None
        if output is not None:
            self.arbiter = CommandArbiter(cc.max_speed_mps, cc.max_turn_radps, check_goal=self._check_goal)
            oc = config.output
            self.commands = CommandLoop(
                output,
                self.arbiter,
                oc.format,
                mavlink_ids=(oc.mavlink_sysid, oc.mavlink_compid),
                clock_s=lambda: clock_ns() * 1e-9,
            )
            self.drive_step = DirectiveDrive(
                self.arbiter,
                self.drive,
                self.commands.answer,
                clock_ns,
                lambda: self.navigator,
                lambda: self.navigation.guard if self.navigation is not None else None,
            )

    # -- public -------------------------------------------------------------------------------------
    def start(self) -> None:
        """Start every loop. Devices are opened by their loops; the output is opened now if it can be."""
        # Collect and freeze the heap before any loop runs, when a long pass stalls nobody: settle_heap's
        # pass once started then has only what starting made to look at. Its full pass over everything
        # held the interpreter lock for up to a second on a loaded machine, the device loops (and the
        # simulator's fakes) stalled behind it, and a laser open timed out.
        gc.collect()
        gc.freeze()
        self._started_ns = self.clock_ns()
        self._hold_cpu_latency()
        if self.recorder is not None:
            self.recorder.start(self.fusion.parameters)
        if self.flight_recorder is not None:
            # First in the recording: how the filter was set up, so that its inputs can be replayed.
            setup = self.fusion.parameters
            self.flight_recorder.record("fusion_setup", setup["t0_ns"], setup)
            self.flight_recorder.give_way = self.hot_path.give_way
            self.flight_recorder.start()
            self.state.set_recorder(self.flight_recorder.record)
            if self.commands is not None:
                self.commands.record = self.flight_recorder.record
        if self.output is not None:
            try:
                self.output.open()
            except DeviceError as exc:
                log.warning("%s (retrying as poses come)", exc)
        d, s = self.devices, self.state
        timeout = self.config.health.loop_timeout_s
        hot, fusion = self.hot_path, self.fusion
        if d.camera is not None:
            vlp = VlpLoop(
                s,
                localizer=self.localizer,
                fusion=fusion,
                frames=self.frames,
                hot_path=hot,
                collector=self.collector,
                tilt=self.tilt if d.imu is not None else None,
                slam_fixes=self.slam_fixes if self.mapper is not None else None,
                publish=self._publish,
            )
            camera = partial(camera_loop, s, camera=d.camera, hot_path=hot, frames=self.frames)
            self._spawn("camera", self.critical("camera"), timeout, camera)
            self._spawn("vlp", self.critical("camera"), timeout, vlp.run)
        if d.laser is not None:
            slam = SlamLoop(
                s,
                mapper=self.mapper,
                fusion=fusion,
                scans=self.scans,
                slam_fixes=self.slam_fixes,
                hot_path=hot,
                odometry_track=self.odometry_track if d.servos is not None else None,
                on_map=self._on_map if self.navigation is not None or self.config.fleet.socket else None,
                saver=self.map_saver,
            )
            scans = self.scans if self.mapper is not None else None
            on_scan = self._on_scan if self.navigation is not None or self.scan_listeners else None
            laser = partial(laser_loop, s, laser=d.laser, scans=scans, on_scan=on_scan)
            self._spawn("laser", self.critical("laser"), timeout, laser)
            self._spawn("slam", self.critical("laser"), max(timeout, 5.0), slam.run)
        if d.servos is not None:
            servo = partial(
                servo_loop,
                s,
                servos=d.servos,
                hot_path=hot,
                fusion=fusion,
                drive=self.drive,
                still=self.still,
                odometry_track=self.odometry_track,
            )
            self._spawn("servos", self.critical("servos"), timeout, servo)
        if d.imu is not None:
            still, tilt = self.still, self.tilt
            imu = partial(imu_loop, s, imu=d.imu, hot_path=hot, fusion=fusion, still=still, tilt=tilt)
            self._spawn("imu", self.critical("imu"), timeout, imu)
        if d.forward_camera is not None:
            forward = partial(
                forward_camera_loop,
                s,
                camera=d.forward_camera,
                hot_path=hot,
                frames=self.forward_frames,
                stall_s=self.config.health.camera_stall_s,
            )
            self._spawn(FORWARD_CAMERA, self.critical(FORWARD_CAMERA), timeout, forward)
        if d.rfid is not None:
            self.coarse = self._coarse_layer(d.rfid)
            rfid = partial(rfid_loop, s, rfid=d.rfid, coarse=self.coarse)
            self._spawn("rfid", self.critical("rfid"), timeout, rfid)
        if self.output is not None:
            output = partial(output_loop, s, output=self.output, publish=self._publish)
            self._spawn("output", True, timeout, output)
        if self.config.fleet.socket is not None:  # not critical: the robot works alone without its bridge
            self.fleet = FleetLoop.for_agent(self)
            self._spawn("fleet", False, timeout, partial(self.fleet.run, stop=s.stop))
        if self.missions is not None:
            # Not critical: without it the robot stands still, and the dead-man covers the wheels.
            self._spawn("missions", False, max(timeout, 5.0), partial(self.missions.run, stop=s.stop))
        if self.commands is not None and self.drive_step is not None:
            # Not critical: a controller that sends nothing is no fault, and the dead-man covers this loop.
            commands = partial(self.commands.run, stop=s.stop, then=self.drive_step.step)
            self._spawn("commands", False, timeout, commands)
        monitor_loop = MonitorLoop(
            s, agent=self, health=self.health, collector=self.collector, started_ns=self._started_ns
        )
        monitor = threading.Thread(target=monitor_loop.run, name="agent-monitor", daemon=True)
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

    def stop(self, timeout_s: float = 1.5, why: str = "") -> None:
        """Stop the loops, command zero, close the devices and the output. Safe to call twice. ``why``: for
        the log (e.g. ``SIGTERM``)."""
        if self._stopped:
            return
        self._stopped = True
        log.info("stopping%s: wheels to zero, closing devices", f" ({why})" if why else "")
        self.health.stopping("stopping: wheels to zero, closing devices")
        self.state.stop.set()
        if self.mapper is not None:
            # A SLAM process leaves the update it is in now (and the SLAM thread its wait for it), so that
            # the thread joins within the deadline below and the final map is taken out of it promptly.
            self.mapper.begin_stop()
        self.hot_path.close()
        self.frames.close()
        self.forward_frames.close()
        self.scans.close()
        self.slam_fixes.close()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(max(0.0, deadline - time.monotonic()))
            if thread.is_alive():
                log.warning("thread %s did not stop in time", thread.name)
        self.collector.stop()
        if self.map_saver is not None:
            # Before the caller's final save: one writer per map folder at a time.
            self.map_saver.close()
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
        if self.flight_recorder is not None:
            self.flight_recorder.close()
        if self._cpu_latency is not None:
            self._cpu_latency.release()

    def request_map_save(self) -> None:
        """Save the map at the SLAM thread's next turn (SIGUSR1 under ``vlp-agent run``); nothing without a
        map saver. Safe from a signal handler: it sets a flag and takes no lock."""
        if self.map_saver is not None:
            self.map_saver.request()

    @property
    def stopping(self) -> bool:
        return self.state.stop.is_set()

    def command_velocity(self, v_mps: float, omega_radps: float) -> None:
        """A velocity command for the base; it must be repeated within the dead-man timeout. Ignored (and
        counted) while the controller's velocity or stop is in force: it takes precedence."""
        if self.drive_step is not None and self.drive_step.controller_drives:
            self.state.count("velocity_commands_overridden")
            return
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
            now - self.state.last_scan_ns > hc.laser_lost_s * 1e9 or not self.state.watch["laser"].ok
        ):
            flags |= PoseFlags.LASER_LOST
        if d.camera is not None and now - self.state.last_frame_ns > hc.camera_stall_s * 1e9:
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
        watch = self.state.watch["servos"]
        if not watch.ok or any(self.state.hardware_error):
            return True
        since = self.state.servo_read_since_ns
        if since and now_ns - since > self.config.health.servo_fault_s * 1e9:
            return True
        beat = self.health.heartbeat("servos")
        return beat is not None and not beat.alive()

    def status(self) -> AgentStatus:
        now = self.clock_ns()
        with self.state.counts_lock:
            counts = dict(self.state.counts)
            no_fix = dict(self.state.no_fix.most_common(8))
        # How often background loops waited for the hot path, and waits cut at the bound (a hot path
        # stuck for longer than max_wait_s).
        counts["hot_path_waits"] = self.hot_path.waits
        counts["hot_path_wait_timeouts"] = self.hot_path.timeouts
        if self.map_saver is not None:
            counts.update(self.map_saver.counters())
        if self.fleet is not None:
            counts.update(self.fleet.counters())
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
        vlp_ms = self.state.vlp_ms.percentiles(50, 99)
        cpu_ms = self.state.hot_cpu_ms.percentiles(50, 99)
        return AgentStatus(
            now,
            self.fusion.estimate(),
            self.flags(now),
            {name: w.state() for name, w in self.state.watch.items()},
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
            *self._command_status(),
            self._following_status(),
        )

    def _following_status(self) -> dict[str, float | int] | None:
        if self.coarse is not None and not self.coarse.tag_id:  # on command, no tag followed yet
            return None
        latest = self.coarse.latest if self.coarse is not None else None
        return latest.as_dict() if latest is not None else None

    def _command_status(self) -> tuple[dict[str, int], tuple[GoalStatus, ...]]:
        if self.commands is None or self.arbiter is None or self.drive_step is None:
            return {}, ()
        counts = dict(self.commands.counts)
        counts.update({f"arbiter_{key}": n for key, n in dict(self.arbiter.counts).items()})
        counts.update(self.drive_step.counts)
        if self.navigation is not None:
            counts.update({f"navigation_{key}": n for key, n in self.navigation.counts.items()})
        return counts, tuple(list(self.commands.statuses)[-_LAST_STATUSES:])

    def status_line(self) -> str:
        """One line for STATUS= and logs; it starts with ``NOT LOCALIZING`` and why while no position source
        is live (the pose is a stale hold)."""
        est = self.fusion.estimate()
        flags = self.flags()
        names = [f.name for f in PoseFlags if f & flags and f.name] or ["no source"]
        if self.localizer is not None and self.fusion.integrity_alert(Source.VLP):
            # The newest VLP fix was refused for integrity: VLP is off the pose until one is fused again.
            names.append("VLP-INTEGRITY-ALERT")
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
        return list(self.state.tags)

    def _coarse_layer(self, reader: Any) -> CoarseLayer | None:
        """Person following's RFID layer when ``[following] tag_id`` names the tag: the calibrated table,
        or the physical model of ``antenna_yaws_rad`` on the reader's antenna ports."""
        fc = self.config.following
        if fc.tag_id is None and (self.follow_control is None or self.follow_control.loop is None):
            return None
        table = fc.table
        if table is None:
            ports = tuple(getattr(reader, "antenna_ports", (1,)))
            if len(ports) != len(fc.antenna_yaws_rad):
                # Only a config that names the user's tag asked for following by RFID: without one the layer
                # is made for a follow command that may never come, on the default yaws.
                log.log(
                    logging.WARNING if fc.tag_id is not None else logging.DEBUG,
                    "[following] antenna_yaws_rad gives %d yaws for the reader's %d antenna ports %s; "
                    "using the first %d",
                    len(fc.antenna_yaws_rad),
                    len(ports),
                    ports,
                    min(len(ports), len(fc.antenna_yaws_rad)),
                )
            antennas = tuple(Antenna(p, y) for p, y in zip(ports, fc.antenna_yaws_rad, strict=False))
            table = default_table(RadioModel(antennas))
        fusion = self.fusion

        def pose() -> tuple[float, float, float]:
            e = fusion.estimate()
            return e.x_m, e.y_m, e.yaw_rad

        # Without [following] tag_id (following on command) the layer hears no tag until a follow names one.
        return CoarseLayer(CoarseFilter(table), fc.tag_id or "", fc.cycle_s, pose)

    # -- helpers -----------------------------------------------------------------------------------
    def critical(self, name: str) -> bool:
        """Whether the watchdog waits for this device's loops (the config says; an injected device the
        config does not list: the default for its kind)."""
        if name == FORWARD_CAMERA:
            forward = self.config.forward_camera
            return forward is not None and forward.critical
        device = self.config.devices.get(_kind(name))
        return device.critical if device is not None else name in ("camera", "laser", "servos")

    def enable_navigation(self, laser_mount: MountConfig) -> bool:
        """Drive goals with ``agent.navigation`` on the live SLAM map (needs SLAM, a laser, wheels and a
        command line); False, saying why in the log, where one is missing. Before :meth:`start`."""
        missing = [
            name
            for name, present in (
                ("SLAM", self.mapper is not None),
                ("a laser", self.devices.laser is not None),
                ("wheels", self.devices.servos is not None),
                ("a command line (the pose output)", self.arbiter is not None and self.commands is not None),
            )
            if not present
        ]
        if missing:
            log.warning("navigation off: it needs %s", ", ".join(missing))
            return False
        assert self.arbiter is not None and self.commands is not None
        mount = (laser_mount.x_m, laser_mount.y_m, laser_mount.yaw_rad)
        self.navigation = NavigationLoop(
            self.config.navigation,
            mount,
            self.drive,
            self.arbiter,
            self.commands.answer,
            self._navigation_pose,
            self.clock_ns,
        )
        self.navigator = self.navigation
        return True

    def enable_following(self, loop: FollowLoop | None, unavailable: str = "") -> FollowControl | None:
        """Following on command (``agent.runtime.follow_control``): the controller's follow frames turn
        ``loop`` (``follow_setup.make_follow_loop``) on and off through the arbiter, and its state goes
        back as goal statuses. ``loop`` None: following is not set up (``unavailable`` says why) and follow
        commands are refused FOLLOW_UNAVAILABLE. Needs the command line (the pose output); None, saying why
        in the log, without it. Before :meth:`start` (with a reader, the RFID layer is then made even
        without ``[following] tag_id``, for a follow that names its tag)."""
        if self.arbiter is None or self.commands is None:
            log.warning("following on command off: it needs a command line (the pose output)")
            return None
        from agent.runtime.follow_control import FollowControl

        self.follow_control = FollowControl(
            self.arbiter,
            self.commands.answer,
            loop,
            lambda: self.clock_ns() * 1e-9,
            coarse=lambda: self.coarse,
            configured_tag=self.config.following.tag_id,
            unavailable=unavailable,
        )
        return self.follow_control

    def enable_missions(self, places: Mapping[str, NamedPlace] | None = None) -> bool:
        """Run local missions (``mission_loop``): exploring with the configured explorer
        (``[exploration]``) and going to the named ``places``, as commands on the serial link (explore,
        go to place) or from the caller (``missions.take``). The SLAM map and the fused pose in, mission
        goals to the navigation out. Needs the navigation (:meth:`enable_navigation`); False, saying why
        in the log, without it. Before :meth:`start`."""
        if self.navigation is None or self.arbiter is None or self.commands is None:
            log.warning("missions off: they need the navigation")
            return False
        if self.missions is not None:  # on already (create_agent): the caller's places join them
            for name, place in (places or {}).items():
                self.missions.places[name] = place
            return True
        from agent.exploration import make_explorer

        explorer = make_explorer(self.config.exploration, self.config.navigation)
        # A target whose way the scans show shut (a door closed) is pruned at once, not retried.
        explorer.evidence = self.navigation.obstacle_points
        named = dict(places or {})
        for p in self.config.exploration.places:  # [[exploration.places]]
            named.setdefault(p.name, NamedPlace(p.name, p.x_m, p.y_m, p.yaw_rad))
        commands = self.commands
        self.missions = MissionLoop(
            explorer,
            self.config.navigation,
            self.arbiter,
            lambda status: commands.answer(status, None),
            self._navigation_pose,
            self.clock_ns,
            places=named,
        )
        commands.listeners.append(self.missions.on_status)
        commands.missions = self.missions.take
        self._load_topology()
        if self.map_saver is not None:  # the topological map written beside every map saved
            self.map_saver.topology = self.missions.topology
        return True

    def _load_topology(self) -> None:
        """The topological map beside the map the robot starts on (``slam.map``), if there is one: its
        named places and rooms become places missions can go to."""
        from agent.slam import mapio
        from drivers.errors import ConfigError

        if self.missions is None or self.config.slam.map is None:
            return
        path = mapio.topology_path(self.config.slam.map)
        if not path.exists():
            return
        try:
            taken = self.missions.load_topology(mapio.load_topology(path))
        except (ConfigError, ValueError) as exc:
            log.error("topological map %s not loaded: %s", path, exc)
            return
        log.info("topological map %s: places %s", path, ", ".join(taken) or "none new")

    def _on_map(self, image: Any) -> None:
        """The SLAM loop's map every ``map_period_s``: the navigation's static layer and the missions'
        map, the fleet's map snapshots."""
        if self.navigation is not None:
            self.navigation.on_map(image)
        if self.fleet is not None:
            self.fleet.on_map(image)
        if self.missions is not None:
            self.missions.on_map(image)

    def _on_scan(self, scan: Scan) -> None:
        if self.navigation is not None:
            self.navigation.on_scan(scan)
        for listener in self.scan_listeners:
            listener(scan)

    def _navigation_pose(self) -> tuple[float, float, float] | None:
        """The fused pose while a position source is live (a stale hold is not driven on)."""
        estimate, flags = self.pose()
        if not flags & (PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY):
            return None
        return (estimate.x_m, estimate.y_m, estimate.yaw_rad)

    def _check_goal(self, goal: GoalCommand) -> GoalReason | None:
        """The navigation's verdict on a goal; without navigation no goal can be driven to (an ACCEPTED goal
        would never move)."""
        if self.navigation is not None:
            return self.navigation.check_goal(goal)
        if self.navigator is None:
            self.state.count("goals_without_navigator")
            return GoalReason.NOT_LOCALIZED
        return None  # a navigator of someone else's (a test, a mission) judges its goals itself

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
        if self.mapper is None or not self.state.slam_good:
            return False
        s = self.state
        return now_ns - s.last_scan_ns <= self.timeouts_ns[Source.SLAM] and s.watch["laser"].ok

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

    def _publish(self, trigger_ns: int | None, arrival_ns: int | None = None) -> None:
        if self.output is None:
            return
        estimate, flags = self.fusion.estimate(), self.flags()
        written = self.output.publish(estimate, flags, trigger_ns, arrival_ns)
        if written is not None and self.recorder is not None:
            self.recorder.record_output(estimate, int(flags))
        if written is not None and self.state.recording:
            self.state.record("pose", estimate.t_ns, FusedSample(estimate, int(flags)))

    def _hold_cpu_latency(self) -> None:
        """Ask the kernel to keep idle cores out of deep sleep while the agent runs, when configured: a
        frame that has to wake a sleeping core starts cold (``agent.runtime.priority.CpuLatencyRequest``)."""
        latency_us = self.config.scheduling.cpu_latency_us
        if latency_us < 0 or self.devices.camera is None:
            return
        request = CpuLatencyRequest(latency_us)
        refused = request.acquire()
        with self.state.counts_lock:
            self.state.counts["cpu_latency_held"] = int(refused is None)
        if refused is None:
            self._cpu_latency = request
            log.info("CPU wake-up latency limited to %d us while running (PM QoS)", latency_us)
        else:
            log.warning("CPU wake-up latency not limited: %s", refused)

    def slam_start_pose(self, t_ns: int) -> tuple[float, float, float] | None:
        """Where SLAM starts its map: the fused pose at ``t_ns`` once it is known well enough, else None."""
        est = self.fusion.estimate_at(t_ns)
        pose = None if est.sigma_xy_m > _SLAM_START_SIGMA_M else (est.x_m, est.y_m, est.yaw_rad)
        # The mapper asks from the SLAM thread, between the scans it records: a replay answers the same.
        self.state.record("slam_start", t_ns, SlamStartSample(t_ns, pose))
        return pose

    def missing(self, *, opened_once: bool = False) -> list[str]:
        """What is not there: each device whose loop cannot use it now (``opened_once``: that has never been
        opened), then the pose output port when it is not open."""
        out = [name for name, w in self.state.watch.items() if not (w.opened_once if opened_once else w.ok)]
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


def _fusion_observer(
    recorder: Recorder | None, flight_recorder: McapRecorder | None
) -> Callable[[dict[str, Any]], None] | None:
    """What the fusion tells each of its inputs to (under its lock): the JSON-lines recorder, the flight
    recorder, both or neither."""
    if flight_recorder is None:
        return recorder.record_input if recorder is not None else None
    record = flight_recorder.record

    def observe(r: dict[str, Any]) -> None:
        if recorder is not None:
            recorder.record_input(r)
        record("fusion_input", fusion_record_time(r), r)

    return observe


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
