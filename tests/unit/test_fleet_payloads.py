"""The fleet's network payloads (agent.fleet.payloads): JSON with a schema version, decoded strictly."""

from __future__ import annotations

import contextlib
import json
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.fleet import payloads
from agent.fleet.local_protocol import GoalMessage, GoalStateMessage, PoseMessage, StatusMessage
from firmware_protocol.errors import ProtocolError

POSE = PoseMessage(10, 1.5, 2.5, -0.5, 0.01, math.nan, 3)


def test_pose_round_trip_with_an_unknown_sigma() -> None:
    data = payloads.encode_pose("r1", POSE)
    obj = json.loads(data)
    assert obj["v"] == payloads.SCHEMA and obj["robot"] == "r1" and obj["sigma_yaw_rad"] is None
    back = payloads.decode_pose(data, "r1")
    assert (back.x_m, back.y_m, back.yaw_rad, back.flags) == (1.5, 2.5, -0.5, 3)
    assert math.isnan(back.sigma_yaw_rad)


def test_status_round_trip_and_state() -> None:
    status = StatusMessage(5, 1, StatusMessage.READY | StatusMessage.LOCALIZED)
    seen = payloads.decode_status(payloads.encode_status("r1", status, {"rejected_goal": 2}), "r1")
    assert seen.state == "ready" and seen.counters == {"rejected_goal": 2} and seen.agent_connected
    down = payloads.decode_status(payloads.encode_status("r1", None, {}), "r1")
    assert down.state == "agent-down"


def test_goal_and_goal_state() -> None:
    goal = payloads.decode_goal(payloads.encode_goal("r1", GoalMessage(0, 7, 1.0, 2.0)), "r1")
    assert goal.goal_id == 7 and math.isnan(goal.yaw_rad)
    state = json.loads(payloads.encode_goal_state("r1", GoalStateMessage(1, 7, 3, 0)))
    assert state["remaining_m"] is None and state["state"] == 3


@pytest.mark.parametrize(
    "data",
    [
        b"",
        b"\xff\xfe",
        b"[1, 2]",
        b'{"v": 2, "robot": "r1", "goal_id": 1, "x_m": 0, "y_m": 0}',
        b'{"v": 1, "robot": "r2", "goal_id": 1, "x_m": 0, "y_m": 0}',  # another robot's goal
        b'{"v": 1, "robot": "r1", "goal_id": 70000, "x_m": 0, "y_m": 0}',
        b'{"v": 1, "robot": "r1", "goal_id": 1, "x_m": NaN, "y_m": 0}',
        b'{"v": 1, "robot": "r1", "goal_id": 1, "x_m": "1", "y_m": 0}',
        b'{"v": 1, "robot": "r1", "goal_id": true, "x_m": 1, "y_m": 0}',
        b'{"v": 1, "robot": "r1", "goal_id": 1, "x_m": 1e999, "y_m": 0}',
        b"[" * 100_000,
        b'{"v": 1, "robot": "r1", "pad": "' + b"x" * payloads.MAX_PAYLOAD + b'"}',
    ],
)
def test_malformed_goals_are_refused(data: bytes) -> None:
    with pytest.raises(payloads.FleetPayloadError):
        payloads.decode_goal(data, "r1")


@pytest.mark.parametrize(
    "key", ["fleet/r1", "fleet/r1/pose/x", "other/r1/pose", "fleet/a b/pose", "fleet//pose"]
)
def test_keys_that_are_not_fleet_keys(key: str) -> None:
    with pytest.raises(payloads.FleetPayloadError):
        payloads.robot_of("fleet", key)


def test_robot_of_with_a_nested_prefix() -> None:
    assert payloads.robot_of("site/a/fleet", "site/a/fleet/r-9/pose") == "r-9"


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=200), st.text(max_size=200).map(str.encode)))
def test_garbage_decodes_or_raises_protocol_error(data: bytes) -> None:
    for decode in (payloads.decode_pose, payloads.decode_goal, payloads.decode_status):
        with contextlib.suppress(ProtocolError):
            decode(data, "r1")


def test_a_goals_leave_into_unknown_space_goes_through_and_must_be_a_bool() -> None:
    goal = GoalMessage(0, 7, 1.0, 2.0, options=GoalMessage.ALLOW_UNKNOWN)
    assert payloads.decode_goal(payloads.encode_goal("r1", goal), "r1").allow_unknown
    bad = b'{"v":1,"robot":"r1","goal_id":1,"x_m":0,"y_m":0,"yaw_rad":null,"allow_unknown":1}'
    with pytest.raises(payloads.FleetPayloadError, match="allow_unknown"):
        payloads.decode_goal(bad, "r1")
