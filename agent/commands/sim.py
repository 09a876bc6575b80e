"""``vlp-agent sim``: the whole agent on the simulated robot, through the real drivers and the real bytes.

Every fake device is served where hardware would be (``drivers.sim.harness.SimulatedRobot``), the agent is
the same runtime ``vlp-agent run`` starts (config ``examples/sim.toml`` unless ``--config``), and the pose
stream goes out on a pseudo-terminal that a simulated controller reads and decodes. The world's route is
driven by a pure-pursuit autopilot that steers from the agent's *own* fused pose (never the truth), through
the agent's velocity command, its dead-man and the Dynamixel servos; the simulated robot moves only from
what the fake servos receive.

While it runs a status line shows the pose, its error against the simulation's truth, the frame and fix
rates and the latency from a frame's capture to the last byte of its pose on the line. At the end: a
summary (``--json``: one JSON object), a trajectory plot and, when SLAM built one, the map.

``--fault KIND@START[+DURATION]`` injects a fault at START seconds for DURATION seconds from when it was
applied (for good without; the summary's ``faults`` says when each was applied, ``done_s`` when that had
returned):
``laser`` (the URG's USB cable pulled), ``camera`` (frames stop), ``servo`` (the left wheel servo stops
answering), ``forward_camera`` (person following's forward camera stops; needs ``[camera.forward]``).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import logging
import math
import os
import resource
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from agent import figure
from agent.commands.args import UsageError, dumps_json, positive_seconds
from agent.config import AgentConfig, OutputFormat, SimConfig, SlamMode, load_config
from agent.recording.messages import TruthSample
from agent.recording.writer import McapRecorder
from agent.runtime import Agent, ScanMapper, create_agent
from agent.runtime.follow_loop import FollowLoop
from agent.runtime.mapper import save_final_map, tidy_map_folder
from agent.runtime.mission_loop import MissionLoop, NamedPlace
from agent.runtime.priority import SWITCH_INTERVAL_S, realtime_thread
from agent.runtime.shutdown import AgentRequests, ShutdownRequest
from agent.shipped import DEFAULT_SIM_CONFIG
from agent.sim_score import Scorer
from agent.slam.render import MapPath
from drivers.errors import ConfigError
from drivers.sim.controller import SimulatedController
from drivers.sim.harness import SimulatedRobot
from drivers.sim.route import RouteFollower
from drivers.sim.simulation import Simulation
from firmware_protocol.pose_frame import PoseFlags

log = logging.getLogger(__name__)

DEFAULT_CONFIG = DEFAULT_SIM_CONFIG
FAULT_KINDS = ("laser", "camera", "servo", "forward_camera", "person")
_AUTOPILOT_PERIOD_S = 0.05
LATENCY_DEFINITION = (
    "latency: a camera frame captured by the computer (handed over complete by the camera driver) -> the "
    "last byte of its pose written; exposure_age: the frame's mid-exposure time (the capture timestamp in "
    "the pose frame) -> that last byte, i.e. the latency plus the rolling shutter's readout and the transfer"
)


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "sim",
        help="run the whole agent on the simulated robot (no hardware needed)",
        description="Run the agent on a simulated world: fake laser, servos and RFID reader on "
        "pseudo-terminals, a fake IMU behind smbus2 and the simulated rolling-shutter camera, all opened "
        "through the real drivers; VLP, SLAM and fusion on them; the pose stream on a pseudo-terminal read "
        "by a simulated controller. The world's route is driven from the agent's own pose. Prints a live "
        "status line and a summary, and writes a trajectory plot (and the SLAM map).",
    )
    p.add_argument(
        "--world", metavar="FILE", help="world file (default: the config's, examples/worlds/office.toml)"
    )
    p.add_argument("--config", metavar="FILE", help=f"agent config with [sim] (default: {DEFAULT_CONFIG})")
    p.add_argument(
        "--seconds", type=positive_seconds, default=30.0, help="how long to run, > 0 (default: 30)"
    )
    p.add_argument("--json", action="store_true", help="print the summary as one JSON object on stdout")
    p.add_argument(
        "--seed", type=int, default=None, help="seed for the simulated sensors' noise (default: config)"
    )
    p.add_argument(
        "--out", metavar="DIR", default="vlp-sim-out", help="where the plots go (default: vlp-sim-out)"
    )
    p.add_argument(
        "--trajectory", metavar="PNG", help="the trajectory plot's path (default: DIR/trajectory.png)"
    )
    p.add_argument(
        "--output",
        metavar="URL",
        help="send the pose stream there (a device, a pty path, any pyserial URL) instead of the simulated "
        "controller's pty",
    )
    p.add_argument(
        "--output-format",
        choices=[f.value for f in OutputFormat],
        help="pose frames or MAVLink (default: config)",
    )
    p.add_argument(
        "--truth",
        metavar="CSV",
        help="also write the simulation's true pose at the time of every pose frame written "
        "(sequence,t_us,x_m,y_m,yaw_rad,written_us: when the frame's last byte was written, on the agent's "
        "clock), to score a decoded stream against",
    )
    p.add_argument(
        "--record",
        metavar="PATH",
        help="flight-record every sample (scans, wheels, IMU, tags, VLP fixes with their LEDs, poses, maps, "
        "commands, health) as MCAP files PATH-stem-0001.mcap, ... beside PATH, with the config's [recorder] "
        "rotation and caps (docs/recording.md); Foxglove opens them",
    )
    p.add_argument(
        "--snapshot",
        metavar="SECONDS",
        type=positive_seconds,
        default=None,
        help="with --record (or [recorder] path): keep the last SECONDS in memory and write them to "
        "PATH-stem-snapshot-0001.mcap, ... on SIGUSR2 and when a device goes bad ([recorder] snapshot_s)",
    )
    p.add_argument(
        "--snapshot-only",
        action="store_true",
        help="with --snapshot: write nothing but the snapshots ([recorder] continuous = false)",
    )
    p.add_argument(
        "--record-fusion",
        metavar="JSONL",
        help="record what the fusion takes and every pose written as JSON lines, for "
        "agent.runtime.recorder.replay",
    )
    p.add_argument(
        "--controller-record",
        metavar="FILE",
        help="the simulated controller writes every byte it receives from the agent there (pose frames and "
        "goal statuses), for another decoder to read",
    )
    p.add_argument(
        "--fault",
        action="append",
        type=_fault_argument,
        default=[],
        metavar="KIND@START[+DURATION]",
        help=f"inject a fault ({', '.join(FAULT_KINDS)}) at START s (within --seconds) for DURATION s from "
        "when it is applied (for good without); repeatable",
    )
    p.add_argument(
        "--robots",
        type=int,
        default=1,
        metavar="N",
        help="a fleet: N robots, each its own agent process and fleet bridge on loopback, started --spacing "
        "m apart along the world's start heading, robot i driven to the i-th --goal through the fleet; the "
        "summary has 'robots', 'collisions', 'fleet_pose_latency_ms_p95' (docs/fleet.md)",
    )
    p.add_argument(
        "--spacing", type=float, default=4.0, metavar="M", help="with --robots: metres between starts (4)"
    )
    p.add_argument(
        "--fleet-connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="with --robots: every robot's bridge also connects to ENDPOINT, where a fleet view or an audit "
        "listens (e.g. 'vlp-agent fleet list --listen tcp/127.0.0.1:7500'); repeatable",
    )
    p.add_argument(
        "--fleet-ros2",
        action="store_true",
        help="with --robots: every robot's bridge also publishes its pose, map and status as ROS 2 topics "
        "over rmw_zenoh ([ros2] enabled = true, namespace /rI; docs/fleet.md), audited with the rest",
    )
    p.add_argument(
        "--goal",
        action="append",
        type=_goal_argument,
        default=[],
        metavar="X,Y[,YAW]",
        help="drive to this goal (metres, map frame; YAW in degrees, any heading without) instead of the "
        "world's route: the simulated controller sends it as a goal command frame on the pose stream's "
        "line and the next when the agent reports it ended; repeatable, a sequence of goals. The run ends "
        "when the last goal has ended, or at --seconds",
    )
    p.add_argument(
        "--explore",
        action="store_true",
        help="explore the world from an empty map with the config's [exploration] explorer instead of "
        "driving the world's route: the simulated controller sends an explore command frame, the "
        "explorer's targets go to the navigation as mission goals; the run ends when the mission ends "
        "(complete or failed), or at --seconds. The summary's 'exploration' says how much of the "
        "reachable free area the SLAM map saw, and why it stopped",
    )
    p.add_argument(
        "--deliver",
        metavar="A,B",
        type=_deliver_argument,
        default=None,
        help="a delivery: explore first (as --explore), then go to the world's place A ([[places]], "
        "docs/world.md), then to B and back to A, as go-to-place missions the simulated controller sends; "
        "instead of the route. The run ends when they have ended (or one was refused: an unknown place, "
        "no pose, a robot inside an obstacle, a map with no free space), or at --seconds; the summary's "
        "'delivery' has each mission's answer and end and the true position's error at each end",
    )
    p.add_argument(
        "--follow",
        action="store_true",
        help="follow the tagged person ([following] tag_id) instead of driving the world's route: the laser "
        "person tracker seeded by the RFID layer, the follower keeping [following] distance_m behind them "
        "through the navigation's collision checks; the summary adds 'follow' (distance kept, time lost, "
        "identity switches, collisions, stop latency: docs/following.md)",
    )
    p.add_argument(
        "--follow-fine",
        choices=("on", "off"),
        default="on",
        help="with --follow and a forward camera ([camera.forward]): run the fine layer (pre-location in "
        "the laser track's band, mean shift) on its frames and feed its bearing to the person's track (on, "
        "the default), or follow on the laser and RFID only (off), to measure what the camera adds",
    )
    p.add_argument(
        "--send-follow",
        action="append",
        type=_follow_argument,
        default=[],
        metavar="start[:TAG]|stop[@SECONDS]",
        help="the simulated controller sends a follow command frame (docs/wire-format.md, 'Following'): "
        "start following (the user's tag, [following] tag_id, or the EPC TAG in hex) or stop the last "
        "following started, SECONDS (default 0) after the agent answered the one before (for the first, "
        "after the pose stream flows); repeatable, in order. Following is set up on command, as in "
        "`vlp-agent run`; the world's route is not driven. The run ends once the last one is answered "
        "and a second more has passed, or at --seconds. The summary's 'follow_commands' has every status of "
        "the follow ids, 'follow_control' the agent's side, 'follow' the loop's",
    )
    p.add_argument(
        "--follow-trace",
        metavar="FILE",
        help="with --follow: write every 50 ms sample of the score as CSV to FILE (time, the robot's true "
        "pose and speed, the user's position and distance, the nearest body's gap, the loop's state, the "
        "velocity sent, the track, the reason: docs/following.md), to see where a run left the band",
    )
    p.add_argument(
        "--goals-known-map",
        action="store_true",
        help="with --goal: goals may not cross unknown space (by default they may, since the map is being "
        "built as the robot drives)",
    )


# -- faults --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Fault:
    kind: str
    start_s: float
    duration_s: float | None

    @classmethod
    def parse(cls, text: str) -> Fault:
        kind, at, when = text.partition("@")
        if not at or kind not in FAULT_KINDS:
            raise ConfigError(
                "--fault", f"{text!r}: expected KIND@START[+DURATION], KIND one of {FAULT_KINDS}"
            )
        start, plus, duration = when.partition("+")
        try:
            start_s = float(start)
            duration_s = float(duration) if plus else None
        except ValueError as exc:
            raise ConfigError("--fault", f"{text!r}: START and DURATION are seconds") from exc
        # `not x >= 0` (rather than `x < 0`) so NaN, which compares false with everything, is refused too.
        finite = math.isfinite(start_s) and (duration_s is None or math.isfinite(duration_s))
        if not finite or not start_s >= 0 or (duration_s is not None and not duration_s > 0):
            raise ConfigError("--fault", f"{text!r}: START must be a finite >= 0 and DURATION a finite > 0")
        return cls(kind, start_s, duration_s)


def _fault_argument(text: str) -> Fault:
    try:
        return Fault.parse(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from exc


def check_faults_within(faults: Sequence[Fault], seconds: float) -> None:
    """A fault that starts after the run has ended would never happen: refuse it instead of ignoring it."""
    for fault in faults:
        if fault.start_s >= seconds:
            raise UsageError(
                f"argument --fault: {fault.kind}@{fault.start_s:g} starts after the run ends "
                f"(--seconds {seconds:g})"
            )


class FaultInjector:
    """Applies faults on schedule to the simulated robot (and the simulated camera). A fault with a
    duration ends that long after it was applied, not after it was due: a busy machine can apply it late,
    and the fault must still last as long as asked."""

    def __init__(self, faults: list[Fault], robot: SimulatedRobot, agent: Agent) -> None:
        self.robot = robot
        self.agent = agent
        self.pending: list[tuple[float, str, bool, float | None]] = sorted(
            (f.start_s, f.kind, True, f.duration_s) for f in faults
        )
        self.applied: list[dict[str, Any]] = []
        self.follow_loop: FollowLoop | None = None  # with --follow: the person fault hides the person

    def step(self, elapsed_s: float, t0_s: float | None = None) -> None:
        """Apply what is due at ``elapsed_s``. Each applied fault records ``t_s`` (``elapsed_s``: when this
        thread decided to apply it) and, given the start ``t0_s`` on the monotonic clock, ``done_s``: when
        applying it had returned (a busy machine can hold this thread between the two)."""
        while self.pending and self.pending[0][0] <= elapsed_s:
            _, kind, on, duration_s = self.pending.pop(0)
            self.set(kind, on)
            applied: dict[str, Any] = {"kind": kind, "on": on, "t_s": round(elapsed_s, 3)}
            done_s = elapsed_s if t0_s is None else time.monotonic() - t0_s
            if t0_s is not None:
                applied["done_s"] = round(done_s, 3)
            self.applied.append(applied)
            log.warning("fault %s %s at %.1f s", kind, "on" if on else "off", elapsed_s)
            if on and duration_s is not None:
                self.pending.append((done_s + duration_s, kind, False, None))
                self.pending.sort()

    def set(self, kind: str, on: bool) -> None:
        if kind == "laser":
            (self.robot.unplug if on else self.robot.replug)("laser")
        elif kind == "camera":
            camera = self.agent.devices.camera
            stall = getattr(camera, "stall", None)
            if stall is None:
                raise ConfigError("--fault", "the camera backend cannot be stalled (the simulated one can)")
            stall(on)
        elif kind == "servo":
            self.robot.servos.mute(self.robot.world.robot.left_id, on)
        elif kind == "forward_camera":
            stall = getattr(self.agent.devices.forward_camera, "stall", None)
            if stall is None:
                raise ConfigError("--fault", "forward_camera needs the simulated one ([camera.forward])")
            stall(on)
        elif kind == "person":
            follow = self.follow_loop
            if follow is None:
                raise ConfigError("--fault", "person needs --follow")
            follow.blind = on


def _deliver_argument(text: str) -> tuple[str, str]:
    """``A,B``: two place names."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) != 2 or not all(parts):
        raise argparse.ArgumentTypeError(f"{text!r}: expected A,B (two place names)")
    return parts[0], parts[1]


