"""The motor side of the agent, in the servos' own registers (the fake XL430s behind a pty):

* while a wheel servo is silent the other one is commanded to zero (the silent one cannot hear);
* when it answers again both get zero velocity first, and zero is held for ``recovery_hold_s`` although the
  command source never stopped;
* a command that is not repeated within the dead-man timeout becomes zero velocity;
* a wheel servo cut off from the agent stops by its Bus Watchdog, so the robot stops instead of pivoting.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from agent.config import parse_config
from agent.runtime import Agent, create_agent
from drivers.sim.harness import SimulatedRobot
from firmware_protocol.pose_frame import PoseFlags

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"
CONFIG = f"""
[sim]
world = "{OFFICE}"
[camera]
enabled = false
[laser]
enabled = false
[rfid]
enabled = false
[servos]
latency_timer_ms = 20
[control]
deadman_timeout_s = 0.3
recovery_hold_s = 0.6
[output]
url = "pty"
"""


def wait_for(what: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not what():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


@pytest.fixture
def running() -> Iterator[tuple[SimulatedRobot, Agent, threading.Event]]:
    config = parse_config(CONFIG, str(OFFICE.parent / "c.toml"))
    assert config.sim is not None
    with SimulatedRobot(config.sim.world) as robot:
        agent = create_agent(config, robot=robot, output_url=None)
        agent.start()
        commanding = threading.Event()
        commanding.set()

        def command() -> None:
            while not agent.stopping:
                if commanding.is_set():
                    agent.command_velocity(0.1, 0.0)
                time.sleep(0.05)

        thread = threading.Thread(target=command, daemon=True)
        thread.start()
        try:
            yield robot, agent, commanding
        finally:
            agent.stop()
            thread.join(2.0)


def goal(robot: SimulatedRobot, servo_id: int) -> int:
    return robot.servos.register(servo_id, "Goal Velocity")


def test_zero_velocity_is_commanded_when_a_silent_servo_answers_again(
    running: tuple[SimulatedRobot, Agent, threading.Event],
) -> None:
    robot, agent, _ = running
    left, right = robot.world.robot.left_id, robot.world.robot.right_id
    wait_for(lambda: goal(robot, left) != 0 and goal(robot, right) != 0)  # driving
    driving = goal(robot, left)

    robot.servos.mute(left)
    wait_for(lambda: bool(agent.flags() & PoseFlags.SERVO_FAULT))
    wait_for(lambda: goal(robot, right) == 0)  # the one that still hears is stopped
    assert goal(robot, left) == driving  # the silent one could not hear it

    robot.servos.mute(left, False)
    wait_for(lambda: agent.status().counts.get("zero_on_recovery", 0) >= 1)
    recovered = time.monotonic()
    # The zero was written (a sync write has no reply); the fake takes it off its pty a moment later.
    wait_for(lambda: goal(robot, left) == 0 and goal(robot, right) == 0, timeout_s=0.2)
    # Held at zero although commands keep coming...
    while time.monotonic() - recovered < 0.4:
        assert goal(robot, left) == 0 and goal(robot, right) == 0
        time.sleep(0.02)
    # ...then the commands drive again, and the fault is gone.
    wait_for(lambda: goal(robot, left) != 0)
    wait_for(lambda: not agent.flags() & PoseFlags.SERVO_FAULT)
    assert agent.status().devices["servos"].recoveries >= 1


def test_a_wheel_servo_cut_off_stops_by_its_bus_watchdog_so_the_robot_does_not_pivot(
    running: tuple[SimulatedRobot, Agent, threading.Event],
) -> None:
    robot, agent, _ = running
    sim, left = robot.simulation, robot.world.robot.left_id
    servos = agent.devices.servos
    watchdog_s = 0.020 * getattr(servos, "bus_watchdog_units", 0)
    assert watchdog_s == 0.1  # latency_timer_ms = 20: the 100 ms default
    wait_for(lambda: goal(robot, left) != 0)
    time.sleep(0.3)  # at speed: 0.1 m/s straight ahead
    v_mps = 0.1
    yaw0 = sim.pose().yaw_rad
    robot.servos.mute(left)  # its cable pulled: it hears nothing from now on
    time.sleep(1.5)
    turned_rad = abs(math.remainder(sim.pose().yaw_rad - yaw0, math.tau))
    assert sim.wheels().velocity_radps == (0.0, 0.0)
    assert robot.servos.register(left, "Bus Watchdog") == -1
    # The agent stops the right wheel once the left one's reads time out; the left one, deaf, keeps its
    # goal until its watchdog stops it 100 ms after the last instruction it heard. Before the watchdog
    # it drove on alone: 0.1 m/s / 0.16 m = 0.6 rad/s of pivot, 0.9 rad in these 1.5 s. Now the turn is
    # at most one wheel at speed for the watchdog's period; 0.2 s more allows the wheels' spin-down and
    # a loaded machine's delays.
    assert turned_rad < v_mps * (watchdog_s + 0.2) / robot.world.robot.track_m


def test_a_stale_command_stops_the_wheels(running: tuple[SimulatedRobot, Agent, threading.Event]) -> None:
    robot, agent, commanding = running
    left = robot.world.robot.left_id
    wait_for(lambda: goal(robot, left) != 0)
    commanding.clear()  # whoever commanded the base went quiet
    wait_for(lambda: goal(robot, left) == 0)
    # Zero because the last command is stale ("none" if a servo hiccup's recovery forgot it meanwhile).
    assert dataclasses.asdict(agent.drive.current(time.monotonic_ns()))["reason"] in ("stale", "none")
    time.sleep(0.3)
    assert goal(robot, left) == 0  # and it stays stopped


def _once_in_servo_loop(pause_s: float, then: Callable[[], object], armed: threading.Event) -> object:
    """``then()``, after a pause of ``pause_s`` the first time the servo loop calls it once ``armed``."""
    if armed.is_set() and threading.current_thread().name == "agent-servos":
        armed.clear()
        time.sleep(pause_s)
    return then()


def _flags_while(armed: threading.Event, agent: Agent, seconds: float) -> list[PoseFlags]:
    armed.set()
    seen = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        seen.append(agent.flags())
        time.sleep(0.01)
    return seen


def test_a_late_servo_loop_is_not_a_servo_fault_but_a_hanging_wheel_read_is(
    running: tuple[SimulatedRobot, Agent, threading.Event],
) -> None:
    _, agent, _ = running
    servos = agent.devices.servos
    assert servos is not None
    wait_for(lambda: bool(agent.flags() & PoseFlags.ODOMETRY) and not agent.flags() & PoseFlags.SERVO_FAULT)

    # The loop is 0.6 s late for its next read (what a stalled machine looks like to it): the odometry goes
    # stale, which the ODOMETRY bit says, but the servos answer every read they get: no SERVO_FAULT.
    late = threading.Event()
    give_way = agent.hot_path.give_way
    agent.hot_path.give_way = lambda: _once_in_servo_loop(0.6, give_way, late)  # type: ignore[method-assign]
    seen = _flags_while(late, agent, 0.8)
    assert any(not f & PoseFlags.ODOMETRY for f in seen), "the loop was not late"
    assert not any(f & PoseFlags.SERVO_FAULT for f in seen), seen
    agent.hot_path.give_way = give_way  # type: ignore[method-assign]
    wait_for(lambda: bool(agent.flags() & PoseFlags.ODOMETRY))

    # A wheel read that hangs for 0.6 s (a bus that holds the reply back): SERVO_FAULT after
    # health.servo_fault_s (0.2 s), gone once the read returns.
    hanging = threading.Event()
    read = servos.read
    servos.read = lambda: _once_in_servo_loop(0.6, read, hanging)  # type: ignore[method-assign]
    seen = _flags_while(hanging, agent, 0.8)
    assert any(f & PoseFlags.SERVO_FAULT for f in seen), seen
    wait_for(lambda: not agent.flags() & PoseFlags.SERVO_FAULT)
