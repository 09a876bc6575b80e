"""The simulated robot as the calibration steps see it.

* :class:`BoardHelper`: a person holding the board in front of a simulated camera (the ceiling camera's,
  :func:`target_renderer`, or the forward camera's in its room, :func:`forward_target_renderer`). It
  follows the step's guidance (the emptiest image cell, more tilt, closer), looks at the screen (it keeps
  the whole sheet in the picture, as a person watching the live view does) and holds each pose still for
  one frame.
* :func:`as_built`: the robot as built rather than as drawn. A world file gives the design (wheel radius,
  track, where the laser and camera sit); a real robot differs from it by a worn tyre, a bracket a degree off.
  Each step's simulated robot is built with such deviations (seeded) in what that step measures, so the
  calibration has something to find, and the report compares the estimate with the truth.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Protocol

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.forward_targets import ForwardTargetRenderer
from drivers.sim.raycast import cast_rays, walls_array
from drivers.sim.render import OutputIntrinsics
from drivers.sim.targets import RenderedTarget, Target, TargetLighting, TargetRenderer
from drivers.sim.world import CameraModel, Mount, Pose2D, World

__all__ = [
    "AsBuilt",
    "BoardCamera",
    "BoardHelper",
    "as_built",
    "corner_viewpoint",
    "forward_target_renderer",
    "target_renderer",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]


def target_renderer(camera: CameraModel, target: Target, seed: int = 0) -> TargetRenderer:
    """The simulated camera looking at a board, lit for calibration (a long exposure, not the LED one)."""
    return TargetRenderer(camera, target, TargetLighting(), seed=seed)


def forward_target_renderer(world: World, target: Target, seed: int = 0) -> ForwardTargetRenderer:
    """The simulated forward camera (the world's ``[forward_camera]``) looking at a board held in front of
    it, the robot at its start pose in the world's room."""
    return ForwardTargetRenderer(
        world.forward_camera, target, walls_array(world.walls), world.robot.start, seed=seed
    )


class BoardCamera(Protocol):
    """A simulated camera a board is shown to: the ceiling camera's :class:`TargetRenderer` or the forward
    camera's :class:`ForwardTargetRenderer`."""

    @property
    def target(self) -> Target: ...

    @property
    def output_intrinsics(self) -> OutputIntrinsics: ...

    def project(
        self, points_board: FloatArray, rotation: FloatArray, translation_m: FloatArray
    ) -> FloatArray: ...

    def render(self, rotation: FloatArray, translation_m: FloatArray) -> RenderedTarget: ...


def rotation_from_axis_angle(axis: FloatArray, angle_rad: float) -> FloatArray:
    rot, _ = cv2.Rodrigues(
        np.asarray(axis, dtype=np.float64) / max(float(np.linalg.norm(axis)), 1e-12) * angle_rad
    )
    return np.asarray(rot, dtype=np.float64)


class BoardHelper:
    """Holds the board where the guidance asks (image cell, tilt, distance), with a person's variety."""

    def __init__(self, renderer: BoardCamera, seed: int = 0, margin_px: float = 6.0) -> None:
        self.renderer = renderer
        self.rng = np.random.default_rng(seed + 7919)
        self.margin_px = margin_px
        intr = renderer.output_intrinsics
        # What the helper knows of the camera: roughly where it points and how wide it sees.
        self.width, self.height = intr.width_px, intr.height_px
        self.f_px = intr.fx_px
        self.sheet_w, self.sheet_h = renderer.target.size_m
        self._outline = np.array(
            [
                [0.0, 0.0, 0.0],
                [self.sheet_w, 0.0, 0.0],
                [self.sheet_w, self.sheet_h, 0.0],
                [0.0, self.sheet_h, 0.0],
            ]
        )
        self.poses: list[tuple[FloatArray, FloatArray]] = []

    def _in_picture(self, rot: FloatArray, t: FloatArray) -> bool:
        depth = (self._outline @ rot.T + t)[:, 2]
        if np.any(depth < 0.05):
            return False
        uv = self.renderer.project(self._outline, rot, t)
        m = self.margin_px
        return bool(
            np.all(uv[:, 0] >= m)
            and np.all(uv[:, 0] <= self.width - 1 - m)
            and np.all(uv[:, 1] >= m)
            and np.all(uv[:, 1] <= self.height - 1 - m)
        )

    def pose(self, cell: tuple[int, int], tilt_more: bool, closer: bool) -> tuple[FloatArray, FloatArray]:
        """A pose putting the sheet's centre in ``cell`` (3 x 3 split), tilted and turned as people do."""
        rng = self.rng
        for attempt in range(40):
            # Aim at the cell's centre, pulled towards the image centre after failed attempts.
            pull = min(attempt / 20.0, 0.8)
            u = ((cell[0] + 0.5) / 3.0 + rng.uniform(-0.1, 0.1)) * self.width
            v = ((cell[1] + 0.5) / 3.0 + rng.uniform(-0.1, 0.1)) * self.height
            u = u + pull * (self.width / 2 - u)
            v = v + pull * (self.height / 2 - v)
            fill = rng.uniform(0.45, 0.7) if closer else rng.uniform(0.3, 0.6)
            fill *= 1.0 - 0.5 * pull
            z = self.f_px * self.sheet_w / (fill * self.width)
            tilt = math.radians(rng.uniform(30.0, 55.0) if tilt_more else rng.uniform(10.0, 50.0))
            axis_angle = rng.uniform(0.0, 2.0 * math.pi)
            spin = rng.uniform(-0.4, 0.4)
            rot = rotation_from_axis_angle(np.array([math.cos(axis_angle), math.sin(axis_angle), 0.0]), tilt)
            rot = rot @ rotation_from_axis_angle(np.array([0.0, 0.0, 1.0]), spin)
            centre = np.array(
                [(u - self.width / 2) / self.f_px * z, (v - self.height / 2) / self.f_px * z, z]
            )
            t = centre - rot @ np.array([self.sheet_w / 2, self.sheet_h / 2, 0.0])
            if self._in_picture(rot, t):
                return rot, t
        # Straight on, in the middle: always in the picture.
        rot = np.eye(3)
        z = self.f_px * self.sheet_w / (0.5 * self.width)
        return rot, np.array([-self.sheet_w / 2, -self.sheet_h / 2, z])

    def source(self, max_images: int) -> HeldBoard:
        return HeldBoard(self, max_images)


class HeldBoard:
    """A view source: the helper moves the board by the guidance, the simulated camera takes a frame."""

    live = False

    def __init__(self, helper: BoardHelper, max_images: int) -> None:
        self.helper = helper
        self.max_images = max_images

    def images(self, guidance: Callable[[], object]) -> Iterator[tuple[ImageU8, str]]:
        for n in range(self.max_images):
            g = guidance()
            cell = getattr(g, "cell", (1, 1))
            rot, t = self.helper.pose(
                cell, bool(getattr(g, "tilt_more", False)), bool(getattr(g, "closer", False))
            )
            self.helper.poses.append((rot, t))
            yield self.helper.renderer.render(rot, t).image, f"sim view {n + 1}"


# -- the robot as built -----------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class AsBuilt:
    """How the built robot differs from its design (the world file)."""

    wheel_radius_scale: float
    track_scale: float
    laser_yaw_rad: float
    laser_offset_m: tuple[float, float]
    camera_yaw_rad: float
    camera_offset_m: tuple[float, float]


def as_built(world: World, seed: int = 0) -> tuple[World, AsBuilt]:
    """The world with its robot built with realistic deviations from the design: wheel radius within
    +-1.5 % (tyre wear, load), track within +-2 %, laser yaw within +-2 deg and its place within +-1.5 cm,
    camera yaw within +-3 deg and its place within +-1 cm. The IMU is fixed on the camera's bracket (same
    orientation), so its tilt at rest is the camera's."""
    rng = np.random.default_rng(seed + 104729)

    def spread(limit: float) -> float:
        # At least a third of the limit, so there is always something to find.
        return float(rng.uniform(limit / 3.0, limit) * rng.choice([-1.0, 1.0]))

    dev = AsBuilt(
        1.0 + spread(0.015),
        1.0 + spread(0.02),
        math.radians(spread(2.0)),
        (spread(0.015), spread(0.015)),
        math.radians(spread(3.0)),
        (spread(0.01), spread(0.01)),
    )
    robot = world.robot
    lm, cm = robot.laser_mount, robot.camera_mount
    laser = dataclasses.replace(
        lm,
        x_m=lm.x_m + dev.laser_offset_m[0],
        y_m=lm.y_m + dev.laser_offset_m[1],
        yaw_rad=lm.yaw_rad + dev.laser_yaw_rad,
    )
    camera = dataclasses.replace(
        cm,
        x_m=cm.x_m + dev.camera_offset_m[0],
        y_m=cm.y_m + dev.camera_offset_m[1],
        yaw_rad=cm.yaw_rad + dev.camera_yaw_rad,
    )
    tilt = world.errors.camera_tilt_rad
    imu = Mount(
        camera.x_m,
        camera.y_m,
        camera.z_m,
        camera.yaw_rad,
        camera.roll_rad + tilt[0],
        camera.pitch_rad + tilt[1],
    )
    built = dataclasses.replace(
        robot,
        wheel_radius_m=robot.wheel_radius_m * dev.wheel_radius_scale,
        track_m=robot.track_m * dev.track_scale,
        laser_mount=laser,
        camera_mount=camera,
        imu_mount=imu,
    )
    return dataclasses.replace(world, robot=built), dev


def with_start(world: World, start: Pose2D) -> World:
    return dataclasses.replace(world, robot=dataclasses.replace(world.robot, start=start))


def corner_viewpoint(world: World, distance_m: float = 1.3) -> Pose2D:
    """Where to put the robot to face a room corner from ``distance_m``: the corner (two walls meeting at
    60-120 degrees) nearest the robot's start whose bisector leads into free space with the corner in plain
    sight. Raises ValueError when the world has none."""
    segments = walls_array(world.walls)
    ends: list[tuple[FloatArray, FloatArray, FloatArray]] = []  # corner, direction of wall a, of wall b
    for i, a in enumerate(world.walls):
        for b in world.walls[i + 1 :]:
            pa = [np.array([a.x1_m, a.y1_m]), np.array([a.x2_m, a.y2_m])]
            pb = [np.array([b.x1_m, b.y1_m]), np.array([b.x2_m, b.y2_m])]
            for ia in (0, 1):
                for ib in (0, 1):
                    if np.linalg.norm(pa[ia] - pb[ib]) < 1e-3:
                        da, db = pa[1 - ia] - pa[ia], pb[1 - ib] - pb[ib]
                        if min(np.linalg.norm(da), np.linalg.norm(db)) < 0.8:
                            continue
                        ends.append((pa[ia], da / np.linalg.norm(da), db / np.linalg.norm(db)))
    start = np.array([world.robot.start.x_m, world.robot.start.y_m])
    best: tuple[float, Pose2D] | None = None
    for corner, da, db in ends:
        angle = math.degrees(math.acos(float(np.clip(da @ db, -1.0, 1.0))))
        if not 60.0 <= angle <= 120.0:
            continue
        bisector = (da + db) / np.linalg.norm(da + db)
        spot = corner + distance_m * bisector
        heading = math.atan2(-bisector[1], -bisector[0])
        # The corner must be the first thing straight ahead, and the robot must have room around it.
        ahead = cast_rays((float(spot[0]), float(spot[1])), np.array([heading]), segments, None, 10.0)[0]
        around = cast_rays(
            (float(spot[0]), float(spot[1])),
            np.linspace(0, 2 * math.pi, 24, endpoint=False),
            segments,
            None,
            10.0,
        )
        if abs(ahead - distance_m) > 0.02 or float(around.min()) < world.robot.radius_m + 0.2:
            continue
        score = float(np.linalg.norm(spot - start))
        if best is None or score < best[0]:
            best = (score, Pose2D(float(spot[0]), float(spot[1]), heading))
    if best is None:
        raise ValueError("the world has no room corner the robot can face from there")
    return best[1]