def _goal_argument(text: str) -> tuple[float, float, float | None]:
    """``X,Y`` or ``X,Y,YAW_DEG``: finite numbers."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected X,Y or X,Y,YAW (numbers)") from None
    if len(values) not in (2, 3) or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: expected X,Y or X,Y,YAW (finite numbers)")
    return values[0], values[1], math.radians(values[2]) if len(values) == 3 else None


def _follow_argument(text: str) -> tuple[str, str, str | None, float]:
    """``start``, ``start:TAG`` or ``stop``, with ``@SECONDS`` (>= 0) or not: a follow item for the simulated
    controller (``drivers.sim.controller``)."""
    what, _, at = text.partition("@")
    action, _, tag = what.partition(":")
    try:
        delay = float(at) if at else 0.0
    except ValueError:
        delay = math.nan
    bad_delay = not (math.isfinite(delay) and delay >= 0)
    if action not in ("start", "stop") or (action == "stop" and tag) or bad_delay:
        raise argparse.ArgumentTypeError(f"{text!r}: expected start[:TAG][@SECONDS] or stop[@SECONDS]")
    if tag:
        from firmware_protocol.command_frame import CommandFrameError, FollowCommand, encode_command

        try:
            encode_command(FollowCommand(0, 1, tag=tag))
        except CommandFrameError as exc:
            raise argparse.ArgumentTypeError(f"{text!r}: {exc.args[0]}") from None
    return "follow", action, tag.upper() or None, delay


# -- the simulated controller on the pose stream's pty --------------------------------------------------
def serve_pose_stream(
    stack: contextlib.ExitStack,
    config: AgentConfig,
    goals: Sequence[tuple[Any, ...]] = (),
    allow_unknown: bool = True,
    record: str | None = None,
) -> tuple[str | None, SimulatedController | None]:
    """With ``[output] url = "pty"``: a pseudo-terminal for the pose stream and a simulated controller
    reading it, in a process of its own (``drivers.sim.controller``; ended with ``stack``), sending
    ``goals`` as goal commands; the URL the agent writes to, and that controller (None otherwise)."""
    url = config.output.url
    if url != "pty":
        return url, None
    controller = SimulatedController(
        mavlink=config.output.format is OutputFormat.MAVLINK,
        goals=goals,
        allow_unknown=allow_unknown,
        record=record,
    )
    stack.callback(controller.stop)
    return controller.url, controller


def simulated_robot(sim: SimConfig) -> SimulatedRobot:
    """The simulated robot of ``[sim]``, its fakes' threads real-time at ``device_priority`` (0: not)."""
    priority = sim.device_priority
    realtime = functools.partial(realtime_thread, priority) if priority else None
    return SimulatedRobot(sim.world, seed=sim.seed, realtime=realtime)


