"""The follow loop on synthetic scans and a stepped clock (agent.runtime.follow_loop): it acquires the person
ahead, drives after them, and sends a stop on the first step after the track is lost."""

from __future__ import annotations

import math

import numpy as np

from agent.following.follower import Follower, FollowState
from agent.following.person import PersonTracker, TrackerConfig
from agent.runtime.follow_loop import FollowLoop
from drivers.samples import Scan
from drivers.sim.raycast import cast_rays

N = 682
INC = math.radians(240.0) / (N - 1)
WALLS = np.array([[0.0, 0.0, 12.0, 0.0], [12.0, 0.0, 12.0, 6.0], [12.0, 6.0, 0.0, 6.0], [0.0, 6.0, 0.0, 0.0]])


def make_scan(t_s: float, person: tuple[float, float] | None, seq: int) -> Scan:
    angles = -math.radians(120.0) + INC * np.arange(N)
    circles = np.array([[*person, 0.2]]) if person is not None else None
    r = cast_rays((1.0, 3.0), angles, WALLS, circles, 5.6)
    mm = np.where(np.isfinite(r), r * 1000.0, 0).astype(np.int32)
    return Scan(mm, -math.radians(120.0), INC, 20, 5600, seq, int(t_s * 1e9))


def test_it_follows_then_stops_on_the_first_step_after_the_person_is_lost() -> None:
    now = [0.0]
    sent: list[tuple[float, float]] = []
    loop = FollowLoop(
        Follower(),
        PersonTracker(TrackerConfig(lost_after_s=1.0)),
        (0.0, 0.0, 0.0),
        lambda: (1.0, 3.0, 0.0),  # the robot stands still here (the test moves only the person)
        lambda: None,  # no RFID reader: acquisition looks ahead
        lambda v, w: sent.append((v, w)),
        lambda: now[0],
    )
    seq = 0
    for k in range(20):  # 2 s: the person walks away from 2.5 m ahead at 0.7 m/s
        now[0] = k * 0.1
        loop.on_scan(make_scan(now[0], (3.5 + 0.7 * now[0], 3.0), seq))
        seq += 1
        snap = loop.step()
    assert snap.command.state is FollowState.FOLLOWING and snap.person is not None
    assert sent[-1][0] > 0.5  # far behind: closing in
    assert abs(snap.person.velocity[0] - 0.7) < 0.2
    # The person vanishes from the scans: the track coasts for lost_after_s, then the loop stops the robot.
    states = []
    for k in range(20, 40):
        now[0] = k * 0.1
        loop.on_scan(make_scan(now[0], None, seq))
        seq += 1
        snap = loop.step()
        states.append(snap.command.state)
        if snap.command.state is FollowState.LOST:
            assert sent[-1] == (0.0, 0.0)
            break
    assert states[-1] is FollowState.LOST
    assert now[0] <= 2.0 + 1.0 + 0.1 + 1e-9  # lost after the timeout, and stopped at that very step
