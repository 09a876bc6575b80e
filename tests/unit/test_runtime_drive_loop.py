"""The controller's commands drive the base: a velocity frame on the pose output's line reaches the wheels'
DriveCommand, a stop holds zero, and with no command the sim's route follower (``command_velocity``)
drives as before. On a real pseudo-terminal; the agent's clock is the test's."""

from __future__ import annotations

import os
import time

from agent.config import AgentConfig, OutputConfig
from agent.runtime.agent import Agent
from agent.runtime.arbiter import DriveSource
from agent.runtime.devices import Devices
from agent.runtime.output import PoseOutput
from firmware_protocol.command_frame import (
    NO_SEQUENCE,
    GoalCommand,
    GoalReason,
    GoalState,
    GoalStatusDecoder,
    ResumeCommand,
    StopCommand,
    VelocityCommand,
    encode_command,
)
from tests.unit.test_runtime_output import pty, read_all

__all__ = ["pty"]  # the fixture


class Clock:
    def __init__(self) -> None:
        self.now_ns = 5_000_000_000

    def __call__(self) -> int:
        return self.now_ns

    def advance(self, seconds: float) -> None:
        self.now_ns += int(seconds * 1e9)


def make_agent(path: str, clock: Clock | None = None) -> Agent:
    config = AgentConfig(file="test", devices={}, output=OutputConfig(url=path))
    output = PoseOutput(config.output, path)
    if clock is None:
        return Agent(config, Devices(), output=output)
    return Agent(config, Devices(), output=output, clock_ns=clock)


def send(agent: Agent, master: int, data: bytes) -> bytes:
    """Write ``data`` as the controller, run the command loop until it took a command; the answers."""
    assert agent.commands is not None and agent.drive_step is not None
    os.write(master, data)
    for _ in range(50):  # the pty hands bytes over at once; this only waits for them, it measures nothing
        if agent.commands.step():
            break
        time.sleep(0.01)
    agent.drive_step.step()
    return read_all(master)


def wheels(agent: Agent) -> tuple[float, float, str]:
    command = agent.drive.current(agent.clock_ns())
    return command.v_mps, command.omega_radps, command.reason


def test_velocity_drives_stop_holds_zero_and_the_route_follower_drives_else(
    pty: tuple[int, str],
) -> None:
    master, path = pty
    clock = Clock()
    agent = make_agent(path, clock)
    assert agent.output is not None and agent.drive_step is not None
    agent.output.open()
    read_all(master)

    # Nothing from the controller: the route follower's velocity is what the wheels get.
    agent.command_velocity(0.1, 0.05)
    assert agent.drive_step.step().source is DriveSource.NONE
    assert wheels(agent) == (0.1, 0.05, "command")

    # A controller velocity takes over, and the route follower gives way to it.
    reply = send(agent, master, encode_command(VelocityCommand(7, 0.2, -0.5, 0.4)))
    assert wheels(agent) == (0.2, -0.5, "command")
    agent.command_velocity(0.1, 0.05)
    assert wheels(agent) == (0.2, -0.5, "command")
    clock.advance(0.3)  # repeated every pass while in force: DriveCommand's dead-man does not cut it
    agent.drive_step.step()
    assert wheels(agent) == (0.2, -0.5, "command")

    # Stop: zero, held whatever else commands; resume gives the base back after the hold.
    reply += send(agent, master, encode_command(StopCommand(8)))
    assert wheels(agent) == (0.0, 0.0, "hold")
    agent.command_velocity(0.1, 0.05)
    assert wheels(agent) == (0.0, 0.0, "hold")
    reply += send(agent, master, encode_command(ResumeCommand(9)))
    assert agent.drive_step.source is DriveSource.NONE
    clock.advance(agent.config.control.recovery_hold_s + 0.01)
    agent.command_velocity(0.1, 0.05)
    assert wheels(agent) == (0.1, 0.05, "command")

    statuses = GoalStatusDecoder().feed(reply)
    assert [(s.command_sequence, s.state) for s in statuses] == [
        (7, GoalState.ACCEPTED),
        (8, GoalState.ACCEPTED),
        (9, GoalState.ACCEPTED),
    ]
    status = agent.status()
    assert status.commands["command_velocity"] == 1 and status.commands["command_stop"] == 1
    assert status.commands["arbiter_accepted"] == 3 and status.commands["drive_velocity"] == 2
    assert status.counts["velocity_commands_overridden"] == 2
    assert [s.command_sequence for s in status.command_statuses] == [7, 8, 9]


def test_an_expired_velocity_stops_the_base_at_once_and_is_answered(pty: tuple[int, str]) -> None:
    master, path = pty
    clock = Clock()
    agent = make_agent(path, clock)
    assert agent.output is not None and agent.drive_step is not None
    agent.output.open()
    read_all(master)
    send(agent, master, encode_command(VelocityCommand(1, 0.1, 0.0, 0.2)))
    assert wheels(agent) == (0.1, 0.0, "command")
    clock.advance(0.25)  # past the command's own timeout, within DriveCommand's (0.5 s)
    agent.drive_step.step()
    assert wheels(agent) == (0.0, 0.0, "command")
    (status,) = GoalStatusDecoder().feed(read_all(master))
    assert (status.command_sequence, status.state, status.reason) == (
        NO_SEQUENCE,
        GoalState.CANCELLED,
        GoalReason.DEAD_MAN,
    )


def test_goals_are_rejected_without_a_navigator(pty: tuple[int, str]) -> None:
    master, path = pty
    agent = make_agent(path)
    assert agent.output is not None
    agent.output.open()
    read_all(master)
    (status,) = GoalStatusDecoder().feed(send(agent, master, encode_command(GoalCommand(3, 21, 1.0, 2.0))))
    assert (status.goal_id, status.state, status.reason) == (21, GoalState.REJECTED, GoalReason.NOT_LOCALIZED)
    seen = []
    agent.navigator = lambda directive, now_s: seen.append(directive.goal)
    (status,) = GoalStatusDecoder().feed(send(agent, master, encode_command(GoalCommand(4, 22, 1.0, 2.0))))
    assert status.state is GoalState.ACCEPTED
    assert [g.goal_id for g in seen if g is not None] == [22]


def test_the_running_agent_takes_commands_in_its_commands_loop(pty: tuple[int, str]) -> None:
    master, path = pty
    agent = make_agent(path)
    agent.start()
    try:
        assert agent.health.heartbeat("commands") is not None
        os.write(master, encode_command(VelocityCommand(1, 0.15, 0.0, 5.0)))
        deadline = time.monotonic() + 5.0
        while wheels(agent)[0] != 0.15 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert wheels(agent) == (0.15, 0.0, "command")
    finally:
        agent.stop()