def give_way_to_agent(agent: Agent, robot: SimulatedRobot | None) -> None:
    """The simulated hardware, threads of the agent's process here, waits while a frame is on the agent's
    hot path (see ``agent.runtime.hotpath``)."""
    if robot is not None:
        robot.give_way_to(agent.hot_path.give_way)


# -- the command -----------------------------------------------------------------------------------------
def _config(args: argparse.Namespace) -> AgentConfig:
    config = load_config(args.config or DEFAULT_CONFIG)
    if config.sim is None:
        raise ConfigError(
            "sim", "vlp-agent sim needs a config with a [sim] table (see examples/sim.toml)", config.file
        )
    sim = config.sim
    if args.world:
        from agent.commands.worlds import resolve_world
        from drivers.sim.worldfile import load_world

        path = resolve_world(args.world)
        sim = dataclasses.replace(sim, world_file=path, world=load_world(path))
    if args.seed is not None:
        sim = dataclasses.replace(sim, seed=args.seed)
    output = config.output
    if args.output_format:
        output = dataclasses.replace(output, format=OutputFormat(args.output_format))
    if args.output:
        output = dataclasses.replace(output, url=args.output)
    record = config.record
    if args.record_fusion:
        record = dataclasses.replace(record, path=Path(args.record_fusion))
    recorder = config.recorder
    if args.record:
        recorder = dataclasses.replace(recorder, path=Path(args.record))
    if args.snapshot is not None:
        recorder = dataclasses.replace(recorder, snapshot_s=args.snapshot)
    if args.snapshot_only:
        if recorder.snapshot_s == 0:
            raise UsageError("--snapshot-only needs --snapshot SECONDS (or [recorder] snapshot_s)")
        recorder = dataclasses.replace(recorder, continuous=False)
    if recorder.snapshot_s > 0 and recorder.path is None:
        raise UsageError(
            "--snapshot needs --record PATH (or [recorder] path): snapshots are written beside it"
        )
    return config.replace(sim=sim, output=output, record=record, recorder=recorder)


