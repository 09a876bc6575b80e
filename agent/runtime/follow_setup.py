"""Person following wired on a running agent, the same for ``vlp-agent run --follow`` (the robot's own
devices) and ``vlp-agent sim --follow`` (the simulated robot): ``docs/following.md``, "Following in the
agent".

* :func:`forward_view`: the forward camera's geometry from ``[camera.forward]`` (its mount and lens keys,
  ``agent.config.ForwardViewConfig``), so that the fine layer's image columns become the right bearings on
  the robot; under ``[sim]`` the world's camera (:func:`camera_view`).
* :func:`make_follow_loop`: the follow loop on the agent: its fused pose (and the pose at a scan's or a
  frame's time), the RFID coarse layer, the navigation's costmap and collision monitor; commands as a local
  mission's velocity (``Agent.command_velocity``). With a view, the fine layer runs on the forward camera's
  frames.
* :func:`start_following`: the loop's threads (the command every 50 ms; the camera's frames through the
  fine layer).
"""

from __future__ import annotations

import contextlib
import math
import threading
from typing import Any

from agent.config import AgentConfig, ForwardViewConfig
from agent.following.fine import FineLayer
from agent.following.follower import Follower, FollowerConfig
from agent.following.person import PersonTracker, TrackerConfig
from agent.following.prelocate import HeadShoulderLocator
from agent.runtime.follow_loop import CameraView, FollowLoop, ProjectedLocator
from drivers.errors import ConfigError
from firmware_protocol.pose_frame import PoseFlags

__all__ = ["camera_view", "forward_view", "make_follow_loop", "start_following"]

DEFAULT_SIZE = (640, 480)  # the frames' size when the config gives none (the first frame rescales it)


def forward_view(view: ForwardViewConfig, file: str = "<config>") -> CameraView:
    """The follow loop's :class:`CameraView` of ``[camera.forward]``'s keys. ConfigError when the lens is
    not given: without it a column is no bearing."""
    if not view.lens_given:
        raise ConfigError(
            "camera.forward.hfov_deg",
            "missing: following with the forward camera needs its lens (camera_info = the file `vlp-agent "
            "calibrate forward-camera` wrote, or hfov_deg, or fx_px with cx_px, cy_px, width and height) "
            "and its [camera.forward.mount]",
            file,
        )
    width, height = view.width_px or DEFAULT_SIZE[0], view.height_px or DEFAULT_SIZE[1]
    hfov = view.hfov_rad
    if hfov is None:
        assert view.fx_px is not None
        hfov = 2.0 * math.atan((width / 2.0) / view.fx_px)
    cx = (width - 1) / 2.0 if view.cx_px is None else view.cx_px
    cy = (height - 1) / 2.0 if view.cy_px is None else view.cy_px
    m = view.mount
    return CameraView(
        width,
        height,
        hfov,
        cx,
        cy,
        (m.x_m, m.y_m, m.z_m, m.yaw_rad),
        view.fy_px,
        m.pitch_rad,
        view.distortion,
    )


def camera_view(model: Any) -> CameraView:
    """The follow loop's view of the simulated forward camera (``drivers.sim.world.ForwardCameraModel``: a
    level camera)."""
    cx, cy = model.principal_point_px
    m = model.mount
    return CameraView(
        model.width_px, model.height_px, model.hfov_rad, cx, cy, (m.x_m, m.y_m, m.z_m, m.yaw_rad)
    )


def make_follow_loop(
    agent: Any,
    config: AgentConfig,
    laser_mount: tuple[float, float, float],
    view: CameraView | None = None,
) -> FollowLoop:
    """The follow loop on ``agent`` (an ``agent.runtime.agent.Agent``); registers its scan listener (before
    ``agent.start()``). With ``view`` the fine layer runs on the forward camera's frames
    (:func:`start_following`): OpenCV's HOG people detector in the track's band, the track's projection when
    it finds nobody, mean shift from there."""
    f = config.following
    follower = Follower(
        FollowerConfig(
            distance_m=f.distance_m,
            min_gap_m=f.min_gap_m,
            max_speed_mps=f.max_speed_mps,
            search_after_s=f.search_after_s,
        )
    )
    tracker = PersonTracker(TrackerConfig(lost_after_s=f.lost_after_s))
    sources = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY

    def pose() -> tuple[float, float, float] | None:
        estimate, flags = agent.pose()
        if not flags & sources:
            return None
        return (estimate.x_m, estimate.y_m, estimate.yaw_rad)

    def pose_at(t_s: float) -> tuple[float, float, float] | None:
        if not agent.flags() & sources:
            return None
        e = agent.fusion.estimate_at(round(t_s * 1e9))
        return (e.x_m, e.y_m, e.yaw_rad)

    def navigator() -> Any:
        return agent.navigation.navigator if agent.navigation is not None else None

    fine = locator = None
    if view is not None:
        locator = ProjectedLocator(view, HeadShoulderLocator())
        fine = FineLayer(locator)
    loop = FollowLoop(
        follower,
        tracker,
        laser_mount,
        pose,
        lambda: agent.coarse,
        agent.command_velocity,
        lambda: agent.clock_ns() * 1e-9,
        guard=agent.navigation.guard if agent.navigation is not None else None,
        pose_at=pose_at,
        pose_epoch=lambda: int(agent.fusion.reset_counter),
        navigator=navigator,
        fine=fine,
        locator=locator,
    )
    agent.scan_listeners.append(loop.on_scan)
    return loop


def start_following(
    agent: Any, loop: FollowLoop, stop: threading.Event, stack: contextlib.ExitStack
) -> list[threading.Thread]:
    """Start the loop's threads (after ``agent.start()``): its command steps, and with a fine layer the
    forward camera's newest frames through it; each joined by ``stack`` at its close (set ``stop`` first).
    The loop sends zero speed when it ends."""
    threads = [threading.Thread(target=loop.run, args=(stop,), name="follow", daemon=True)]
    if loop.fine is not None:
        threads.append(
            threading.Thread(
                target=loop.run_camera,
                args=(agent.forward_frames.take, stop),
                name="follow-fine",
                daemon=True,
            )
        )
    for thread in threads:
        thread.start()
        stack.callback(thread.join, 1.0)
    return threads
