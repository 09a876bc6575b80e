"""The SLAM filter on the simulated robot, against ground truth: the first 60 s of the office route.

The robot drives 10 m: the corridor east, through a door into a room, along it; the scans come from the
world's URG-04LX model, the odometry from wheels that err (``agent.slam.simlog``). Over that stretch raw
odometry is 15 cm off (RMS); the acceptance run (5 minutes, ``vlp-agent eval slam --world
examples/worlds/office.toml``) holds the same bounds over 52 m and a loop and a half (docs/slam.md).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent import figure
from agent.cli import main
from agent.commands.sim_fixes import PipelineFixes
from agent.slam.logs import LogRecord, SlamLog
from agent.slam.metrics import absolute_trajectory_error
from agent.slam.pose import compose
from agent.slam.rbpf import RbpfConfig
from agent.slam.replay import ReplayResult, replay
from agent.slam.scan import Rejection
from agent.slam.simlog import MOTION_NOISE, SimulatedRun, simulate_log
from drivers.sim.worldfile import load_world
from tests.figures import has_swatch

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"
SECONDS = 60.0


@pytest.fixture(scope="module")
def drive() -> SimulatedRun:
    return simulate_log(load_world(OFFICE), SECONDS, seed=0)


@pytest.fixture(scope="module")
def camera_drive() -> SimulatedRun:
    """The same drive with its fixes from rendered frames through the VLP pipeline."""
    world = load_world(OFFICE)
    return simulate_log(world, SECONDS, fixes=PipelineFixes(world, seed=0), seed=0)


def run_filter(drive: SimulatedRun, log: SlamLog | None = None, with_fixes: bool = False) -> ReplayResult:
    config = RbpfConfig(particles=30, noise=MOTION_NOISE, initial_pose=drive.start_pose(from_fix=with_fixes))
    return replay(log or drive.log, config, fixes=drive.fixes if with_fixes else ())


def test_without_vlp_the_trajectory_stays_within_5_cm(drive: SimulatedRun) -> None:
    result = run_filter(drive)
    odometry_ate = absolute_trajectory_error(drive.truth, drive.odometry_in_world())
    ate = absolute_trajectory_error(drive.truth, result.poses)
    assert odometry_ate > 0.1
    assert ate < 0.05
    # 4.2 cm against odometry's 15.4 cm. With walkers who never stop the same drive gives 2.1 cm, but
    # without any people also 4.2 cm: the standing people are not the cause, moving ones change the scans
    # and so the filter's draws (docs/slam.md, "Open problems").
    assert ate < odometry_ate / 3
    assert np.max(np.hypot(*(result.poses[:, :2] - drive.truth[:, :2]).T)) < 0.1
    assert result.slam.stats.fixes_applied == 0


def test_with_vlp_fixes_the_trajectory_stays_within_15_mm(drive: SimulatedRun) -> None:
    result = run_filter(drive, with_fixes=True)
    # 10 Hz; those after the last filter update are still pending.
    assert len(drive.fixes) > 500
    assert 0 <= len(drive.fixes) - result.slam.stats.fixes_applied < 20
    assert absolute_trajectory_error(drive.truth, result.poses) < 0.015
    assert absolute_trajectory_error(drive.truth, result.online_poses) < 0.015


def test_with_fixes_from_the_camera_pipeline_the_trajectory_stays_within_15_mm(
    camera_drive: SimulatedRun,
) -> None:
    # The office repeats LED ids: the pipeline tells them apart by the prior (the last fix carried by
    # odometry), so every fix must land where the robot was, none at another place with the same ids.
    fixes = camera_drive.fixes
    assert len(fixes) > 450  # 600 camera instants; one LED in view leaves some without a fix
    xy = np.array([(f.fix.x_m, f.fix.y_m) for f in fixes])
    fix_error = np.hypot(*(xy - camera_drive.fix_truth[:, :2]).T)
    assert np.mean(fix_error) < 0.008 and np.max(fix_error) < 0.03
    assert sum(camera_drive.no_fix_reasons.values()) == camera_drive.frames_without_fix
    result = run_filter(camera_drive, with_fixes=True)
    assert absolute_trajectory_error(camera_drive.truth, result.poses) < 0.015
    assert absolute_trajectory_error(camera_drive.truth, result.online_poses) < 0.015


def test_bad_scans_are_rejected_and_the_filter_carries_on(drive: SimulatedRun) -> None:
    records = list(drive.log.records)
    nan = records[100].ranges_m.copy()
    nan[300] = np.nan
    records[100] = dataclasses.replace(records[100], ranges_m=nan)
    records[150] = dataclasses.replace(records[150], ranges_m=np.zeros_like(records[150].ranges_m))
    records[200] = dataclasses.replace(records[200], ranges_m=records[200].ranges_m[:-10])
    records[250] = dataclasses.replace(records[250], t_s=records[248].t_s)
    # The laser's pose jumps 3 m in the odometry at scan 300 and stays there: the filter drops the jump.
    jump = np.array([3.0, 0.0, 0.0])
    records[300:] = [dataclasses.replace(r, odom_pose=compose(jump, r.odom_pose)) for r in records[300:]]
    faulty = dataclasses.replace(drive.log, records=tuple(records))
    result = run_filter(drive, faulty)
    assert dict(result.rejections) == {
        Rejection.NON_FINITE.value: 1,
        Rejection.NO_RETURNS.value: 1,
        Rejection.BEAM_COUNT.value: 1,
        Rejection.TIME_BACKWARDS.value: 1,
        Rejection.POSE_JUMP.value: 1,
    }
    kept = [i for i in range(len(records)) if i not in (100, 150, 200, 250, 300)]
    assert absolute_trajectory_error(drive.truth[kept], result.poses[kept]) < 0.05
    assert result.slam.stats.updates > 40


def test_the_command_reports_ate_with_and_without_fixes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    summaries = {}
    for vlp in (False, True):
        out = tmp_path / ("vlp" if vlp else "plain")
        args = ["eval", "slam", "--world", str(OFFICE), "--seconds", "15", "--json", "--out", str(out)]
        assert main([*args, "--vlp-fixes"] if vlp else args) == 0
        summaries[vlp] = json.loads(capsys.readouterr().out)
        assert (out / "map.yaml").is_file() and (out / "trajectory.png").stat().st_size > 1000
    plain, fixed = summaries[False], summaries[True]
    for s in (plain, fixed):
        assert s["format"] == "simulated" and s["scans"] == 150 and s["distance_m"] > 2.0
        assert s["odometry_noise"] == [0.03, 0.05, 0.03, 0.05]
        # Over these 15 s (2 m) odometry is still within 2 cm, and the filter without fixes about as good:
        # that it beats odometry four times over is checked on the 60 s drive above.
        assert 0.0 < s["ate_m"] < 0.05 and s["odometry_ate_m"] > 0.0
        assert 0.0 < s["ate_aligned_m"] <= s["ate_m"]  # the best rigid alignment is at least no alignment
        assert s["update_ms_median"] > 0 and s["peak_rss_mb"] > 0
        # The odometry of a robot through `calibrate wheels` (the wheels over-count 0.5 % on average), and
        # the same drive replayed with the design's geometry beside it.
        assert s["wheels"] == "calibrated" and s["wheel_radius_m"] == pytest.approx(0.033 / 1.005, rel=1e-3)
        assert s["ate_uncalibrated_m"] > 0.0
    assert plain["vlp_fixes"] is False and plain["fixes_used"] == 0
    # 10 Hz from the camera pipeline (the default source); a few still pending, a few instants with one
    # LED in view.
    assert fixed["vlp_fixes"] is True and fixed["fix_source"].startswith("pipeline")
    assert 100 < fixed["fixes_used"] <= 151 and fixed["fix_error_m_mean"] < 0.01
    assert fixed["ate_m"] < 0.015 and fixed["ate_m"] < fixed["odometry_ate_m"]


def test_the_command_maps_with_the_design_wheels_on_request(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["eval", "slam", "--world", str(OFFICE), "--seconds", "5", "--json", "--out", str(tmp_path)]
    assert main([*args, "--wheels", "nominal"]) == 0
    s = json.loads(capsys.readouterr().out)
    # The design's radius, and the track the odometry divides by (the effective one is 1 % wider).
    assert s["wheels"] == "nominal" and s["wheel_radius_m"] == pytest.approx(0.033)
    assert s["wheel_track_m"] == pytest.approx(0.16 / 1.01, abs=1e-6)
    assert "ate_uncalibrated_m" not in s and s["ate_m"] > 0.0
    # The picture names the truth once (the simulated log's reference poses are that truth).
    picture = cv2.imread(str(tmp_path / "trajectory.png"))
    samples = cv2.erode(
        np.all(picture == np.array(figure.TRUTH, np.uint8), axis=2).astype(np.uint8),
        np.ones((figure.SWATCH_PX[1], figure.SWATCH_PX[1]), np.uint8),
    )
    assert cv2.connectedComponents(samples)[0] - 1 == 1
    assert has_swatch(picture, figure.ODOMETRY) and has_swatch(picture, figure.SLAM)


def test_the_command_refuses_mixed_sources(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval", "slam", "--world", str(OFFICE), "--format", "radish", "--out", str(tmp_path)]) == 1
    assert "--format" in capsys.readouterr().err
    log = tmp_path / "x.dat"
    log.write_text("")
    assert main(["eval", "slam", "--log", str(log), "--format", "breezyslam", "--vlp-fixes"]) == 1
    assert "--vlp-fixes" in capsys.readouterr().err
    assert main(["eval", "slam", "--log", str(log)]) == 1
    assert "--format" in capsys.readouterr().err


def test_records_keep_their_truth(drive: SimulatedRun) -> None:
    # The log's reference poses are the simulation's truth at each scan: what the ATE is taken against.
    first: LogRecord = drive.log.records[0]
    assert first.reference_pose is not None
    np.testing.assert_allclose(first.reference_pose, drive.truth[0])
    # 10 Hz, the first scan once its sweep is whole (70 ms), the last before the drive ends.
    assert len(drive.log) == 600
    assert drive.log.duration_s == pytest.approx(SECONDS - 0.1, abs=0.01)
