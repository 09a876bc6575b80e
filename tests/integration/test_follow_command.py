"""Following on command on the simulated robot: the simulated controller sends a follow start frame, the
agent answers ACCEPTED and reports how following goes (ACTIVE statuses of the follow id), then a follow stop
ends it (CANCELLED) and the follow loop goes idle. No timing or distance asserted: under load the person may
not be found before the stop; the protocol's answers are what is checked."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import EXAMPLES, run_sim

FOLLOW_REASONS = {"FOLLOWING", "SEARCHING", "PERSON_LOST", "TAG_ABSENT", "NOT_LOCALIZED"}


def test_following_is_started_and_stopped_by_command_frames(tmp_path: Path) -> None:
    s = run_sim(
        "--config",
        str(EXAMPLES / "follow.toml"),
        "--follow-fine",
        "off",
        "--send-follow",
        "start",
        "--send-follow",
        "stop@2",
        "--seconds",
        "60",  # a bound only: the run ends a second after the stop is answered
        "--out",
        str(tmp_path / "out"),
        timeout_s=240,
    )
    statuses = s["follow_commands"]
    assert statuses[0] == "1 ACCEPTED NONE"
    assert statuses[-1] == "1 CANCELLED NONE"
    active = [line.split() for line in statuses[1:-1]]
    assert active and all(st == "ACTIVE" and reason in FOLLOW_REASONS for _, st, reason in active)
    control = s["follow_control"]
    assert control["set_up"] and control["following"] is None and control["counts"]["followings"] == 1
    follow = s["follow"]
    assert follow["counts"]["restarts"] == 1 and follow["counts"]["steps"] > 0
    assert s["goals"] is None