def run(args: argparse.Namespace) -> int:
    if args.fleet_connect and args.robots == 1:
        raise UsageError("--fleet-connect goes with --robots N")
    if args.fleet_ros2 and args.robots == 1:
        raise UsageError("--fleet-ros2 goes with --robots N")
    if args.robots != 1:
        if not 2 <= args.robots <= 8:
            raise UsageError(f"--robots must be 1..8, not {args.robots}")
        from agent.commands.sim_fleet import run_fleet

        return run_fleet(args)
    faults: list[Fault] = args.fault
    check_faults_within(faults, args.seconds)
    config = _config(args)
    assert config.sim is not None
    stop = threading.Event()  # set from ordinary code only, never from a signal handler
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    live = sys.stderr.isatty() and not args.json
    out_dir = Path(args.out)
    world = config.sim.world
    unknown = [name for name in args.deliver or () if name not in {p.name for p in world.places}]
    if unknown:
        raise UsageError(
            f"--deliver: no place {', '.join(map(repr, unknown))} in the world "
            f"({', '.join(p.name for p in world.places) or 'it names no [[places]]'})"
        )
    with contextlib.ExitStack() as stack:
        shutdown = stack.enter_context(ShutdownRequest())
        # SIGUSR1: save the map now; SIGUSR2: a flight-recorder snapshot (dropped until the agent exists).
        requests = stack.enter_context(AgentRequests())
        robot = stack.enter_context(simulated_robot(config.sim))
        scorer = Scorer(robot.simulation, Path(args.truth) if args.truth else None)
        stack.callback(scorer.discard)  # after a clean run the truth file is already in place
        goals: list[tuple[float, float, float | None]] = args.goal
        missions = args.explore or args.deliver is not None
        if (goals or missions) and (
            config.output.url != "pty" or config.output.format is OutputFormat.MAVLINK
        ):
            raise UsageError(
                "--goal, --explore and --deliver need the simulated controller on a pty sending command "
                'frames ([output] url = "pty", format "frame")'
            )
        if goals and missions:
            raise UsageError("--goal with --explore or --deliver: the robot drives one mission at a time")
        sent_follows: list[tuple[Any, ...]] = args.send_follow
        if sent_follows and (config.output.url != "pty" or config.output.format is OutputFormat.MAVLINK):
            raise UsageError(
                "--send-follow needs the simulated controller on a pty sending command frames "
                '([output] url = "pty", format "frame")'
            )
        if sent_follows and (goals or missions or args.follow):
            raise UsageError("--send-follow with --goal, --explore, --deliver or --follow: give one")
        commands: list[tuple[Any, ...]] = mission_items(args.deliver) if missions else list(goals)
        commands += sent_follows
        url, controller = serve_pose_stream(
            stack, config, commands, not args.goals_known_map, args.controller_record
        )
        mapping = config.slam.mode is not SlamMode.LOCALIZATION
        if mapping:
            tidy_map_folder(out_dir)
        agent = create_agent(
            config,
            robot=robot,
            output_url=url,
            observer=scorer.observe,
            map_dir=out_dir if mapping else None,
        )
        recorder = agent.flight_recorder
        requests.attach(agent.request_map_save, recorder.request_snapshot if recorder is not None else None)
        if agent.flight_recorder is not None:
            scorer.on_truth = _truth_recorder(agent.flight_recorder)
        if agent.mapper is not None:
            # Last: the map is saved through it once the agent has stopped (a SLAM process ends here).
            stack.callback(agent.mapper.close)
        script: MissionScript | None = None
        if missions:
            places = {p.name: NamedPlace(p.name, p.x_m, p.y_m, p.yaw_rad) for p in world.places}
            if not agent.enable_missions(places):
                raise UsageError(
                    "--explore and --deliver need the navigation: SLAM, a laser, wheels and the pose "
                    "output ([navigation] enabled)"
                )
            assert agent.missions is not None
            script = MissionScript(agent.missions, robot.simulation, args.deliver)
        give_way_to_agent(agent, robot)
        injector = FaultInjector(faults, robot, agent)
        follow = None
        if args.follow:
            if goals or missions:
                raise UsageError("--follow, --goal and --explore/--deliver each drive the robot: give one")
            from agent.runtime.agent import laser_mount_for
            from agent.runtime.follow_setup import camera_view, make_follow_loop
            from agent.sim_follow import FollowScore

            m = laser_mount_for(config, world)
            fine = args.follow_fine == "on" and config.forward_camera is not None
            loop = make_follow_loop(
                agent, config, (m.x_m, m.y_m, m.yaw_rad), camera_view(world.forward_camera) if fine else None
            )
            follow = FollowScore(robot, loop, config.following.tag_id, config.following.distance_m)
            if args.follow_trace:
                follow.trace = []
            injector.follow_loop = loop
        on_command = None
        if sent_follows:
            from agent.runtime.agent import laser_mount_for
            from agent.runtime.follow_loop import follow_summary
            from agent.runtime.follow_setup import camera_view, make_follow_loop

            m = laser_mount_for(config, world)
            fine = args.follow_fine == "on" and config.forward_camera is not None
            on_command = make_follow_loop(
                agent, config, (m.x_m, m.y_m, m.yaw_rad), camera_view(world.forward_camera) if fine else None
            )
            agent.enable_following(on_command)
            injector.follow_loop = on_command
        agent.start()
        if on_command is not None:
            from agent.runtime.follow_setup import start_following

            start_following(agent, on_command, stop, stack)
        if follow is not None:
            from agent.runtime.follow_setup import start_following

            start_following(agent, follow.loop, stop, stack)
            thread = threading.Thread(target=follow.run, args=(stop,), name="sim-follow-score", daemon=True)
            thread.start()
            stack.callback(thread.join, 1.0)
        # The world's route, driven from the agent's own pose, unless goals, missions or following drive it.
        driven = goals or script is not None or follow is not None or on_command is not None
        route = () if driven else world.route
        autopilot = threading.Thread(
            target=_autopilot,
            args=(agent, route, world.route_speed_mps, stop),
            name="sim-autopilot",
            daemon=True,
        )
        autopilot.start()
        agent.settle_heap()
        t0 = time.monotonic()
        t0_us = time.monotonic_ns() // 1000
        try:
            _watch(args, agent, scorer, injector, shutdown, t0, live, controller)
        finally:
            stop.set()
            autopilot.join(1.0)
            elapsed = time.monotonic() - t0
            agent.stop(why=shutdown.why("an error" if sys.exc_info()[1] is not None else "the run's end"))
            status = agent.status()
            slam_path = agent.mapper.trajectory() if agent.mapper is not None else np.zeros((0, 3))
            if controller is not None:
                controller.stop()
            scorer.drain()
        if live:
            print(file=sys.stderr)
        files = _write_files(
            args, out_dir, robot.simulation, scorer, agent.mapper if mapping else None, slam_path
        )
        summary = _summary(config, elapsed, status, scorer, controller, injector, files)
        if script is not None:
            summary["exploration"] = _exploration_summary(agent, robot.simulation)
        if script is not None and args.deliver:
            summary["delivery"] = script.delivery(controller)
        summary["t0_us"] = t0_us
        summary["sim_devices"] = robot.lateness()
        if follow is not None:
            summary["follow"] = follow.figures()
            if args.follow_trace:
                follow.write_trace(args.follow_trace)
        if on_command is not None:
            summary["goals"] = None  # the controller sent follow commands, no goals
            summary["follow"] = follow_summary(on_command)
            summary["follow_control"] = (
                agent.follow_control.summary() if agent.follow_control is not None else None
            )
            summary["follow_commands"] = _follow_commands(controller, len(commands))
        if agent.flight_recorder is not None:
            summary["recording"] = {
                "files": [str(p) for p in agent.flight_recorder.files],
                **agent.flight_recorder.counters(),
            }
    summary["stop"] = shutdown.stop_times()  # from SIGTERM / SIGINT to here; None: none came
    if args.json:
        print(dumps_json(summary, sort_keys=True))
    else:
        _print_summary(summary)
    return 0


