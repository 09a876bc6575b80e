"""The pure pursuit controller: it respects the speed, acceleration and wheel limits, and gets there."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.controller import Command, PurePursuit

CONFIG = NavConfig()
DT = 0.05


def _drive(
    path: np.ndarray, pose: tuple[float, float, float], seconds: float
) -> tuple[list[Command], list[tuple[float, float, float]]]:
    """Follow ``path`` with ideal motion (the command is what the robot does)."""
    controller = PurePursuit(CONFIG)
    x, y, yaw = pose
    commands, poses = [], []
    for _ in range(round(seconds / DT)):
        command = controller.follow((x, y, yaw), path, DT)
        commands.append(command)
        x += command.v_mps * DT * math.cos(yaw)
        y += command.v_mps * DT * math.sin(yaw)
        yaw += command.omega_radps * DT
        poses.append((x, y, yaw))
    return commands, poses


def test_every_command_is_within_the_speed_acceleration_and_wheel_limits() -> None:
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.5]])
    commands, _ = _drive(path, (0.0, 0.0, math.pi), 40.0)  # starts facing away: turns in place first
    v = np.array([c.v_mps for c in commands])
    w = np.array([c.omega_radps for c in commands])
    assert v.max() <= CONFIG.max_speed_mps + 1e-9 and v.min() >= -CONFIG.max_reverse_mps - 1e-9
    assert np.abs(w).max() <= CONFIG.max_turn_radps + 1e-9
    assert np.abs(np.diff(np.concatenate([[0.0], v]))).max() <= CONFIG.max_accel_mps2 * DT + 1e-9
    assert np.abs(np.diff(np.concatenate([[0.0], w]))).max() <= CONFIG.max_turn_accel_radps2 * DT + 1e-9
    wheel = np.abs(v) + np.abs(w) * CONFIG.track_m / 2.0
    assert wheel.max() <= CONFIG.max_wheel_speed_mps + 1e-9
    assert v.max() > 0.9 * CONFIG.max_speed_mps  # and it does use the speed it has


def test_it_follows_the_path_to_its_end_and_stops_there() -> None:
    path = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]])
    commands, poses = _drive(path, (0.0, 0.0, 0.0), 40.0)
    x, y, _ = poses[-1]
    assert math.hypot(x - 2.0, y - 2.0) < 0.05
    assert abs(commands[-1].v_mps) < 0.05
    # Never far off the path: pure pursuit cuts the corner by less than its lookahead.
    off = [min(abs(py), abs(px - 2.0)) for px, py, _ in poses]
    assert max(off) < CONFIG.lookahead_max_m


def test_turning_to_a_heading_decelerates_onto_it_without_overshoot() -> None:
    controller = PurePursuit(CONFIG)
    yaw = 0.0
    for _ in range(200):
        command = controller.turn_to(math.pi / 2 - yaw, DT)
        yaw += command.omega_radps * DT
    assert abs(yaw - math.pi / 2) < math.radians(2.0)
