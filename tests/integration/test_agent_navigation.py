"""The whole agent drives itself: ``vlp-agent sim --goal`` through three goals across rooms of the office,
sent as goal command frames on the pose stream's pty by the simulated controller, with people walking the
corridor. Every goal is reached, no wall is touched, and the goal statuses the agent sent back are read by
the reference C decoder (``firmware_protocol/c/command_frame.c``) from the bytes the controller received.

No contact with walls or people: the robot gives way to the walkers (``agent/navigation/give_way.py``),
and they, as pedestrians, stop for the robot standing in their way (``drivers/sim/pedestrians.py``); any
overlap of the footprints counts, whoever moved.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from tests.helpers import run_sim
from tests.unit.test_c_decoder import STRICT

REPO = Path(__file__).resolve().parents[2]
C_DIR = REPO / "firmware_protocol" / "c"
# Corridor -> S2 (through its north door) -> S3 (through the connecting door) -> N3 (across the corridor,
# where a person walks up and down).
GOALS = ["7.5,2.5", "12.5,2.5,90", "12.5,9.5"]


def test_three_goals_across_rooms_are_reached_without_contact(tmp_path: Path) -> None:
    received = tmp_path / "received.bin"
    # At most 400 s of simulation; the run ends as soon as the last goal has ended (about 170 s).
    args = ["--seconds", "400", "--out", str(tmp_path), "--controller-record", str(received)]
    for goal in GOALS:
        args += ["--goal", goal]
    summary = run_sim(*args, timeout_s=900)
    goals = summary["goals"]
    context = f"goals {goals}, commands {summary['commands']}"
    assert goals["sent"] == 3 and goals["reached"] == 3 and goals["all_ended"], context
    assert summary["collisions_walls"] == 0, summary["clearance_wall_m_min"]
    assert summary["collisions_people"] == 0, summary["clearance_person_m_min"]
    assert summary["frames_rejected_by_receiver"] == 0

    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc not found: the C decoder cannot check the goal statuses")
    binary = tmp_path / "test_command_frame"
    sources = [C_DIR / "test_command_frame.c", C_DIR / "command_frame.c", C_DIR / "pose_frame.c"]
    build = subprocess.run([gcc, *STRICT, "-O2", "-o", str(binary), *map(str, sources)], capture_output=True)
    assert build.returncode == 0, build.stderr
    decoded = subprocess.run(
        [str(binary), str(received)], capture_output=True, text=True, timeout=60, check=False
    )
    assert decoded.returncode == 0, decoded.stderr
    rows = [line.split(",") for line in decoded.stdout.splitlines()[1:]]
    reached = [int(goal_id) for _, _, goal_id, state, *_ in rows if int(state) == 3]  # GOAL_REACHED
    assert reached == [1, 2, 3]
    assert len(rows) == goals["statuses_decoded"]  # C and Python read the same statuses
    stats = dict(item.split("=") for item in decoded.stderr.split())
    assert int(stats["pose_frames"]) == summary["frames_received"]
    assert all(int(stats[k]) == 0 for k in ("crc_errors", "cobs_errors", "type_errors", "length_errors"))
