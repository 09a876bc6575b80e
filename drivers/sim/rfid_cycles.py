"""The simulated Mercury reader on a stepped clock, read through its bytes: read cycles with ground truth.

For calibration in simulation (``vlp-agent calibrate rfid --sim``), tests and evaluations that need
minutes of reads in seconds: the world runs on a clock this module steps, the fake reader
(:class:`drivers.fakes.rfid.FakeRfidReader`) gets the host's commands as bytes (antenna search list, start
of the continuous read) and its stream is decoded by the same codec the driver uses
(``firmware_protocol.rfid``), so what comes out is what the driver would hand the agent, without a pty or
the wall clock.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

from drivers.fakes.rfid import FakeRfidReader
from drivers.samples import TagRead
from drivers.sim.simulation import Simulation
from drivers.sim.world import Pose2D, World
from firmware_protocol.rfid import (
    MercuryResponseDecoder,
    MercuryTagRead,
    decode_stream_message,
    encode_set_antenna_search_list,
    encode_start_continuous_read,
)

__all__ = ["ReadCycle", "TruthBearing", "read_cycles"]


@dataclass(frozen=True, slots=True)
class TruthBearing:
    """Where a person is from the robot's base at the end of a cycle: range and bearing (CCW from
    forward), and whether they are within the reader's ``range_m``."""

    range_m: float
    bearing_rad: float


@dataclass(frozen=True, slots=True)
class ReadCycle:
    """One read cycle: the reads that arrived in it, the robot's pose and every person's truth at its end."""

    t_s: float
    reads: tuple[TagRead, ...]
    pose: Pose2D
    truth: dict[str, TruthBearing]


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def read_cycles(
    world: World,
    *,
    duration_s: float,
    cycle_s: float = 0.25,
    ports: tuple[int, ...] = (1, 2),
    seed: int = 0,
    step_s: float = 0.02,
    drive: Callable[[Simulation, float], None] | None = None,
) -> Iterator[ReadCycle]:
    """Run ``world`` for ``duration_s`` of simulated time and yield one :class:`ReadCycle` per ``cycle_s``.

    ``drive(sim, t)``: called every step to move the robot (``sim.set_body_velocity``); the robot stands
    still without it. ``ports``: the antenna search list the host sends.
    """
    clock = _Clock()
    sim = Simulation(world, clock=clock, seed=seed)
    fake = FakeRfidReader(sim, "mercury", seed=seed)
    decoder = MercuryResponseDecoder()
    fake.receive(encode_set_antenna_search_list([(p, p) for p in ports]), 0.0)
    decoder.feed(fake.receive(encode_start_continuous_read(), 0.0))
    reads: list[TagRead] = []
    cycle_end = cycle_s
    steps = math.ceil(duration_s / step_s)
    for k in range(1, steps + 1):
        clock.t = k * step_s
        if drive is not None:
            drive(sim, clock.t)
        for response in decoder.feed(fake.poll(clock.t)):
            message = decode_stream_message(response)
            if isinstance(message, MercuryTagRead):
                reads.append(
                    TagRead(
                        message.epc_hex,
                        round(clock.t * 1e9),
                        "sim-mercury",
                        float(message.rssi_dbm),
                        message.rx_antenna,
                        message.frequency_khz,
                        float(message.phase_deg),
                    )
                )
        if clock.t + 1e-9 >= cycle_end:
            pose = sim.pose()
            truth = {}
            for person in world.people:
                px, py = sim.person_position(person)
                dx, dy = px - pose.x_m, py - pose.y_m
                bearing = math.atan2(dy, dx) - pose.yaw_rad
                truth[person.name] = TruthBearing(
                    math.hypot(dx, dy), math.atan2(math.sin(bearing), math.cos(bearing))
                )
            yield ReadCycle(clock.t, tuple(reads), pose, truth)
            reads = []
            cycle_end += cycle_s
