"""``vlp-agent sim --follow`` on the straight-walk scenario: the robot locks on to the tagged user (not a
passer-by), drives after them without touching anyone, the forward camera's fine layer feeds the track,
a forward camera stall stops following with the state ``no_camera`` while the pose stream carries on, and
the summary carries the follow figures. Short, and no timing asserted (the figures against the acceptance
are measured by the runs in docs/following.md)."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import EXAMPLES, run_sim


def test_sim_follow_locks_on_to_the_user_and_follows_without_contact(tmp_path: Path) -> None:
    s = run_sim(
        "--config",
        str(EXAMPLES / "follow.toml"),
        "--follow",
        "--seconds",
        "14",
        "--fault",
        "forward_camera@9+2.5",
        "--out",
        str(tmp_path / "out"),
        timeout_s=300,
    )
    f = s["follow"]
    assert f["user"] == "user"
    assert f["tracker"]["acquired"] >= 1 and f["states"].get("state_following", 0) > 0
    assert f["followed"] == "user" and f["identity_switches"] == 0
    # The robot never drives into anyone. (The simulated walkers do not yield: on a starved machine a
    # passer-by can walk into the robot standing still; that contact is counted, not the robot's doing.)
    assert f["contacts_robot_moving"] == 0
    assert f["collisions_people"] <= 1 and s["collisions_people"] <= 1
    assert f["min_person_gap_m"] is not None
    if f["collisions_people"] == 0:
        # (With that one contact the gap is the walker's overlap with the robot at rest: -0.07 m in a
        # full-suite run where the robot stood for the camera stall and a passer-by walked on into it.)
        assert f["min_person_gap_m"] > 0.0
    assert s["distance_m"] > 1.0  # it drove after them
    for key in ("within_band", "distance_m_median", "time_lost_s", "stop_latency_s_max", "lost_events"):
        assert key in f
    for key in ("vanish_stop_s", "vanish_stop_command_s", "occluded_scans"):
        assert key in f
    # The camera's bearings reached the track; its stall stopped following (flagged), the pose went on.
    assert f["fine"].get("fine_bearings", 0) > 0
    assert f["fine"].get("fine_camera_stale", 0) > 0 and f["states"].get("state_no_camera", 0) > 0
    assert s["counts"]["forward_frame_timeouts"] >= 1
    assert s["frames_out"] > 100
