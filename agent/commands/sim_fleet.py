"""``vlp-agent sim --robots N``: a fleet in one simulated world on this machine (docs/fleet.md, "A simulated
fleet").

Each robot is its own ``vlp-agent sim`` process (its own simulated devices, the world without its route,
started ``--spacing`` metres apart along the world's start heading and facing its goal, seed ``--seed + i``)
with ``[fleet] socket`` set, and its own ``vlp-agent bridge`` (peer mode, scouting off, ``tcp/127.0.0.1``:
robot i listens on one port and connects to every earlier robot's, and to each ``--fleet-connect``).
Robot i gets the i-th ``--goal`` through the fleet (``agent.fleet.goal_sender``, as ``vlp-agent fleet
goal`` sends it), sent again while its agent is not ready for it. An observer peer in this process hears
every pose. The run ends when every goal has ended or at ``--seconds``; the summary (``--json``: one
object) has ``robots`` (each robot's goal outcome and its simulator's pose figures), ``collisions`` (times
two robots' true footprints touched), the closest two robots came, and ``fleet_pose_latency_ms_p95`` (a
pose's age at its delivery to the observer: from the pose's own time on the agent, so it includes how old
the fused estimate was when the agent sent it).

The robots simulate the same world in separate processes: a robot does not see another with its laser,
only through the fleet (the costmap's fleet layer, ``agent.navigation.fleet_layer``).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from agent.commands.args import UsageError, dumps_json
from agent.config import load_config
from agent.fleet import payloads
from agent.fleet.audit import Audit
from agent.fleet.bridge_config import ZenohConfig
from agent.fleet.fleet_score import contacts, separation
from agent.fleet.goal_sender import GoalSender
from agent.fleet.local_protocol import GoalMessage
from agent.fleet.map_view import FleetMaps, picture, report
from agent.shipped import DEFAULT_SIM_CONFIG
from firmware_protocol.command_frame import GoalReason, GoalState
from firmware_protocol.errors import ProtocolError

__all__ = ["run_fleet"]

_STOP_WAIT_S = 60.0
# Reasons a goal is refused that pass on their own in a fleet among people: the agent not localized yet,
# busy; its map not reaching the goal yet (built as the robot's laser sees more: the robot starts facing its
# goal, but a loaded machine can answer before the first scans reached that far); a person or another robot
# on the goal or across the way (IN_OBSTACLE, UNREACHABLE: the office's walker crosses both goals of the
# head-on run, and a goal checked while she passes was refused for good before).
_RETRY = (
    GoalReason.NOT_LOCALIZED,
    GoalReason.BUSY,
    GoalReason.OUTSIDE_MAP,
    GoalReason.IN_OBSTACLE,
    GoalReason.UNREACHABLE,
)


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _world_text(text: str, start: tuple[float, float, float]) -> str:
    """The world without its route, the robot's start moved."""
    text = re.sub(r"(?ms)^\[route\]\n.*?(?=^\[|\Z)", "", text)
    line = f"start = {{ x_m = {start[0]:.3f}, y_m = {start[1]:.3f}, yaw_deg = {math.degrees(start[2]):.3f} }}"
    out, n = re.subn(r"(?m)^start\s*=\s*\{[^}]*\}", line, text, count=1)
    if n != 1:
        raise UsageError("--robots: the world has no '[robot] start = { ... }' line to move the robots apart")
    return out


class _Observer:
    """Every pose heard on ``fleet/*/pose``: its age at delivery (this machine's monotonic clock, which the
    simulated agents' clocks are)."""

    def __init__(self) -> None:
        self.ages_ms: list[float] = []
        self.robots: set[str] = set()
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        now_us = time.monotonic_ns() // 1000
        try:
            robot = payloads.robot_of("fleet", str(sample.key_expr))
            pose = payloads.decode_pose(bytes(sample.payload.to_bytes()), robot)
        except ProtocolError:
            return
        with self.lock:
            self.robots.add(robot)
            self.ages_ms.append((now_us - pose.t_us) / 1000.0)


