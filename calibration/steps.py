"""The calibration steps, in the order a new robot goes through them, and how to load one.

Each step module has ``add_arguments(parser)`` (its options), ``interactive(ctx, options)`` (the wizard's
questions, returning the options) and ``run(ctx, options) -> StepResult``.
"""

from __future__ import annotations

import argparse
import importlib
from dataclasses import dataclass
from types import ModuleType
from typing import Protocol

from calibration.context import StepContext
from calibration.report import StepResult

__all__ = ["STEPS", "StepInfo", "StepModule", "find", "load"]


class StepModule(Protocol):
    def add_arguments(self, parser: argparse.ArgumentParser) -> None: ...

    def interactive(self, ctx: StepContext, options: argparse.Namespace) -> argparse.Namespace: ...

    def run(self, ctx: StepContext, options: argparse.Namespace) -> StepResult: ...


@dataclass(frozen=True, slots=True)
class StepInfo:
    name: str
    module: str
    title: str
    needs: str
    writes: str


STEPS: tuple[StepInfo, ...] = (
    StepInfo(
        "servos",
        "calibration.servos",
        "find the wheel servos on the bus; set their ids, velocity mode and baud rate",
        "the servo bus (U2D2 adapter), servos powered",
        "servos.toml",
    ),
    StepInfo(
        "intrinsics",
        "calibration.intrinsics",
        "camera focal length, principal point and lens distortion",
        "a printed chessboard or ChArUco board; the camera (or a folder of images)",
        "camera_info.yaml",
    ),
    StepInfo(
        "mount",
        "calibration.mount",
        "camera tilt (IMU at rest or a level board) and its yaw and offset on the base",
        "the IMU on the camera bracket, or a board held level above the camera; room to drive 0.3 m and turn",
        "mount.toml",
    ),
    StepInfo(
        "wheels",
        "calibration.wheels",
        "wheel radius and track from a measured straight run and turns in place",
        "1.5 m of floor, a tape measure, a mark on the floor",
        "wheels.toml",
    ),
    StepInfo(
        "laser",
        "calibration.laser",
        "laser yaw and position on the base from a room corner",
        "a room corner 1-2 m ahead of the robot, room to drive 0.3 m and turn",
        "laser.toml",
    ),
    StepInfo(
        "row-time",
        "calibration.row_time",
        "the camera's row time (the stripes' clock) from the LEDs' known frequencies",
        "the LED map with the drivers' frequencies; the robot where 2+ LEDs are in view",
        "row_time.toml",
    ),
    StepInfo(
        "leds",
        "calibration.leds",
        "survey the ceiling LEDs: frequency and duty signature of each, with its coordinates",
        "the camera under each LED in turn; the LED coordinates (typed or a CSV file)",
        "leds.toml",
    ),
    StepInfo(
        "vlp-error",
        "calibration.vlp_error",
        "VLP error calibration: rotation centre (turn in place) and residual correction at known points",
        "the LED map and camera calibration; the robot under 2+ LEDs; a few marked points",
        "vlp.toml",
    ),
    StepInfo(
        "forward-camera",
        "calibration.forward_camera",
        "forward camera (person following) focal length, principal point and lens distortion",
        "a printed chessboard or ChArUco board; the forward camera (or a folder of images)",
        "forward_camera_info.yaml",
    ),
    StepInfo(
        "rfid",
        "calibration.rfid",
        "RFID likelihood table of person following: reads of the tag walked round the robot",
        "the reader's antennas mounted; the person's tag; marks on the floor every 45 deg at 1, 2 and 3 m",
        "rfid_table.toml",
    ),
)


def find(name: str) -> StepInfo:
    for step in STEPS:
        if step.name == name:
            return step
    raise KeyError(name)


def load(step: StepInfo) -> ModuleType:
    return importlib.import_module(step.module)
