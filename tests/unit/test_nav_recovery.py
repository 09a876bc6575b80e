"""Recovery and the navigator: blocked robots wait, rotate, back up, and give up with a reason after a
bound; goals that cannot be reached fail at once; a free goal is reached."""

from __future__ import annotations

import math

import numpy as np

from agent.navigation.config import NavConfig
from agent.navigation.costmap import Costmap, GridSpec
from agent.navigation.navigator import Goal, Navigator, NavStatus
from agent.navigation.recovery import SEQUENCE, Action, Recovery

SPEC = GridSpec((0.0, 0.0), 0.05, (80, 120))  # 6 x 4 m
DT = 0.05


def test_recovery_rounds_go_wait_rotate_back_up_and_are_bounded() -> None:
    config = NavConfig(max_recoveries=3, wait_s=1.0)
    recovery = Recovery(config)
    t, pose = 0.0, (0.0, 0.0, 0.0)
    actions = []
    while not recovery.exhausted():
        actions.append(recovery.begin(t, pose, "blocked ahead"))
        while True:
            command = recovery.step(t, pose, backward_clear=True)
            if command is None:
                break
            x, y, yaw = pose
            pose = (
                x + command.v_mps * DT * math.cos(yaw),
                y + command.v_mps * DT * math.sin(yaw),
                yaw + command.omega_radps * DT,
            )
            t += DT
            assert t < 60.0
    assert actions == list(SEQUENCE[:3]) == [Action.WAIT, Action.ROTATE, Action.BACK_UP]
    assert abs(pose[2] - config.rotate_rad) < math.radians(5.0)  # turned
    assert math.hypot(pose[0], pose[1]) >= config.backup_m - 0.01  # backed up
    reason = recovery.reason("blocked ahead")
    assert "gave up after 3 recoveries" in reason and "back_up" in reason


def test_progress_resets_the_count() -> None:
    recovery = Recovery(NavConfig(max_recoveries=2))
    recovery.begin(0.0, (0.0, 0.0, 0.0), "no progress")
    recovery.begin(1.0, (0.0, 0.0, 0.0), "no progress")
    assert recovery.exhausted()
    recovery.progressed(2.0)
    assert not recovery.exhausted()


def _navigator(occupied: np.ndarray, config: NavConfig) -> Navigator:
    return Navigator(config, Costmap(SPEC, occupied, np.zeros(SPEC.shape, bool), config))


def _run(
    navigator: Navigator, pose: tuple[float, float, float], seconds: float
) -> tuple[float, float, float]:
    """Ideal kinematics: the robot does what it is told."""
    t = 0.0
    x, y, yaw = pose
    while t < seconds and navigator.status in (NavStatus.ACTIVE, NavStatus.RECOVERING):
        t += DT
        out = navigator.step(t, (x, y, yaw))
        x += out.command.v_mps * DT * math.cos(yaw)
        y += out.command.v_mps * DT * math.sin(yaw)
        yaw += out.command.omega_radps * DT
    return x, y, yaw


def test_the_navigator_reaches_a_goal_round_a_wall_within_the_tolerances() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:50, 60] = True  # a wall along x = 3 from y = 0 to 2.5
    config = NavConfig()
    navigator = _navigator(occupied, config)
    navigator.set_goal(Goal(5.0, 1.0, math.pi / 2), 0.0)
    x, y, yaw = _run(navigator, (1.0, 1.0, 0.0), 120.0)
    assert navigator.status is NavStatus.REACHED
    assert math.hypot(x - 5.0, y - 1.0) <= config.xy_tolerance_m
    assert abs(math.remainder(yaw - math.pi / 2, math.tau)) <= config.yaw_tolerance_rad


def test_a_goal_cut_off_on_the_map_fails_at_once_with_the_reason() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:, 60] = True
    navigator = _navigator(occupied, NavConfig())
    navigator.set_goal(Goal(5.0, 1.0), 0.0)
    _run(navigator, (1.0, 1.0, 0.0), 5.0)
    assert navigator.status is NavStatus.FAILED
    assert "unreachable" in navigator.reason


def test_a_goal_blocked_by_an_obstacle_that_stays_fails_after_the_recovery_bound() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:30, 60] = True
    occupied[40:, 60] = True  # a wall along x = 3 with a door at y = 1.5 .. 2.0
    config = NavConfig(max_recoveries=3, wait_s=1.0)
    navigator = _navigator(occupied, config)
    navigator.set_goal(Goal(5.0, 1.75), 0.0)
    t, pose = 0.0, (1.0, 1.75, 0.0)
    while t < 200.0 and navigator.status in (NavStatus.ACTIVE, NavStatus.RECOVERING):
        t += DT
        # Someone stands in the door: every scan shows them (so clearing the layer does not help).
        navigator.costmap.obstacles[30:40, 60] = True
        navigator.costmap.version += 1
        out = navigator.step(t, pose)
        x, y, yaw = pose
        pose = (
            x + out.command.v_mps * DT * math.cos(yaw),
            y + out.command.v_mps * DT * math.sin(yaw),
            yaw + out.command.omega_radps * DT,
        )
    assert navigator.status is NavStatus.FAILED
    assert "gave up after 3 recoveries" in navigator.reason
    assert t < 60.0


def test_the_navigator_replans_round_an_obstacle_that_closes_its_way() -> None:
    occupied = np.zeros(SPEC.shape, bool)
    occupied[:, 60] = True
    occupied[10:20, 60] = False  # door A at y = 0.5 .. 1.0 (the near one)
    occupied[60:72, 60] = False  # door B at y = 3.0 .. 3.6
    config = NavConfig()
    navigator = _navigator(occupied, config)
    navigator.set_goal(Goal(5.0, 1.0), 0.0)
    t, (x, y, yaw) = 0.0, (1.0, 1.0, 0.0)
    first_plan = None
    while t < 200.0 and navigator.status in (NavStatus.ACTIVE, NavStatus.RECOVERING):
        t += DT
        if t > 2.0:  # door A is closed (a trolley parked in it), as every scan from now on shows
            navigator.costmap.obstacles[10:20, 60] = True
            navigator.costmap.version += 1
        out = navigator.step(t, (x, y, yaw))
        first_plan = first_plan if first_plan is not None else navigator.plan
        x += out.command.v_mps * DT * math.cos(yaw)
        y += out.command.v_mps * DT * math.sin(yaw)
        yaw += out.command.omega_radps * DT
    assert first_plan is not None and first_plan.path_m[:, 1].max() < 1.5  # it meant to take door A
    assert navigator.status is NavStatus.REACHED
    assert len(navigator.plans) >= 2
    assert max(p.path_m[:, 1].max() for p in navigator.plans if p.ok) > 3.0  # and went through door B