def _drive(
    sender: GoalSender,
    robot: str,
    goal: GoalMessage,
    deadline: float,
    out: dict[str, Any],
    stop: threading.Event,
) -> None:
    """Send ``goal`` until it is taken (rejected for a reason that passes, ``_RETRY``: again, a second
    later), then wait for its end. ``out["history"]`` keeps each attempt's last state and reason."""
    out.update(state="not sent", reason=None, attempts=0, history=[])
    while not stop.is_set() and time.monotonic() < deadline:
        out["attempts"] += 1
        trace = sender.send(robot, goal, wait_end=True, timeout_s=max(deadline - time.monotonic(), 0.1))
        last = trace.last
        if last is None:
            out["history"].append("sent, no answer" if trace.sent else "not sent: no bridge subscribed")
        else:
            out["state"] = (
                GoalState(last.state).name.lower()
                if last.state in GoalState._value2member_map_
                else last.state
            )
            out["reason"] = (
                GoalReason(last.reason).name.lower()
                if last.reason in GoalReason._value2member_map_
                else last.reason
            )
            out["statuses"] = len(trace.states)
            out["history"].append(f"{out['state']} ({out['reason']})")
            if not (last.state == GoalState.REJECTED and last.reason in _RETRY):
                return
        stop.wait(1.0)


def _stop(proc: subprocess.Popen[str]) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=_STOP_WAIT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


def _maps_summary(fleet_maps: FleetMaps, png: Path) -> dict[str, Any]:
    """The robots' newest maps merged (docs/fleet.md, 'Maps'), the picture written to ``png``."""
    maps, poses, topologies = fleet_maps.snapshot()
    summary = report(maps, poses)
    summary["topologies"] = sorted(topologies)
    summary["rejected"] = fleet_maps.rejected
    summary["png"] = None
    if maps:
        import cv2

        if cv2.imwrite(str(png), picture(maps, poses)):
            summary["png"] = str(png)
    return summary