def _truth_recorder(recorder: McapRecorder) -> Callable[[int, float, float, float], None]:
    """The simulation's truth into the recording (``/sim/truth``), for ``eval slam --log``'s ATE. Truths
    sampled after the agent stopped (its last poses, scored once it has) are left out, not counted as
    drops: they are the simulation's, not the agent's."""

    def record(t_ns: int, x_m: float, y_m: float, yaw_rad: float) -> None:
        if not recorder.closed:
            recorder.record("sim_truth", t_ns, TruthSample(t_ns, x_m, y_m, yaw_rad))

    return record


def _autopilot(
    agent: Agent, route: tuple[tuple[float, float], ...], speed_mps: float, stop: threading.Event
) -> None:
    """Pure pursuit along the route from the agent's own fused pose; nothing without a live source or a
    route."""
    if not route:
        return
    follower = RouteFollower(route, speed_mps)
    sources = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY
    while not stop.wait(_AUTOPILOT_PERIOD_S):
        estimate, flags = agent.pose()
        if not flags & sources:
            continue  # no pose to steer by: the dead-man stops the wheels
        v, omega = follower.command(estimate.x_m, estimate.y_m, estimate.yaw_rad)
        agent.command_velocity(v, omega)


def _watch(
    args: argparse.Namespace,
    agent: Agent,
    scorer: Scorer,
    injector: FaultInjector,
    shutdown: ShutdownRequest,
    t0: float,
    live: bool,
    controller: SimulatedController | None = None,
) -> None:
    """Until --seconds, a stop request, (with --goal) the last goal's end, or (with --explore,
    --deliver) the missions' end; the status line each second."""
    next_status = t0 + 1.0
    follows_done_s: float | None = None
    last_counts: dict[str, int] = {}
    last_t = t0
    while not shutdown.requested:
        now = time.monotonic()
        elapsed = now - t0
        if elapsed >= args.seconds:
            return
        injector.step(elapsed, t0)
        scorer.drain()
        if now >= next_status:
            next_status += 1.0
            missions = args.explore or args.deliver is not None
            if (args.goal or missions) and controller is not None and controller.counts().goals_done:
                return
            if args.send_follow and controller is not None and controller.counts().goals_done:
                # The last follow command answered: a second more, for the statuses that follow it.
                follows_done_s = follows_done_s if follows_done_s is not None else elapsed
                if elapsed - follows_done_s >= 1.0:
                    return
            status = agent.status()
            dt = max(now - last_t, 1e-3)
            rate = {
                k: (status.counts.get(k, 0) - last_counts.get(k, 0)) / dt for k in ("frames", "fixes_fused")
            }
            last_counts, last_t = dict(status.counts), now
            est = status.estimate
            names = " ".join(f.name or "" for f in PoseFlags if f & status.flags) or "no source"
            p50, p99 = (
                agent.output.latency.percentiles(50, 99, last=60) if agent.output else (math.nan, math.nan)
            )
            age50 = agent.output.exposure_age.percentiles(50, last=60)[0] if agent.output else math.nan
            line = (
                f"t={elapsed:5.1f}s pose=({est.x_m:6.3f},{est.y_m:6.3f},{math.degrees(est.yaw_rad):6.1f}deg) "
                f"err={100 * scorer.last_error_m:5.2f}cm frames={rate['frames']:4.1f}/s "
                f"fixes={rate['fixes_fused']:4.1f}/s latency p50={p50:5.1f} p99={p99:5.1f}ms "
                f"age p50={age50:5.1f}ms [{names}]"
            )
            if live:
                print("\r" + line + "\033[K", end="", file=sys.stderr, flush=True)
            elif not args.json:
                print(line, file=sys.stderr, flush=True)
        shutdown.wait(min(0.05, max(0.0, args.seconds - elapsed)))


