"""``vlp-agent run --config FILE``: the agent process, as the systemd service starts it.

Loads and checks the robot's config, brings the devices up (each loop keeps retrying one that is not
there), tells systemd READY=1 once they are up and WATCHDOG=1 while every critical loop is alive, and runs
until SIGTERM or SIGINT, then stops the wheels, closes the devices and exits 0 within about two seconds.
While mapping, the map is saved every ``slam.save_interval_s`` and on SIGUSR1 (docs/slam.md, "Maps as
the robot goes"), and once more at the end.
A device that is missing is retried and reported (``ready without ...``, and while no position source is
live ``STATUS=NOT LOCALIZING: ...`` and a journal warning every ``health.not_localizing_log_s``), but the
watchdog is still fed: a restart plugs in no camera (docs/operations.md).
A config with ``[sim]`` runs the same process on the simulated robot (nothing commands the wheels then:
`vlp-agent sim` is the one that drives the route); there ``output.url = "pty"`` means what it means for
`vlp-agent sim`: a pseudo-terminal that a simulated controller (a child process) makes and reads as a
controller would.
Following is set up whenever it can be (a laser; ``agent.runtime.follow_setup``: the same follow loop as
``vlp-agent sim --follow``; the forward camera's mount and lens from ``[camera.forward]``) and the controller
starts and stops it with follow frames (``agent.runtime.follow_control``; docs/following.md, "Following on
command"); with ``--follow`` the robot follows its tagged user from the start too, as if commanded (follow
id 0). The final status adds ``follow`` (the loop) and ``follow_control`` (the commands).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from agent.commands.args import UsageError, dumps_json, positive_seconds
from agent.config import AgentConfig, SlamMode, load_config
from agent.runtime import create_agent
from agent.runtime.follow_loop import follow_summary
from agent.runtime.map_saver import save_topology_beside
from agent.runtime.mapper import save_final_map, tidy_map_folder
from agent.runtime.priority import SWITCH_INTERVAL_S
from agent.runtime.shutdown import AgentRequests, ShutdownRequest
from firmware_protocol.command_frame import GoalState

if TYPE_CHECKING:
    from agent.runtime.follow_loop import FollowLoop

log = logging.getLogger(__name__)


def add_parser(sub: Any, argv: Sequence[str] = ()) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "run",
        help="run the agent (the systemd service's entry point)",
        description="Run the agent on the robot described by the config file: devices, VLP, SLAM, fusion "
        "and the pose stream, until SIGTERM or SIGINT. Notifies systemd (READY, WATCHDOG, STATUS, STOPPING) "
        "when started by it. Keys: docs/config.md.",
    )
    p.add_argument("--config", required=True, metavar="FILE", help="the robot's config (TOML)")
    p.add_argument(
        "--seconds",
        type=positive_seconds,
        default=None,
        help="stop after this long, > 0 (default: run until stopped)",
    )
    p.add_argument("--json", action="store_true", help="print the final status as one JSON object on stdout")
    p.add_argument(
        "--follow",
        action="store_true",
        help="follow the tagged person ([following] tag_id) from the start, as if the controller had sent a "
        "follow start (follow id 0): the laser person tracker seeded by the RFID layer, refined by the "
        "forward camera's fine layer ([camera.forward] with its mount and lens keys), the follower keeping "
        "[following] distance_m behind them through the navigation's collision checks; a controller's goal, "
        "velocity, stop, cancel or follow stop ends it (docs/following.md). Without --follow the robot "
        "follows only when the controller sends a follow start",
    )
    p.add_argument(
        "--follow-fine",
        choices=("on", "off"),
        default="on",
        help="with --follow and [camera.forward]: run the fine layer on the forward camera (on, the "
        "default) or follow on the laser and RFID only (off)",
    )


def map_directory(config: AgentConfig) -> Path | None:
    """Where the map is saved at the end: ``slam.map_dir``, else systemd's state directory (``maps/`` in the
    first path of ``$STATE_DIRECTORY``), else nowhere."""
    if config.slam.map_dir is not None:
        return config.slam.map_dir
    state = os.environ.get("STATE_DIRECTORY")
    if state:
        return Path(state.split(":")[0]) / "maps"
    return None


def _notifier() -> Any:
    try:
        from agent.sdnotify import Notifier
    except ImportError:  # not installed with this checkout: run without systemd notifications
        return None
    return Notifier.from_environ(unset_environment=True)


def _follow_loop(args: argparse.Namespace, config: AgentConfig, agent: Any) -> FollowLoop:
    """The follow loop for ``--follow``: the same loop as ``vlp-agent sim --follow``, on this robot's devices;
    the forward camera's view from ``[camera.forward]``'s mount and lens (under ``[sim]``, the world's)."""
    from agent.runtime.agent import laser_mount_for
    from agent.runtime.follow_setup import camera_view, forward_view, make_follow_loop
    from drivers.registry import DeviceKind

    if DeviceKind.LASER not in config.devices:
        raise UsageError("following needs the laser ([laser]): it finds and tracks the person")
    world = config.sim.world if config.sim is not None else None
    view = None
    if config.forward_camera is not None and args.follow_fine == "on":
        if world is not None:
            view = camera_view(world.forward_camera)
        else:
            assert config.forward_view is not None
            view = forward_view(config.forward_view, config.file)
    m = laser_mount_for(config, world)
    loop = make_follow_loop(agent, config, (m.x_m, m.y_m, m.yaw_rad), view)
    log.info(
        "following set up (%s): it follows when commanded, or from the start with --follow",
        "laser, RFID and the forward camera" if view is not None else "laser and RFID, no camera",
    )
    return loop


def _follow_on_command(args: argparse.Namespace, config: AgentConfig, agent: Any) -> FollowLoop | None:
    """The follow loop, set up for following on command (and from the start with ``--follow``). Without
    ``--follow`` a robot that cannot follow (no laser, a forward camera without its lens) still runs: the
    follow commands are refused FOLLOW_UNAVAILABLE, with the reason in the log."""
    from drivers.errors import ConfigError

    wanted = getattr(args, "follow", False)
    try:
        loop = _follow_loop(args, config, agent)
    except (UsageError, ConfigError) as exc:
        if wanted or agent.arbiter is None:
            raise
        agent.enable_following(None, f"following is not set up: {exc}")
        log.info("following on command: unavailable (%s)", exc)
        return None
    if agent.enable_following(loop) is None and not wanted:
        # No command line to start it on: without --follow nothing would ever turn it on.
        agent.scan_listeners.remove(loop.on_scan)
        return None
    return loop


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    notifier = _notifier()
    with contextlib.ExitStack() as stack:
        shutdown = stack.enter_context(ShutdownRequest())
        # SIGUSR1: save the map now; SIGUSR2: a flight-recorder snapshot (dropped until the agent exists).
        requests = stack.enter_context(AgentRequests())
        robot = None
        from agent.commands.sim import give_way_to_agent, serve_pose_stream, simulated_robot

        if config.sim is not None:
            robot = stack.enter_context(simulated_robot(config.sim))

        url, controller = serve_pose_stream(stack, config)
        directory = map_directory(config)
        mapping = config.slam.mode is not SlamMode.LOCALIZATION
        if directory is not None and mapping:
            tidy_map_folder(directory)
        agent = create_agent(
            config, robot=robot, notifier=notifier, output_url=url, map_dir=directory if mapping else None
        )
        if agent.mapper is not None:
            # Last: the map is saved through it once the agent has stopped (a SLAM process ends here).
            stack.callback(agent.mapper.close)
        recorder = agent.flight_recorder
        requests.attach(agent.request_map_save, recorder.request_snapshot if recorder is not None else None)
        give_way_to_agent(agent, robot)
        follow = _follow_on_command(args, config, agent)
        agent.start()
        if follow is not None:
            from agent.runtime.follow_setup import start_following

            follow_stop = threading.Event()
            start_following(agent, follow, follow_stop, stack)
            stack.callback(follow_stop.set)  # first at the end: the threads then end and are joined
            control = agent.follow_control
            if getattr(args, "follow", False) and control is not None:
                answer = control.start_now()
                if answer.state is not GoalState.ACCEPTED:
                    raise UsageError(f"--follow: the agent refused to follow: {answer.reason.name}")
        agent.settle_heap()
        try:
            deadline = None if args.seconds is None else time.monotonic() + args.seconds
            while not shutdown.requested:
                if deadline is not None and time.monotonic() >= deadline:
                    break
                shutdown.wait(0.2 if deadline is None else max(0.0, min(0.2, deadline - time.monotonic())))
        finally:
            agent.stop(why=shutdown.why("an error" if sys.exc_info()[1] is not None else "--seconds ran out"))
            status = agent.status()
            map_files: list[str] = []
            map_optimised = False
            if agent.mapper is not None and directory is not None and mapping:
                # The filter's map, then the final optimisation and the map again (the first kept beside
                # it as map.prev.yaml): docs/slam.md, "Loop closure", *The final optimisation*.
                saved, map_optimised = save_final_map(agent.mapper, directory)
                map_files = [str(p) for p in saved]
                if map_files and agent.missions is not None:
                    map_files += save_topology_beside(directory / "map.yaml", agent.missions.topology)
            if controller is not None:
                controller.stop()
            if notifier is not None:
                notifier.close()
    summary = {
        "pose": {"x_m": status.estimate.x_m, "y_m": status.estimate.y_m, "yaw_rad": status.estimate.yaw_rad},
        "flags": [f.name for f in type(status.flags) if f & status.flags],
        "counts": status.counts,
        "drops": status.drops,
        "output": status.output,
        "devices": {
            k: {"ok": v.ok, "reason": v.reason, "failures": v.failures} for k, v in status.devices.items()
        },
        "unavailable": status.unavailable,
        "following": status.following,
        "follow": None if follow is None else follow_summary(follow),
        "follow_control": None if agent.follow_control is None else agent.follow_control.summary(),
        "frames_received": controller.frames if controller is not None else None,
        "map_files": map_files,
        "map_optimised": map_optimised,
    }
    summary["stop"] = shutdown.stop_times()  # from SIGTERM / SIGINT to here; None: none came
    if args.json:
        print(dumps_json(summary, sort_keys=True))
    else:
        print(f"vlp-agent run stopped: {agent.status_line()}")
    return 0