def run_fleet(args: argparse.Namespace) -> int:
    n: int = args.robots
    goals: list[tuple[float, float, float | None]] = args.goal
    if len(goals) != n:
        raise UsageError(f"--robots {n} needs {n} --goal (one per robot, in order), got {len(goals)}")
    if args.explore or args.deliver is not None or args.follow:
        raise UsageError(
            "--robots drives each robot to its --goal: not with --explore, --deliver or --follow"
        )
    config_path = Path(args.config).resolve() if args.config else None
    base = load_config(config_path or DEFAULT_SIM_CONFIG)
    if base.sim is None:
        raise UsageError("vlp-agent sim needs a config with a [sim] table (see examples/sim.toml)")
    if base.fleet.socket is not None:
        raise UsageError("--robots sets each robot's [fleet] socket itself: give a config without one")
    world_file, world = base.sim.world_file, base.sim.world
    if args.world:
        from agent.commands.worlds import resolve_world
        from drivers.sim.worldfile import load_world

        world_file = resolve_world(args.world).resolve()
        world = load_world(world_file)
    start = (world.robot.start.x_m, world.robot.start.y_m, world.robot.start.yaw_rad)
    radius = base.navigation.radius_m
    out_dir = Path(args.out) / "fleet"
    out_dir.mkdir(parents=True, exist_ok=True)
    config_text = Path(base.file).read_text(encoding="utf-8")
    seed = args.seed if args.seed is not None else base.sim.seed
    ports = [_free_port() for _ in range(n)]
    extra: list[str] = list(args.fleet_connect)  # an outside listener: a fleet view, a test's audit
    bad = [e for e in extra if "/" not in e or '"' in e]
    if bad:
        raise UsageError(f"--fleet-connect {bad[0]!r}: an endpoint like tcp/127.0.0.1:7500")
    procs: list[subprocess.Popen[str]] = []
    names = [f"r{i + 1}" for i in range(n)]
    results: list[dict[str, Any]] = [{} for _ in range(n)]
    observer = _Observer()
    fleet_maps = FleetMaps("fleet")
    audit = Audit("fleet")
    stop = threading.Event()
    t0 = time.monotonic()
    import zenoh

    session: Any = None
    try:
        for i, name in enumerate(names):
            d = out_dir / name
            d.mkdir(exist_ok=True)
            sx = start[0] + i * args.spacing * math.cos(start[2])
            sy = start[1] + i * args.spacing * math.sin(start[2])
            gx, gy, _ = goals[i]
            # Facing its goal: the robot maps the way there from the start (a goal outside the map so far
            # is refused).
            s = (sx, sy, math.atan2(gy - sy, gx - sx) if (gx, gy) != (sx, sy) else start[2])
            (d / "world.toml").write_text(
                _world_text(world_file.read_text(encoding="utf-8"), s), encoding="utf-8"
            )
            config = re.sub(r"(?m)^world\s*=.*$", f'world = "{d / "world.toml"}"', config_text, count=1)
            (d / "robot.toml").write_text(
                config + f'\n[fleet]\nsocket = "{d / "fleet.sock"}"\n', encoding="utf-8"
            )
            endpoints = ", ".join(json.dumps(e) for e in [*(f"tcp/127.0.0.1:{p}" for p in ports[:i]), *extra])
            (d / "bridge.toml").write_text(
                f'[bridge]\nrobot = "{name}"\nsocket = "{d / "fleet.sock"}"\n[zenoh]\nmode = "peer"\n'
                f'listen = ["tcp/127.0.0.1:{ports[i]}"]\nconnect = [{endpoints}]\n'
                + ("[ros2]\nenabled = true\n" if args.fleet_ros2 else ""),
                encoding="utf-8",
            )
            sim = ["sim", "--config", str(d / "robot.toml"), "--seconds", str(args.seconds), "--json"]
            sim += ["--out", str(d), "--truth", str(d / "truth.csv"), "--seed", str(seed + i)]
            for argv in (sim, ["bridge", "--config", str(d / "bridge.toml"), "--json"]):
                procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "agent.cli", *argv],
                        stdout=subprocess.PIPE,
                        stderr=subprocess.DEVNULL,
                        stdin=subprocess.DEVNULL,
                        text=True,
                        start_new_session=True,
                    )
                )
        zc = ZenohConfig("peer", (), tuple(f"tcp/127.0.0.1:{p}" for p in ports), False)
        session = zenoh.open(zc.zenoh_config())
        session.declare_subscriber("fleet/*/pose", observer)
        fleet_maps.subscribe(session)
        session.declare_subscriber("**", audit)
        sender = GoalSender(zc)
        deadline = t0 + args.seconds
        threads = []
        for i, name in enumerate(names):
            x, y, yaw = goals[i]
            message = GoalMessage(
                0, 1000 + i, x, y, math.nan if yaw is None else yaw, GoalMessage.ALLOW_UNKNOWN
            )
            t = threading.Thread(
                target=_drive, args=(sender, name, message, deadline, results[i], stop), daemon=True
            )
            t.start()
            threads.append(t)
        for t in threads:
            t.join(max(deadline - time.monotonic(), 0.0) + 5.0)
    finally:
        stop.set()
        for proc in procs:  # all at once: each simulator takes a while to write its files and summary
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        outputs = [_stop(p) for p in procs]
        if session is not None:
            session.close()
    elapsed = time.monotonic() - t0
    summaries = []
    for i in range(n):
        try:
            summaries.append(json.loads(outputs[2 * i]))
        except (json.JSONDecodeError, IndexError):
            summaries.append({})
    truths = []
    for name in names:
        path = out_dir / name / "truth.csv"
        data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2) if path.is_file() else np.zeros((0, 6))
        truths.append(data)
    collisions, closest = 0, math.inf
    for a in range(n):
        for b in range(a + 1, n):
            ta, tb = truths[a], truths[b]
            if len(ta) < 2 or len(tb) < 2:
                continue
            _, dist = separation(ta[:, 1], ta[:, 2:4], tb[:, 1], tb[:, 2:4])
            if dist.size:
                collisions += contacts(dist, 2 * radius)
                closest = min(closest, float(dist.min()))
    ages = np.asarray(observer.ages_ms)
    robots = []
    keys = (
        "seconds",
        "distance_m",
        "pose_error_cm_mean",
        "pose_error_cm_p95",
        "pose_error_cm_max",
        "within_2cm",
        "collisions_walls",
        "collisions_people",
    )
    for i, name in enumerate(names):
        robots.append({"robot": name, "goal": results[i], **{k: summaries[i].get(k) for k in keys}})
    summary = {
        "robots": robots,
        "collisions": collisions,
        "min_separation_m": None if math.isinf(closest) else round(closest, 3),
        "footprint_radius_m": radius,
        "fleet_pose_latency_ms_p95": round(float(np.percentile(ages, 95)), 3) if ages.size else None,
        "fleet_pose_latency_ms_p50": round(float(np.percentile(ages, 50)), 3) if ages.size else None,
        "poses_heard": int(ages.size),
        "robots_heard": sorted(observer.robots),
        "maps": _maps_summary(fleet_maps, out_dir / "merged.png"),
        "privacy": audit.summary(),
        "seconds": round(elapsed, 3),
    }
    if args.json:
        print(dumps_json(summary, sort_keys=True))
    else:
        for r in robots:
            g = r["goal"]
            error = r["pose_error_cm_p95"]
            print(f"{r['robot']}: goal {g.get('state')} ({g.get('reason')}), pose error p95 {error} cm")
        print(
            f"collisions {collisions}, closest {summary['min_separation_m']} m, fleet pose latency p95 "
            f"{summary['fleet_pose_latency_ms_p95']} ms"
        )
    reached = all(r["goal"].get("state") == "reached" for r in robots)
    return 0 if reached and collisions == 0 else 1
