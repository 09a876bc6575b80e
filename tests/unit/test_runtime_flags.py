"""The pose's status word from the agent's own state: a source bit means that source fed this pose lately,
so a pose that no position source moves carries no source bit (docs/wire-format.md: a stale hold)."""

from __future__ import annotations

from agent.config import parse_config
from agent.runtime import Agent
from agent.runtime.devices import Devices
from firmware_protocol.pose_frame import PoseFlags

CONFIG = '[servos]\nbackend = "dynamixel"\nport = "/dev/ttyUSB0"\n[output]\nurl = "loop://"\n'
SOURCES = PoseFlags.VLP | PoseFlags.SLAM | PoseFlags.ODOMETRY | PoseFlags.IMU


class Clock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def test_the_imu_alone_is_a_stale_hold_and_beside_odometry_a_source() -> None:
    clock = Clock()
    agent = Agent(parse_config(CONFIG, "c.toml"), Devices(), clock_ns=clock)
    # Gyro samples keep arriving (yaw rate 0), nothing gives position: the position is frozen.
    for _ in range(50):
        clock.ns += 10_000_000
        assert agent.fusion.add_gyro(clock.ns, 0.0).accepted
    assert agent.fusion.live(clock.ns, agent.timeouts_ns)  # the filter did fuse the IMU...
    flags = agent.flags()
    assert not flags & SOURCES, flags  # ...but the pose is a stale hold: no source bit at all
    # Wheel odometry arriving beside it: position is carried, and the IMU's yaw rate is part of it.
    t = clock.ns
    for _ in range(10):
        clock.ns += 10_000_000
        agent.fusion.add_odometry(t, clock.ns, 0.001, 0.0)
        agent.fusion.add_gyro(clock.ns, 0.0)
        t = clock.ns
    flags = agent.flags()
    assert flags & PoseFlags.ODOMETRY and flags & PoseFlags.IMU, flags