def _write_png(path: Path, image: np.ndarray) -> None:
    """Atomically: a reader (or a SIGKILL) never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.png")
    if not cv2.imwrite(str(tmp), image):
        raise OSError(f"could not write {tmp}")
    tmp.replace(path)


def _write_files(
    args: argparse.Namespace,
    out_dir: Path,
    sim: Simulation,
    scorer: Scorer,
    mapper: ScanMapper | None,
    slam_path: np.ndarray,
) -> dict[str, str]:
    files: dict[str, str] = {}
    if mapper is not None:
        # As `vlp-agent run` saves it at a stop: the filter's map, then the final optimisation (off in the
        # shipped simulated configs: [slam] loop_final_scan_chain) and the map again.
        saved, optimised = save_final_map(
            mapper,
            out_dir,
            paths_for=lambda slam: _map_paths(scorer, slam),
            title=f"map.png: laser SLAM map of {sim.world.name}",
        )
        if optimised:
            slam_path = mapper.trajectory()
        if saved:
            files["map_yaml"], files["map_pgm"], files["map_png"] = (str(p) for p in saved)
    if args.record_fusion:
        files["fusion_recording"] = str(Path(args.record_fusion))
    truth = scorer.finish_truth()
    if truth is not None:
        files["truth_csv"] = str(truth)
    trajectory = Path(args.trajectory) if args.trajectory else out_dir / "trajectory.png"
    if len(scorer.truth_path):
        _write_png(trajectory, _trajectory_picture(sim, scorer, slam_path))
        files["trajectory_png"] = str(trajectory)
    return files


def _map_paths(scorer: Scorer, slam_path: np.ndarray) -> list[MapPath]:
    """The truth underneath, thick; the fused pose stream and the SLAM trajectory thin on top of it."""
    return [
        MapPath("truth (simulator)", _xy(scorer.truth_path.points()), figure.TRUTH, figure.TRUTH_WIDTH_PX),
        MapPath("fused pose (output)", _xy(scorer.fused_path.points()), figure.FUSED, figure.FUSED_WIDTH_PX),
        MapPath("SLAM estimate", np.asarray(slam_path, dtype=np.float64).reshape(-1, 3)[:, :2], figure.SLAM),
    ]


def _xy(points: list[tuple[float, float]]) -> np.ndarray:
    return np.asarray(points, dtype=np.float64).reshape(-1, 2)


def _trajectory_picture(sim: Simulation, scorer: Scorer, slam_path: np.ndarray) -> np.ndarray:
    """The world's walls and LEDs with the paths of :func:`_map_paths` over them, axes in metres, a legend
    and a scale bar; at least ``MIN_MAP_PX`` pixels across the building."""
    walls = np.array([(w.x1_m, w.y1_m, w.x2_m, w.y2_m) for w in sim.world.walls]).reshape(-1, 4)
    paths = [p for p in _map_paths(scorer, slam_path) if p.xy.shape[0] >= 1]
    pts = np.vstack([walls[:, :2], walls[:, 2:], *(p.xy for p in paths)])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    xmin, ymin = pts.min(axis=0)
    xmax, ymax = pts.max(axis=0)
    pad = 0.03 * max(xmax - xmin, ymax - ymin, 1.0)
    bounds = (xmin - pad, xmax + pad, ymin - pad, ymax + pad)
    span = max(bounds[1] - bounds[0], bounds[3] - bounds[2])
    px_per_m = 1000 / span
    left, top = 80, 66
    plot_w = int((bounds[1] - bounds[0]) * px_per_m)
    plot_h = int((bounds[3] - bounds[2]) * px_per_m)
    entries = [figure.Entry(p.label, p.colour) for p in paths]
    entries += [figure.Entry("LED", figure.LED, figure.Mark.DOT), figure.Entry("wall", figure.BLACK)]
    legend_w, legend_h = figure.legend_size(entries)
    panel_x = left + plot_w + 24
    width = panel_x + max(legend_w, 220) + 16
    height = max(top + plot_h + 62, top + legend_h + 120)
    img = np.full((height, width, 3), 255, np.uint8)
    axes = figure.Axes((left, top, left + plot_w, top + plot_h), bounds)
    axes.draw(img, grid=True)
    for x1, y1, x2, y2 in walls:
        cv2.line(img, axes.to_px(x1, y1), axes.to_px(x2, y2), figure.BLACK, 3)
    for led in sim.world.leds:
        centre = axes.to_px(led.x_m, led.y_m)
        cv2.circle(img, centre, 6, figure.LED, -1, cv2.LINE_AA)
        cv2.circle(img, centre, 6, figure.BLACK, 1, cv2.LINE_AA)
    for p in paths:
        figure.draw_path(img, axes, p.xy, p.colour, p.width)
    figure.title(img, f"trajectory.png: {sim.world.name}, paths over the world's walls and LEDs")
    figure.legend(img, entries, (panel_x, top))
    y = top + legend_h + 50
    figure.scale_bar(img, px_per_m, (panel_x + 10, y))
    figure.text(img, "ring: where a path starts", (panel_x + 10, y + 34), 0.45)
    return img


def _round(value: float, digits: int = 3) -> float | None:
    return None if math.isnan(value) else round(value, digits)


def _goal_summary(controller: SimulatedController | None) -> dict[str, Any] | None:
    """What the simulated controller's goals came to, from the goal statuses it decoded (None: no goals)."""
    if controller is None:
        return None
    counts = controller.counts()
    if not counts.goals_sent:
        return None
    ended: dict[int, tuple[str, str]] = {}
    for goal_id, state, reason in counts.statuses:
        if not 1 <= goal_id <= counts.goals_sent:
            continue  # a mission's own goals (ids from 0xC000), not the controller's
        if state in ("REACHED", "FAILED", "REJECTED", "CANCELLED"):
            ended[goal_id] = (state, reason)  # the last: a goal rejected NOT_LOCALIZED is sent again
    outcome = [s for s, _ in ended.values()]
    return {
        "sent": counts.goals_sent,
        "reached": outcome.count("REACHED"),
        "failed": outcome.count("FAILED"),
        "rejected": outcome.count("REJECTED"),
        "cancelled": outcome.count("CANCELLED"),
        "outcomes": {str(goal_id): f"{state} {reason}".strip() for goal_id, (state, reason) in ended.items()},
        "all_ended": counts.goals_done,
        "statuses_decoded": len(counts.statuses),
    }


def _follow_commands(controller: SimulatedController | None, sent: int) -> list[str]:
    """Every status the simulated controller decoded about its follow ids (1..``sent``), in order, as
    ``"ID STATE REASON"``."""
    if controller is None:
        return []
    statuses = controller.counts().statuses
    return [f"{goal_id} {state} {reason}" for goal_id, state, reason in statuses if 1 <= goal_id <= sent]


def mission_items(deliver: tuple[str, str] | None) -> list[tuple[Any, ...]]:
    """What the simulated controller sends for --explore / --deliver: explore (the map starts empty: a
    place needs a map with free space around it and a way there); then, delivering, go to A, go to B, go
    to A. (Not "B and come back": that returns to where the robot *thought* it was at A, its localization
    error at A added to the one at the end.)"""
    items: list[tuple[Any, ...]] = [("explore",)]
    if deliver is not None:
        a, b = deliver
        items += [("place", a, False), ("place", b, False), ("place", a, False)]
    return items


