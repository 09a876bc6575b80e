"""Fixtures of the whole-agent tests."""

from __future__ import annotations

import os
import signal
import subprocess
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pytest

from tests.fleet_helpers import SimRobot
from tests.integration.sim_pty import SimOnPty
from tests.integration.test_agent_accuracy import REPO, PtyReader, vlp_agent
from tests.integration.test_agent_shutdown import wait_for_frames


@pytest.fixture
def sim_on_pty() -> Iterator[Callable[..., SimOnPty]]:
    """Starts ``vlp-agent sim ARGS --output PTY`` and returns once ``frames`` pose frames came (the agent is
    up: a signal during Python's start-up would be fatal); whatever is still running at the end of the test
    is killed with its whole group, and the pty closed."""
    started: list[SimOnPty] = []

    def start(*args: str, frames: int = 50) -> SimOnPty:
        reader = PtyReader()
        proc = subprocess.Popen(
            [*vlp_agent("sim", *args), "--output", reader.path],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        sim = SimOnPty(proc, reader)
        started.append(sim)
        wait_for_frames(reader, proc, frames)
        return sim

    yield start
    for sim in started:
        if sim.proc.poll() is None:
            os.killpg(sim.proc.pid, signal.SIGKILL)
            sim.proc.wait()
        sim.reader.close()


@pytest.fixture
def fleet_robot(tmp_path: Path) -> Iterator[Callable[..., SimRobot]]:
    """Starts one simulated robot with its fleet bridge (``tests.fleet_helpers.SimRobot``: ``start(world,
    listen=..., connect=...)``); whatever still runs at the end of the test is stopped."""
    started: list[SimRobot] = []

    def start(world: Path, *, listen: Sequence[str] = (), connect: Sequence[str] = ()) -> SimRobot:
        folder = tmp_path / f"robot{len(started) + 1}"
        folder.mkdir()
        robot = SimRobot(folder, world, listen=listen, connect=connect)
        started.append(robot)
        return robot

    yield start
    for robot in started:
        robot.stop()
