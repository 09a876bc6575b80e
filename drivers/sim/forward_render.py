"""The forward colour camera of person following: one BGR8 frame of walls and people, with ground truth.

Pure numpy/OpenCV, no I/O. The model (``docs/world.md``, ``[forward_camera]``):

* **Geometry.** A level pinhole camera (focal length from the horizontal field of view, principal point
  ``cx, cy``) at the mount on the robot base. A point X ahead, Y to the left and Z up of the lens lands at
  u = cx - f Y / X, v = cy - f Z / X. Level means vertical edges stay vertical, so the scene is drawn the
  way ray-casting games draw it: one ray per image column against the walls (exact, since walls are
  vertical planes), runs of columns that hit one wall filled as one quadrilateral with ``cv2.fillPoly``.
* **Walls** are flat shaded: ``wall_rgb`` made a little lighter or darker per wall (so that the background
  is not uniform), times the Lambert factor of the wall's normal against a fixed light direction and a
  slight fall-off with distance. Floor and ceiling are vertical gradients drawn once.
* **People** are upright bodies facing the camera (billboards): legs (trousers; the gap between them
  follows the gait), torso and arms (shirt, with its texture: horizontal stripes or checks of
  ``pattern_period_m``), sloping shoulders, neck, head (skin, with hair on top; all hair seen from
  behind). They are drawn far to near (painter's algorithm), each only in the columns where no wall is
  nearer (the column depth buffer), so a door frame or a corner hides the right part of a body.
* **Light and sensor.** Everything is scaled by the lighting gain of the moment, then Gaussian noise of
  ``noise_dn`` is added (from a pool drawn once), with saturation.

Ground truth per frame (:class:`ForwardTruth`): for each person in front of the camera, their projected
box, the box of their pixels that are actually visible (after walls and nearer people) and the visible
share, for tracking evaluation (``eval follow``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt

from drivers.sim.world import Clothing, ForwardCameraModel, Person, Pose2D

__all__ = ["Box", "ForwardRenderer", "ForwardTruth", "PersonInView", "PersonState"]

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

_NEAR_M = 0.25  # nearer than this to the lens a body is not drawn (it would fill the frame)
_LIGHT_DIR = (math.cos(0.6), math.sin(0.6))  # the light's direction in the floor plane (world frame)
_NOISE_POOL = 4
_STRIDE_M = 1.4  # a gait cycle (two steps)


@dataclass(frozen=True, slots=True)
class Box:
    """A pixel box: left, top, width, height (OTB's x, y, w, h with 0-based pixels)."""

    x: int
    y: int
    w: int
    h: int

    @property
    def centre(self) -> tuple[float, float]:
        return self.x + self.w / 2.0, self.y + self.h / 2.0


@dataclass(frozen=True, slots=True)
class PersonState:
    """A person at the frame's time: where (world), which way they face, how far they have walked."""

    person: Person
    x_m: float
    y_m: float
    heading_rad: float
    walked_m: float


@dataclass(frozen=True, slots=True)
class PersonInView:
    """A person in front of the camera. ``box``: their whole projected body clipped to the image (None when
    it falls outside); ``visible_box``: the box of their pixels left visible (None when fully hidden);
    ``visible``: the share of the body's pixels in the image that are visible; ``distance_m``: depth along
    the optical axis; ``head_box``: the projected head and shoulders (the tracker's target)."""

    name: str
    box: Box | None
    visible_box: Box | None
    head_box: Box | None
    visible: float
    distance_m: float
    bearing_rad: float


@dataclass(frozen=True, slots=True)
class ForwardTruth:
    t_s: float
    camera_pose: Pose2D
    light_gain: float
    people: tuple[PersonInView, ...]

    def person(self, name: str) -> PersonInView | None:
        return next((p for p in self.people if p.name == name), None)


def _bgr(rgb: tuple[float, float, float], gain: float = 1.0) -> tuple[float, float, float]:
    return (min(rgb[2] * gain, 255.0), min(rgb[1] * gain, 255.0), min(rgb[0] * gain, 255.0))


class ForwardRenderer:
    """Renders frames of one camera model in one world (its walls)."""

    def __init__(self, model: ForwardCameraModel, walls: FloatArray, seed: int = 0) -> None:
        self.model = model
        self.segments = np.asarray(walls, dtype=np.float64).reshape(-1, 4)
        self.f_px = model.focal_length_px
        self.cx, self.cy = model.principal_point_px
        w, h = model.width_px, model.height_px
        cols = np.arange(w, dtype=np.float64)
        # Ray of each column in the camera's floor-plane frame: (1, (cx - u) / f), unnormalised, so the
        # distance along it is the depth X.
        self._col_left = (self.cx - cols) / self.f_px
        rng = np.random.default_rng(seed)
        self._rng = rng
        # Each wall a little lighter or darker (seeded: the same world looks the same).
        self._wall_tint = rng.uniform(0.85, 1.1, size=len(self.segments))
        normals = np.column_stack(
            (-(self.segments[:, 3] - self.segments[:, 1]), self.segments[:, 2] - self.segments[:, 0])
        )
        norm = np.maximum(np.hypot(normals[:, 0], normals[:, 1]), 1e-12)
        self._wall_lambert = 0.75 + 0.25 * np.abs(normals @ np.array(_LIGHT_DIR)) / norm
        self._background = self._draw_background()
        self._noise: list[tuple[ImageU8, ImageU8]] = []
        if model.noise_dn > 0:
            for _ in range(_NOISE_POOL):
                n = rng.normal(0.0, model.noise_dn, size=(h, w, 3))
                self._noise.append(
                    (np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8))
                )
        self._labels = np.zeros((h, w), dtype=np.uint8)

    # -- pieces drawn once -----------------------------------------------------------------------------
    def _draw_background(self) -> ImageU8:
        m = self.model
        h, w = m.height_px, m.width_px
        v = np.arange(h, dtype=np.float64)[:, None]
        ceiling = np.array(_bgr(m.ceiling_rgb))
        floor = np.array(_bgr(m.floor_rgb))
        # Ceiling darkens towards the horizon, the floor lightens towards it (far floor reflects more).
        above = np.clip((self.cy - v) / max(self.cy, 1.0), 0.0, 1.0)
        below = np.clip((v - self.cy) / max(h - self.cy, 1.0), 0.0, 1.0)
        row = np.where(v < self.cy, ceiling * (0.8 + 0.2 * above), floor * (1.1 - 0.3 * below))
        return np.ascontiguousarray(np.broadcast_to(row[:, None, :], (h, w, 3)).clip(0, 255).astype(np.uint8))

    # -- geometry --------------------------------------------------------------------------------------
    def camera_pose(self, base: Pose2D) -> Pose2D:
        mount = self.model.mount
        c, s = math.cos(base.yaw_rad), math.sin(base.yaw_rad)
        return Pose2D(
            base.x_m + c * mount.x_m - s * mount.y_m,
            base.y_m + s * mount.x_m + c * mount.y_m,
            base.yaw_rad + mount.yaw_rad,
        )

    def _column_depths(self, cam: Pose2D) -> tuple[FloatArray, npt.NDArray[np.intp]]:
        """Depth X of the nearest wall in each column (inf: none) and its index (-1: none)."""
        w = self.model.width_px
        if not self.segments.size:
            return np.full(w, np.inf), np.full(w, -1, dtype=np.intp)
        c, s = math.cos(cam.yaw_rad), math.sin(cam.yaw_rad)
        # Column rays in the world: d = forward + left * k (unnormalised; distance along it = depth X).
        dx = (c - s * self._col_left)[:, None]
        dy = (s + c * self._col_left)[:, None]
        seg = self.segments
        ax = seg[None, :, 0] - cam.x_m
        ay = seg[None, :, 1] - cam.y_m
        ex = seg[None, :, 2] - seg[None, :, 0]
        ey = seg[None, :, 3] - seg[None, :, 1]
        denom = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (ax * ey - ay * ex) / denom
            u = (ax * dy - ay * dx) / denom
        hit = (np.abs(denom) > 1e-12) & (t > 1e-6) & (u >= 0.0) & (u <= 1.0)
        t = np.where(hit, t, np.inf)
        index = np.argmin(t, axis=1)
        depth = t[np.arange(w), index]
        return depth, np.where(np.isfinite(depth), index, -1)

    def _row(self, height_m: float, depth_m: FloatArray | float) -> FloatArray | float:
        """Image row of a point ``height_m`` above the floor at depth X."""
        z = height_m - self.model.mount.z_m
        return self.cy - self.f_px * z / depth_m

    # -- the frame -------------------------------------------------------------------------------------
    def light_gain(self, t_s: float) -> float:
        m = self.model
        return 1.0 + m.light_variation * math.sin(2.0 * math.pi * t_s / m.light_period_s)

    def render(
        self, base: Pose2D, people: Sequence[PersonState], t_s: float, out: ImageU8 | None = None
    ) -> tuple[ImageU8, ForwardTruth]:
        """The frame seen from the robot's base pose ``base`` with ``people`` where they are at ``t_s``."""
        m = self.model
        h, w = m.height_px, m.width_px
        image = np.empty((h, w, 3), dtype=np.uint8) if out is None else out
        if image.shape != (h, w, 3) or image.dtype != np.uint8:
            raise ValueError(f"out must be a {h}x{w}x3 uint8 array, got {image.dtype} {image.shape}")
        np.copyto(image, self._background)
        cam = self.camera_pose(base)
        depth, index = self._column_depths(cam)
        self._draw_walls(image, depth, index)
        labels = self._labels
        labels.fill(0)
        views = self._draw_people(image, labels, cam, depth, people)
        gain = self.light_gain(t_s)
        if gain != 1.0:
            cv2.convertScaleAbs(image, image, alpha=gain)
        if self._noise:
            pos, neg = self._noise[int(self._rng.integers(len(self._noise)))]
            cv2.add(image, pos, image)
            cv2.subtract(image, neg, image)
        return image, ForwardTruth(t_s, cam, gain, views)

    def _draw_walls(self, image: ImageU8, depth: FloatArray, index: npt.NDArray[np.intp]) -> None:
        m = self.model
        w = m.width_px
        change = np.flatnonzero(np.diff(index)) + 1
        starts = np.concatenate(([0], change))
        ends = np.concatenate((change, [w]))
        base = np.array(_bgr(m.wall_rgb))
        for a, b in zip(starts, ends, strict=True):
            k = int(index[a])
            if k < 0:
                continue
            d0, d1 = float(depth[a]), float(depth[b - 1])
            mid = float(depth[(a + b - 1) // 2])
            shade = self._wall_tint[k] * self._wall_lambert[k] / (1.0 + 0.03 * mid)
            colour = tuple(float(c) for c in np.clip(base * shade, 0, 255))
            top0, top1 = self._row(m.wall_height_m, d0), self._row(m.wall_height_m, d1)
            bot0, bot1 = self._row(0.0, d0), self._row(0.0, d1)
            quad = np.array(
                [[a, top0], [b - 1 + 0.999, top1], [b - 1 + 0.999, bot1], [a, bot0]], dtype=np.float64
            )
            pts = np.round(np.clip(quad, -1e5, 1e5) * 16).astype(np.int32)
            cv2.fillPoly(image, [pts], colour, lineType=cv2.LINE_8, shift=4)

    def _draw_people(
        self,
        image: ImageU8,
        labels: npt.NDArray[np.uint8],
        cam: Pose2D,
        wall_depth: FloatArray,
        people: Sequence[PersonState],
    ) -> tuple[PersonInView, ...]:
        c, s = math.cos(cam.yaw_rad), math.sin(cam.yaw_rad)
        placed = []
        for k, st in enumerate(people):
            rx, ry = st.x_m - cam.x_m, st.y_m - cam.y_m
            x_fwd, y_left = c * rx + s * ry, -s * rx + c * ry
            placed.append((x_fwd, y_left, k, st))
        placed.sort(key=lambda p: -p[0])  # far to near
        boxes: dict[int, tuple[Box | None, Box | None, int]] = {}
        for x_fwd, y_left, k, st in placed:
            if x_fwd < _NEAR_M:
                continue
            facing_camera = math.cos(st.heading_rad - (cam.yaw_rad + math.pi)) > 0.0
            boxes[k] = self._draw_person(image, labels, k + 1, x_fwd, y_left, st, facing_camera, wall_depth)
        views = []
        for x_fwd, y_left, k, st in sorted(placed, key=lambda p: p[2]):
            if k not in boxes:
                continue
            box, head, drawn = boxes[k]
            visible_box, visible_px = None, 0
            if box is not None:
                region = labels[box.y : box.y + box.h, box.x : box.x + box.w] == k + 1
                visible_px = int(np.count_nonzero(region))
                if visible_px:
                    rows = np.flatnonzero(region.any(axis=1))
                    cols = np.flatnonzero(region.any(axis=0))
                    visible_box = Box(
                        box.x + int(cols[0]),
                        box.y + int(rows[0]),
                        int(cols[-1] - cols[0] + 1),
                        int(rows[-1] - rows[0] + 1),
                    )
            views.append(
                PersonInView(
                    st.person.name,
                    box,
                    visible_box,
                    head,
                    visible_px / drawn if drawn else 0.0,
                    x_fwd,
                    math.atan2(y_left, x_fwd),
                )
            )
        return tuple(views)

    def _draw_person(
        self,
        image: ImageU8,
        labels: npt.NDArray[np.uint8],
        label: int,
        x_fwd: float,
        y_left: float,
        st: PersonState,
        facing_camera: bool,
        wall_depth: FloatArray,
    ) -> tuple[Box | None, Box | None, int]:
        """Draw one body; returns its projected box, its head-and-shoulders box (both clipped to the
        image) and how many of its pixels fell inside the image before occlusion."""
        m = self.model
        clothes: Clothing = st.person.clothing
        height = clothes.height_m
        f, depth = self.f_px, x_fwd
        half_w = 0.5 * max(0.44, 2.0 * st.person.radius_m * 1.05)
        u_mid = self.cx - f * y_left / depth
        # Whole-body box in the image (unclipped), then clipped.
        left, right = u_mid - f * half_w / depth, u_mid + f * half_w / depth
        top, bottom = float(self._row(height, depth)), float(self._row(0.0, depth))
        x0, x1 = max(math.floor(left), 0), min(math.ceil(right) + 1, m.width_px)
        y0, y1 = max(math.floor(top), 0), min(math.ceil(bottom) + 1, m.height_px)
        if x1 <= x0 or y1 <= y0:
            return None, None, 0
        canvas = image[y0:y1, x0:x1].copy()
        mask = np.zeros((y1 - y0, x1 - x0), dtype=np.uint8)

        def px(lateral_m: float, height_m: float) -> tuple[float, float]:
            # Lateral offsets are to the person's right as the camera sees them (image right).
            return u_mid + f * lateral_m / depth - x0, float(self._row(height_m, depth)) - y0

        def poly(points: list[tuple[float, float]], colour: tuple[float, float, float]) -> None:
            pts = np.round(np.array([px(a, b) for a, b in points]) * 16).astype(np.int32)
            cv2.fillPoly(canvas, [pts], colour, lineType=cv2.LINE_8, shift=4)
            cv2.fillPoly(mask, [pts], 1, lineType=cv2.LINE_8, shift=4)

        hip, shoulder = 0.47 * height, 0.80 * height
        neck_top, head_c = 0.86 * height, 0.93 * height
        # Legs: the gap opens and closes with the gait.
        swing = abs(math.sin(math.pi * st.walked_m / (_STRIDE_M / 2.0))) if st.walked_m > 0 else 0.0
        gap = 0.02 + 0.1 * swing
        leg_w = 0.13
        trousers = _bgr(clothes.trousers_rgb)
        for side in (-1.0, 1.0):
            inner = side * gap / 2.0
            outer = side * (gap / 2.0 + leg_w)
            poly([(inner, 0.0), (outer, 0.0), (side * 0.15, hip + 0.02), (0.0, hip + 0.02)], trousers)
        shirt = _bgr(clothes.shirt_rgb)
        sleeve = _bgr(clothes.shirt_rgb, 0.85)
        # Arms beside the torso, then the torso, then sloping shoulders.
        for side in (-1.0, 1.0):
            poly(
                [
                    (side * 0.17, shoulder),
                    (side * 0.25, shoulder - 0.02),
                    (side * 0.23, hip - 0.05),
                    (side * 0.16, hip - 0.05),
                ],
                sleeve,
            )
        torso_mask_start = mask.copy()
        poly([(-0.17, hip), (0.17, hip), (0.19, shoulder), (-0.19, shoulder)], shirt)
        poly(
            [
                (-0.24, shoulder - 0.01),
                (0.24, shoulder - 0.01),
                (0.12, 0.845 * height),
                (-0.12, 0.845 * height),
            ],
            shirt,
        )
        torso = (mask > 0) & (torso_mask_start == 0)
        if clothes.pattern != "plain":
            self._texture(canvas, torso, clothes, depth, y0, x0 - u_mid, hip)
        skin = _bgr(clothes.skin_rgb)
        hair = _bgr(clothes.hair_rgb)
        poly([(-0.05, 0.84 * height), (0.05, 0.84 * height), (0.05, neck_top), (-0.05, neck_top)], skin)
        centre = px(0.0, head_c)
        axes = (f * 0.085 / depth, f * 0.115 / depth)
        ctr = (round(centre[0] * 16), round(centre[1] * 16))
        ax = (max(round(axes[0] * 16), 1), max(round(axes[1] * 16), 1))
        cv2.ellipse(canvas, ctr, ax, 0.0, 0.0, 360.0, skin if facing_camera else hair, -1, cv2.LINE_8, 4)
        cv2.ellipse(mask, ctr, ax, 0.0, 0.0, 360.0, 1, -1, cv2.LINE_8, 4)
        if facing_camera:  # hair on the top of the head
            cv2.ellipse(canvas, ctr, ax, 0.0, 180.0, 360.0, hair, -1, cv2.LINE_8, 4)
            face_top = px(0.0, head_c + 0.03)
            cv2.ellipse(
                canvas,
                (round(centre[0] * 16), round(face_top[1] * 16)),
                (ax[0] * 9 // 10, ax[1] * 3 // 4),
                0.0,
                0.0,
                180.0,
                skin,
                -1,
                cv2.LINE_8,
                4,
            )
        # Paste where no wall is nearer.
        visible_cols = wall_depth[x0:x1] > depth
        body = (mask > 0) & visible_cols[None, :]
        region = image[y0:y1, x0:x1]
        region[body] = canvas[body]
        labels[y0:y1, x0:x1][body] = label
        drawn = int(np.count_nonzero(mask))
        hx0 = max(math.floor(u_mid - f * 0.24 / depth), 0)
        hx1 = min(math.ceil(u_mid + f * 0.24 / depth), m.width_px)
        hy0 = max(math.floor(self._row(height, depth)), 0)
        hy1 = min(math.ceil(self._row(0.76 * height, depth)), m.height_px)
        head = Box(hx0, hy0, hx1 - hx0, hy1 - hy0) if hx1 > hx0 and hy1 > hy0 else None
        return Box(x0, y0, x1 - x0, y1 - y0), head, drawn

    def _texture(
        self,
        canvas: ImageU8,
        torso: npt.NDArray[np.bool_],
        clothes: Clothing,
        depth: float,
        y0: int,
        x0: float,
        hip_m: float,
    ) -> None:
        """Stripes (bands along the body's height) or checks on the shirt, ``pattern_period_m`` apart,
        fixed to the body (``x0``: the canvas's left edge from the body's axis, px)."""
        metres_per_px = depth / self.f_px
        rows = (np.arange(canvas.shape[0]) + y0 - float(self._row(hip_m, depth))) * metres_per_px
        band = (np.floor(rows / (clothes.pattern_period_m / 2.0)).astype(np.int64) % 2).astype(bool)
        on = np.broadcast_to(band[:, None], torso.shape)
        if clothes.pattern == "checks":
            cols = (np.arange(canvas.shape[1]) + x0) * metres_per_px
            across = (np.floor(cols / (clothes.pattern_period_m / 2.0)).astype(np.int64) % 2).astype(bool)
            on = on ^ across[None, :]
        canvas[torso & on] = _bgr(clothes.pattern_rgb)
