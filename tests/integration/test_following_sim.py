"""Person following's pieces in the running agent on the simulated robot (``follow_straight``): the forward
camera's frames stay in the process and a stall of it is flagged, survived and recovered from while the pose
stream carries on; the RFID coarse layer runs on the two-antenna reader's reads."""

from __future__ import annotations

from pathlib import Path

from tests.helpers import example_config, run_sim


def test_forward_camera_stall_is_survived_and_the_coarse_layer_runs(tmp_path: Path) -> None:
    config = example_config(
        tmp_path / "follow.toml",
        world="follow_straight.toml",
        replace=(('backend = "id12la"', 'backend = "mercury"'),),
        append=(
            '\n[camera.forward]\nrender_process = true\n\n[following]\ntag_id = "E2000017221101441890ABCD"\n'
        ),
    )
    s = run_sim(
        "--config",
        str(config),
        "--seconds",
        "10",
        "--fault",
        "forward_camera@3+3",
        "--out",
        str(tmp_path / "out"),
        timeout_s=240,
    )
    forward = s["devices"]["forward_camera"]
    # Stalled for 3 s: reported (a timeout per stall period), then recovered and healthy at the end.
    assert s["counts"]["forward_frame_timeouts"] >= 2 and forward["failures"] >= 1
    assert forward["recoveries"] >= 1 and forward["ok"]
    assert s["counts"]["forward_frames"] > 20
    # The pose stream went on through it, on VLP.
    assert s["frames_out"] > 100 and s["fixes_fused"] > 50
    # The coarse layer closed its read cycles on the user's tag.
    following = s["following"]
    assert following is not None and following["cycles"] >= 20
    assert 0.0 <= following["p_absent"] <= 1.0 and following["spread_deg"] >= 0.0
