"""Step ``forward-camera``: the forward camera's focal length, principal point and lens distortion from views
of a board.

The forward camera (``[camera.forward]``, person following's colour camera, docs/following.md) is
calibrated as the ceiling camera is (``calibration/intrinsics.py``, whose collection, fit and checks this step
shares: views taken when the board is held still somewhere new, guidance towards the empty image cells,
``cv2.calibrateCamera`` with outliers dropped once, the rms / coverage / 1-sigma checks). Views come from the
robot's forward camera as its config opens it (V4L2, GenICam, the fake still image), from a folder of
images, or, with ``--sim``, from the simulated forward camera (the world's ``[forward_camera]``) with a
helper holding the board in front of it at varied poses, drawn over the room the camera sees from the
robot's start (``drivers/sim/forward_targets.py``).

The result is a ROS camera_info YAML file (``forward_camera_info.yaml``) and its PNG report; the robot's
config points at it with ``camera_info = "FILE"`` in ``[camera.forward]``, in place of the hand-typed
``hfov_deg`` / ``fx_px``, ``fy_px``, ``cx_px``, ``cy_px`` keys (docs/config.md). The forward camera's mount
(height, pitch) is not measured here: a hand-held board says nothing about where the camera sits on the base.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

from calibration.boards import BoardDetector
from calibration.context import StepContext
from calibration.intrinsics import (
    CameraSource,
    FolderSource,
    add_lens_arguments,
    board_spec,
    check_view_counts,
    first_image_size,
    solve_lens,
    truth_of,
)
from calibration.intrinsics import interactive as lens_questions
from calibration.report import CalibrationError, StepResult
from drivers.errors import DeviceError

__all__ = ["DEFAULT_FILE", "NAME", "add_arguments", "interactive", "run"]

log = logging.getLogger(__name__)

NAME = "forward-camera"
DEFAULT_FILE = "forward_camera_info.yaml"
# What the view collection assumes of an uncalibrated lens (to judge tilts; not part of the fit): a
# webcam's 60-70 degree field of view.
_GUESS_HFOV_RAD = math.radians(65.0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    add_lens_arguments(p)


def interactive(ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace:
    """The wizard's questions: the same as the ceiling camera's (source, board, views)."""
    return lens_questions(ctx, options)


def _f_guess(
    width: int, hfov_rad: float | None = None, fx_px: float | None = None, at: int | None = None
) -> float:
    if fx_px is not None:
        return fx_px * width / at if at else fx_px
    return (width / 2.0) / math.tan((hfov_rad or _GUESS_HFOV_RAD) / 2.0)


def run(ctx: StepContext, options: argparse.Namespace) -> StepResult:
    console = ctx.console
    spec = board_spec(options)
    detector = BoardDetector(spec, equalize_first=False)
    check_view_counts(options)
    output = ctx.output(options.output, DEFAULT_FILE)
    console.say(f"forward-camera: looking for {spec.describe()}")

    if options.images:
        folder = FolderSource(Path(options.images))
        width, height = first_image_size(folder)
        console.say(f"  {len(folder.paths)} images in {options.images}")
        lens = solve_lens(ctx, options, detector, folder, width, height, _f_guess(width))
    elif ctx.sim is not None:
        from calibration.sim import BoardHelper, forward_target_renderer

        world = ctx.sim.load()
        renderer = forward_target_renderer(world, detector.target, seed=ctx.sim.seed)
        model = world.forward_camera
        width, height = model.width_px, model.height_px
        helper = BoardHelper(renderer, seed=ctx.sim.seed)
        console.say(
            f"  simulated forward camera of world {world.name!r} ({width}x{height}); a helper holds the "
            "board in front of it"
        )
        held = helper.source(max_images=max(6 * options.views, 60))
        lens = solve_lens(
            ctx,
            options,
            detector,
            held,
            width,
            height,
            _f_guess(width),
            truth=truth_of(renderer.output_intrinsics),
        )
    else:
        ctx.require_robot("calibrating the forward camera")
        from calibration.rig import Rig

        with Rig.for_context(ctx) as rig:
            exposure = None if options.exposure_ms is None else options.exposure_ms / 1000.0
            camera = rig.forward_camera(exposure_s=exposure)
            try:
                frame = camera.grab(timeout_s=5.0)
            except DeviceError as exc:
                raise CalibrationError(f"the forward camera gave no frame: {exc}") from exc
            height, width = frame.image.shape[:2]
            view = rig.forward_view
            f_guess = (
                _f_guess(width, view.hfov_rad, view.fx_px, view.width_px)
                if view is not None
                else _f_guess(width)
            )
            console.say(
                "  hold the board still in front of the forward camera; a view is taken when it is still"
            )
            lens = solve_lens(
                ctx, options, detector, CameraSource(camera, options.timeout_s), width, height, f_guess
            )
    use = [
        f'set camera_info = "{output}" in the [camera.forward] table of the robot config, in place of '
        "hfov_deg / fx_px, fy_px, cx_px, cy_px (docs/config.md)",
        "the mount ([camera.forward.mount]: x, y, z, yaw, pitch) is not measured by this step: measure it",
    ]
    return lens.result(NAME, output, "forward_camera", options.max_rms, use)