class MissionScript:
    """--explore and --deliver: the missions go to the agent as its controller sends them, explore and
    go-to-place command frames on the serial line (the simulated controller, ``mission_items``; mission
    ids 1 to 4); this watches them: the true position's error at each place reached (the mission loop's
    ``on_leg``) and, from the statuses the controller decoded, each mission's answer and end."""

    def __init__(self, missions: MissionLoop, sim: Simulation, deliver: tuple[str, str] | None) -> None:
        self.missions = missions
        self.sim = sim
        self.deliver = deliver
        self.items = mission_items(deliver)
        self.ends: list[dict[str, Any]] = []  # each leg reached: the place, the true position's error
        missions.on_leg = self._leg

    def _leg(self, mission_id: int, leg: int) -> None:
        if self.deliver is None or not 2 <= mission_id <= len(self.items):
            return
        place = self.items[mission_id - 1][1]
        truth = self.sim.pose()
        where = self.missions.places[place]
        error = math.hypot(truth.x_m - where.x_m, truth.y_m - where.y_m)
        end = {"mission": mission_id, "place": place, "error_m": round(error, 4)}
        self.ends.append({**end, "t_s": round(self.sim.elapsed_s(), 1)})

    def delivery(self, controller: SimulatedController | None) -> dict[str, Any]:
        statuses = controller.counts().statuses if controller is not None else ()
        missions = []
        for mission_id, item in enumerate(self.items, start=1):
            mine = [f"{s} {r}".replace(" NONE", "") for goal_id, s, r in statuses if goal_id == mission_id]
            answers = [t for t in mine if t.split()[0] in ("ACCEPTED", "REJECTED")]
            ends = [t for t in mine if t.split()[0] in ("REACHED", "FAILED", "CANCELLED")]
            what = (
                "explore" if item[0] == "explore" else f"go to {item[1]}" + (" and back" if item[2] else "")
            )
            missions.append(
                {
                    "mission": mission_id,
                    "command": what,
                    "answers": answers,  # a mission refused for want of a pose is sent again
                    "end": ends[-1] if ends else None,
                    "legs": [e for e in self.ends if e["mission"] == mission_id],
                }
            )
        errors = [leg["error_m"] for leg in self.ends]
        return {
            "places": list(self.deliver or ()),
            "missions": missions,
            "complete": all(m["end"] == "REACHED" for m in missions),
            "ends": self.ends,
            "max_end_error_m": max(errors) if errors else None,
        }


def _exploration_summary(agent: Agent, sim: Simulation) -> dict[str, Any] | None:
    """With --explore: the explorer's end and how much of the true reachable free area (the doors as they
    are at the end) the last SLAM map it was given had seen (None: not exploring)."""
    loop = agent.missions
    if loop is None:
        return None
    from agent.commands.eval_explore import explored_share

    out = loop.status()
    grid = loop.last_grid
    fraction, area_m2 = explored_share(grid, sim.world, sim) if grid is not None else (0.0, math.nan)
    out["explored_fraction"] = round(fraction, 4)
    out["reachable_free_m2"] = None if math.isnan(area_m2) else round(area_m2, 2)
    out["stopped_reason"] = (
        f"{out['state']}: {out['reason']}"
        if loop.exploration_ended
        else f"--seconds spent ({out['state']}: {out['reason']})"
    )
    out["door_events"] = [
        {"t_s": round(t_s, 1), "door": name, "closed": closed} for t_s, name, closed in sim.door_events()
    ]
    return out


def _summary(
    config: AgentConfig,
    elapsed: float,
    status: Any,
    scorer: Scorer,
    controller: SimulatedController | None,
    injector: FaultInjector,
    files: dict[str, str],
) -> dict[str, Any]:
    assert config.sim is not None
    own_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    slam_mb = status.mapper.get("worker_peak_rss_kb", 0) / 1024.0
    slam_shared_mb = status.mapper.get("worker_shared_kb", 0) / 1024.0
    scores = scorer.figures()
    latency_p50, latency_p99 = status.latency_ms
    counts = status.counts
    return {
        "world": config.sim.world.name,
        "seconds": round(elapsed, 3),
        "distance_m": scores["distance_m"],
        "output_format": config.output.format.value,
        "frames_out": int(status.output.get("frames", 0)),
        "frames_received": controller.frames if controller is not None else None,
        "frames_rejected_by_receiver": controller.bad if controller is not None else None,
        "camera_frames": counts.get("frames", 0),
        "fixes": counts.get("fixes", 0),
        "fixes_fused": counts.get("fixes_fused", 0),
        "fixes_fused_guarded": counts.get("fixes_fused_guarded", 0),
        "fixes_rejected": counts.get("fixes_rejected", 0),
        "fixes_rejected_integrity": counts.get("fixes_rejected_integrity", 0),
        "fixes_rejected_alert_limit": counts.get("fixes_rejected_alert_limit", 0),
        "no_fix": counts.get("no_fix", 0),
        "no_fix_reasons": status.no_fix_reasons,
        "dropped": int(sum(status.drops.values())),
        "drops": status.drops,
        "latency_ms_p50": None if math.isnan(latency_p50) else round(latency_p50, 3),
        "latency_ms_p99": None if math.isnan(latency_p99) else round(latency_p99, 3),
        "latency_definition": LATENCY_DEFINITION,
        "exposure_age_ms_p50": _round(status.exposure_age_ms[0]),
        "exposure_age_ms_p99": _round(status.exposure_age_ms[1]),
        "vlp_ms_p50": None if math.isnan(status.vlp_ms[0]) else round(status.vlp_ms[0], 3),
        "vlp_ms_p99": None if math.isnan(status.vlp_ms[1]) else round(status.vlp_ms[1], 3),
        "hot_path_cpu_ms_p50": _round(status.hot_path_cpu_ms[0]),
        "hot_path_cpu_ms_p99": _round(status.hot_path_cpu_ms[1]),
        "pose_error_cm_mean": scores["pose_error_cm_mean"],
        "pose_error_cm_p95": scores["pose_error_cm_p95"],
        "pose_error_cm_max": scores["pose_error_cm_max"],
        "within_2cm": scores["within_2cm"],
        "yaw_error_deg_p95": scores["yaw_error_deg_p95"],
        "source_share": scores["source_share"],
        "collisions": scores["collisions"],
        "collisions_walls": scores["collisions_walls"],
        "collisions_people": scores["collisions_people"],
        "clearance_wall_m_min": scores["clearance_wall_m_min"],
        "clearance_person_m_min": scores["clearance_person_m_min"],
        "goals": _goal_summary(controller),
        "commands": status.commands,
        "slam": status.mapper,
        "fusion": status.fusion,
        "output": status.output,
        "devices": {
            name: {"ok": d.ok, "reason": d.reason, "failures": d.failures, "recoveries": d.recoveries}
            for name, d in status.devices.items()
        },
        "unavailable": status.unavailable,
        "following": status.following,
        "faults": injector.applied,
        "counts": counts,
        "files": files,
        # The agent's processes: its own peak and its SLAM process's (an upper bound of their sum), the
        # SLAM process's pages that are shared (the interpreter's and libraries' code, in the agent's RSS
        # too) counted once. The simulated camera's renderer is the simulated hardware's, not the agent's.
        "peak_rss_mb": round(own_mb + slam_mb - slam_shared_mb, 1),
        "peak_rss_mb_parts": {
            "agent": round(own_mb, 1),
            "slam_process": round(slam_mb, 1),
            "slam_process_shared": round(slam_shared_mb, 1),
        },
    }


