"""Wiring an agent from a config (:func:`create_agent`); re-exported by :mod:`agent.runtime`."""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

from agent.config import AgentConfig, SlamMode
from agent.runtime.agent import Agent, laser_mount_for
from agent.runtime.devices import Devices, build_devices
from agent.runtime.health import NotifierLike
from agent.runtime.localizer import FrameLocalizer, make_localizer
from agent.runtime.map_saver import MapSaver
from agent.runtime.mapper import RbpfMapper
from agent.runtime.output import PoseOutput, Written
from agent.runtime.recorder import Recorder
from agent.runtime.slam_factory import make_mapper

__all__ = ["create_agent"]

log = logging.getLogger(__name__)


def create_agent(
    config: AgentConfig,
    *,
    robot: Any | None = None,
    notifier: NotifierLike | None = None,
    output_url: str | None = None,
    observer: Callable[[Written], None] | None = None,
    devices: Devices | None = None,
    map_dir: Path | None = None,
) -> Agent:
    """An agent for ``config``, not started.

    ``robot``: the started ``SimulatedRobot`` under ``[sim]``. ``output_url``: where the pose stream goes
    (default: the config's ``output.url``; the sim command passes the pty it made for ``"pty"``).
    ``observer``: called with every frame written (the simulator measures its error against the truth).
    ``devices``: injected devices (tests); default: built from the config.
    ``map_dir``: where the map is saved as the robot goes (``slam.save_interval_s``, on request); None:
    nowhere (only the caller's save at the end, if any). Not used when localizing on a saved map.
    """
    world = config.sim.world if config.sim is not None else None
    if devices is None:
        devices = build_devices(config, robot)
    unavailable: dict[str, str] = {}
    localizer: FrameLocalizer | None = None
    if devices.camera is not None:
        size = None
        settings = config.devices[_camera_kind()].options.get("settings")
        if settings is not None and settings.width and settings.height:
            size = (settings.width, settings.height)
        elif world is not None:
            size = (world.camera.output_width_px, world.camera.output_height_px)
        localizer, why = make_localizer(config.vlp, world, size)
        if localizer is None:
            unavailable["vlp"] = why
            log.warning("running without VLP: %s", why)
    url = output_url if output_url is not None else config.output.url
    output = None
    if url is not None and url != "pty":
        output = PoseOutput(config.output, url, observer=observer)
    initial = None
    if world is not None:
        initial = (world.robot.start.x_m, world.robot.start.y_m, world.robot.start.yaw_rad)
    recorder = None
    if config.record.path is not None:
        recorder = Recorder(config.record.path, int(config.record.max_mb * 1e6))
    flight_recorder = None
    if config.recorder.path is not None:
        from agent.recording.writer import McapRecorder

        flight_recorder = McapRecorder(config.recorder)
    agent = Agent(
        config,
        devices,
        localizer=localizer,
        output=output,
        notifier=notifier,
        initial_pose=initial,
        unavailable=unavailable,
        recorder=recorder,
        flight_recorder=flight_recorder,
    )
    if devices.laser is not None:
        mount = laser_mount_for(config, world)
        mapper, why = make_mapper(config.slam, mount, agent.slam_start_pose)
        if mapper is not None and flight_recorder is not None:
            from agent.recording.slam_replay import slam_setup

            # How the mapper was built, so that a replay builds the same one (agent.recording.slam_replay).
            setup = slam_setup(config.slam, mount, mapper.name)
            flight_recorder.record("slam_setup", agent.clock_ns(), setup)
        if mapper is None:
            unavailable["slam"] = why
            agent.unavailable["slam"] = why
            log.warning("running without SLAM: %s", why)
        if isinstance(mapper, RbpfMapper):
            mapper.give_way = agent.hot_path.give_way
        agent.mapper = mapper
        if mapper is not None and map_dir is not None and config.slam.mode is not SlamMode.LOCALIZATION:
            agent.map_saver = MapSaver(
                map_dir, config.slam.save_interval_s, comment=f"vlp-agent {mapper.name}"
            )
            from agent.runtime.slam_worker import ProcessMapper

            if isinstance(mapper, ProcessMapper):
                # A SLAM process that dies is replaced by one that continues the last saved map.
                mapper.resume_map = agent.map_saver.last_saved
        # Missions (explore, go to a named place) ride on the navigation.
        if config.navigation.enabled and agent.enable_navigation(laser_mount_for(config, world)):
            agent.enable_missions()
    return agent


def _camera_kind() -> Any:
    from drivers.registry import DeviceKind

    return DeviceKind.CAMERA
