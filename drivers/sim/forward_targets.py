"""A calibration board held in front of the simulated forward camera, in its room.

The forward camera (``drivers/sim/forward_render.py``, ``[forward_camera]`` in docs/world.md) is a level
pinhole camera without distortion, focal length f = (width / 2) / tan(hfov / 2), principal point (cx, cy).
A board in front of it is drawn by the same target renderer as the ceiling camera's boards
(``drivers/sim/targets.py``: exact print raster, lens blur and pixel box, shot and read noise), through a
:class:`~drivers.sim.world.CameraModel` with that pinhole geometry at full resolution (sensor = output, no
resize), and laid over the room the forward renderer draws from the robot's pose (walls, floor, ceiling; the
light gain of the moment applied to the board as to the room). The sheet's outline, projected, is the mask
(anti-aliased); outside it the room shows, so the detector sees the board against a real background.

Frames: a pose (R, t) maps board points into OpenCV's camera frame (x along image u, y along v, z along the
optical axis): p_camera = R p_board + t, as :class:`~drivers.sim.targets.TargetRenderer` has it. The forward
renderer's u = cx - f Y / X, v = cy - f (Z - z_mount) / X (X ahead, Y left, Z up) is the same camera:
x_cv = -Y, y_cv = -(Z - z_mount), z_cv = X.
"""

from __future__ import annotations

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.forward_render import ForwardRenderer
from drivers.sim.render import OutputIntrinsics
from drivers.sim.targets import RenderedTarget, Target, TargetLighting, TargetRenderer
from drivers.sim.world import CameraModel, ForwardCameraModel, Pose2D

__all__ = ["ForwardTargetRenderer", "pinhole_camera"]

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

# Any pixel pitch: only the focal length in pixels matters (f_m = f_px * pitch).
_PIXEL_M = 1e-6


def pinhole_camera(model: ForwardCameraModel) -> CameraModel:
    """The forward camera as the target renderer's camera: its pinhole geometry at full resolution, no
    distortion, read noise ``noise_dn``."""
    cx, cy = model.principal_point_px
    return CameraModel(
        sensor_width_px=model.width_px,
        sensor_height_px=model.height_px,
        pixel_size_m=_PIXEL_M,
        focal_length_m=model.focal_length_px * _PIXEL_M,
        cx_px=cx,
        cy_px=cy,
        output_width_px=model.width_px,
        output_height_px=model.height_px,
        frame_rate_hz=model.frame_rate_hz,
        read_noise_dn=model.noise_dn,
    )


class ForwardTargetRenderer:
    """Views of one board held in front of the forward camera of a robot standing at ``base`` among
    ``walls`` (the world's, ``drivers.sim.raycast.walls_array``). ``seed`` seeds both noises. Each view is
    one frame later than the last (the room's light gain moves on)."""

    def __init__(
        self,
        model: ForwardCameraModel,
        target: Target,
        walls: FloatArray,
        base: Pose2D,
        lighting: TargetLighting | None = None,
        *,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.target = target
        self.base = base
        self.camera = pinhole_camera(model)
        self._board = TargetRenderer(self.camera, target, lighting, seed=seed)
        self._room = ForwardRenderer(model, walls, seed=seed + 1)
        self._frame = 0
        width, height = target.size_m
        self._sheet = np.array([[0.0, 0.0, 0.0], [width, 0.0, 0.0], [width, height, 0.0], [0.0, height, 0.0]])

    @property
    def output_intrinsics(self) -> OutputIntrinsics:
        """The true intrinsics (what a perfect calibration finds): the forward camera's f, f, cx, cy."""
        return self._board.output_intrinsics

    @property
    def distortion(self) -> tuple[float, float, float, float, float]:
        return self.camera.distortion

    def project(
        self, points_board: FloatArray, rotation: FloatArray, translation_m: FloatArray
    ) -> FloatArray:
        """Pixel positions of board points (N, 3) seen with the pose (R, t)."""
        return self._board.project(points_board, rotation, translation_m)

    def render(self, rotation: FloatArray, translation_m: FloatArray) -> RenderedTarget:
        """The BGR8 frame with the board at pose (R, t) in front of the room; the truth as the target
        renderer gives it."""
        t_s = self._frame / self.model.frame_rate_hz
        self._frame += 1
        room, _ = self._room.render(self.base, [], t_s)
        view = self._board.render(rotation, translation_m)
        rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        t = np.asarray(translation_m, dtype=np.float64).reshape(3)
        depth = (self._sheet @ rot.T + t)[:, 2]
        if np.any(depth <= 1e-3):
            # The sheet reaches behind the lens: its outline does not project; the board covers the frame.
            alpha = np.ones(room.shape[:2], dtype=np.float32)
        else:
            outline = self.project(self._sheet, rot, t)
            mask = np.zeros(room.shape[:2], dtype=np.uint8)
            points = np.round(np.clip(outline, -1e5, 1e5) * 16).astype(np.int32)
            cv2.fillPoly(mask, [points], 255, lineType=cv2.LINE_AA, shift=4)
            alpha = mask.astype(np.float32) / 255.0
        gain = self._room.light_gain(t_s)
        board = view.image.astype(np.float32) * gain
        a = alpha[:, :, None]
        image: ImageU8 = np.clip(
            np.rint(room.astype(np.float32) * (1.0 - a) + board[:, :, None] * a), 0, 255
        ).astype(np.uint8)
        return RenderedTarget(image, view.corners_px, view.corners_visible, rot, t, view.front_facing)