def _plural(n: int, one: str, many: str) -> str:
    return f"{n} {one if n == 1 else many}"


def _counts_text(counts: dict[str, int]) -> str:
    """ " (camera 2, laser 1)" for the non-zero counts; "" when there are none."""
    parts = [f"{name} {n}" for name, n in sorted(counts.items()) if n]
    return f" ({', '.join(parts)})" if parts else ""


def _device_text(name: str, device: dict[str, Any]) -> str:
    """ "laser: 1 failure, 1 recovery; now ok" (or "now down: <reason>")."""
    now = "now ok" if device["ok"] else f"now down: {device['reason'] or 'no reason given'}"
    recoveries = device.get("recoveries")
    recovered = f", {_plural(recoveries, 'recovery', 'recoveries')}" if recoveries is not None else ""
    return f"{name}: {_plural(device['failures'], 'failure', 'failures')}{recovered}; {now}"


def _faults_text(applied: list[dict[str, Any]]) -> str:
    """ "laser off at 10.0 s, laser back at 15.0 s": when each injected fault began and ended."""
    return ", ".join(f"{f['kind']} {'off' if f['on'] else 'back'} at {f['t_s']:.1f} s" for f in applied)


def _print_summary(s: dict[str, Any]) -> None:
    def num(value: Any, fmt: str) -> str:
        return "n/a" if value is None else format(value, fmt)

    print(f"vlp-agent sim on world {s['world']!r} for {s['seconds']:.1f} s: drove {s['distance_m']:.2f} m")
    kind = "pose frames" if s["output_format"] == "frame" else "MAVLink messages"
    print(
        f"  pose stream       {s['frames_out']} {kind} written"
        + (f", {s['frames_received']} decoded by the controller" if s["frames_received"] is not None else "")
    )
    print(
        f"  pose error        mean {num(s['pose_error_cm_mean'], '.2f')} cm, "
        f"p95 {num(s['pose_error_cm_p95'], '.2f')} cm, "
        f"max {num(s['pose_error_cm_max'], '.2f')} cm; {100 * (s['within_2cm'] or 0):.1f} % within 2 cm"
    )
    print(
        f"  latency           frame captured -> last byte p50 {num(s['latency_ms_p50'], '.1f')} ms, "
        f"p99 {num(s['latency_ms_p99'], '.1f')} ms; mid-exposure -> last byte p50 "
        f"{num(s['exposure_age_ms_p50'], '.1f')} ms, p99 {num(s['exposure_age_ms_p99'], '.1f')} ms"
    )
    print(
        f"  VLP               {s['fixes']} fixes from {s['camera_frames']} frames, {s['fixes_fused']} fused "
        f"({s['fixes_fused_guarded']} under the integrity guard), {s['fixes_rejected']} gated out, refused "
        f"{s['fixes_rejected_integrity']} degraded and {s['fixes_rejected_alert_limit']} past the alert limit"
    )
    slam = s["slam"]
    updates, applied = slam.get("filter_updates", 0), slam.get("fixes_applied", 0)
    print(f"  SLAM              {updates} filter updates, {applied} VLP fixes applied")
    share = ", ".join(f"{k} {100 * v:.0f} %" for k, v in s["source_share"].items())
    print(f"  sources live      {share} of frames")
    delivery = s.get("delivery")
    if delivery:
        for mission in delivery["missions"]:
            legs = ", ".join(f"{leg['place']} {100 * leg['error_m']:.1f} cm" for leg in mission["legs"])
            print(
                f"  mission {mission['mission']}         {mission['command']}: "
                f"{', '.join(mission['answers']) or 'no answer'}, ended {mission['end'] or 'not yet'}"
                + (f" (at {legs})" if legs else "")
            )
    exploration = s.get("exploration")
    if exploration:
        print(
            f"  exploration       {100 * exploration['explored_fraction']:.1f} % of "
            f"{exploration['reachable_free_m2']} m2 seen; {exploration['stopped_reason']}"
        )
    goals = s.get("goals")
    if goals:
        outcomes = ", ".join(f"{goal_id} {text.lower()}" for goal_id, text in goals["outcomes"].items())
        print(
            f"  goals             {goals['reached']} of {goals['sent']} sent reached"
            + (f" ({outcomes})" if outcomes else "")
        )
    gaps = [
        f"{what} {gap * 100:.0f} cm"
        for what, gap in (("wall", s["clearance_wall_m_min"]), ("person", s["clearance_person_m_min"]))
        if gap is not None
    ]
    print(
        f"  contact           {s['collisions']} collisions (walls {s['collisions_walls']}, people "
        f"{s['collisions_people']}); closest approach {', '.join(gaps) or 'none'}"
    )
    print(f"  dropped           {s['dropped']}{_counts_text(s['drops'])}")
    if s["no_fix_reasons"]:
        reasons = "; ".join(f"{n} x {r}" for r, n in s["no_fix_reasons"].items())
        print(f"  no VLP fix        {reasons}")
    for name, why in s["unavailable"].items():
        print(f"  not running       {name}: {why}")
    for name, device in s["devices"].items():
        if device["failures"]:
            print(f"  device faults     {_device_text(name, device)}")
    if s["faults"]:
        print(f"  injected          {_faults_text(s['faults'])}")
    following = s.get("following")
    if following:
        f = following
        print(
            f"  following (RFID)  the tag at {f['bearing_deg']:+.0f} deg +-{f['spread_deg']:.0f}, "
            f"~{f['range_m']:.1f} m, confidence {f['confidence']:.2f}, absent {f['p_absent']:.2f} "
            f"(after {f['cycles']} read cycles)"
        )
    parts = s.get("peak_rss_mb_parts", {})
    split = (
        f" (agent {parts['agent']:.0f}, SLAM process {parts['slam_process']:.0f} of which "
        f"{parts['slam_process_shared']:.0f} shared with the agent)"
        if parts
        else ""
    )
    print(f"  memory            peak RSS {s['peak_rss_mb']:.0f} MB{split}")
    for path in s["files"].values():
        print(f"  wrote             {path}")
