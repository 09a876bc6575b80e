"""``vlp-agent eval slam`` end to end on short slices of the real logs: the JSON, the table, the files."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from agent import figure
from agent.cli import main
from agent.slam.mapio import load_map
from tests.figures import has_colour, has_swatch


def test_eval_slam_json_on_radish(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = shared_data / "slam/radish/intel_scans.txt"
    out = tmp_path / "intel"
    code = main(
        [
            "eval",
            "slam",
            "--log",
            str(log),
            "--format",
            "radish",
            "--particles",
            "5",
            "--scans",
            "60",
            "--span",
            "20",
            "--out",
            str(out),
            "--json",
        ]
    )
    assert code == 0
    summary = json.loads(capsys.readouterr().out)
    for key in ("update_ms_median", "update_ms_p95", "wall_s", "realtime_factor", "peak_rss_mb", "updates"):
        assert isinstance(summary[key], (int, float)) and summary[key] > 0, key
    assert summary["scans"] == 60 and summary["particles"] == 5
    assert summary["relations"] == 59
    # Over 60 scans the filter follows GMapping's poses closer than raw odometry does.
    assert summary["trans_error_m_mean"] < summary["odometry_trans_error_m_mean"]
    assert summary["rot_error_deg_mean"] < summary["odometry_rot_error_deg_mean"]
    assert summary["trans_error_m_mean"] < 0.1
    # Pairs 20 scans apart: Intel's raw odometry is metres and tens of degrees off over them (6.4 m,
    # 56 deg), the filter a few decimetres.
    assert summary["span_scans"] == 20
    assert summary["span_trans_error_m_mean"] < 0.1 * summary["odometry_span_trans_error_m_mean"]
    assert summary["span_rot_error_deg_mean"] < 0.1 * summary["odometry_span_rot_error_deg_mean"]
    # Global consistency against the reference poses: the aligned ATE and the pairs over 10 m apart, both
    # far below raw odometry's.
    assert summary["ate_aligned_m"] < 0.2 * summary["odometry_ate_aligned_m"]
    assert summary["relations_over_10m"] > 100
    assert summary["relation_over_10m_m"] < 0.2 * summary["odometry_relation_over_10m_m"]
    # The turns against the reference's (a scale of turning) and where the odometry turns about.
    assert 0.9 < summary["turn_ratio"] < 1.1 and summary["odometry_turn_ratio"] > 0.9
    # Intel's odometry turns about a point behind the laser (0.07 m over these 60 scans, ~0.094 m over all).
    assert 0.03 < summary["turning_point_m"][0] < 0.15 and abs(summary["turning_point_m"][1]) < 0.05
    assert summary["loop_closure"] == "on" and summary["loop_checks"] >= 1
    assert summary["loop_closures"] >= summary["loop_rebuilds"] >= 0
    # The final optimisation runs where a loop factor holds the chain (else -1: not run).
    factors = summary["loop_closures"] + summary["loop_agreeing"]
    assert (summary["final_scan_edges"] >= 0) == (factors > 0)
    image = load_map(out / "map.yaml")
    assert image.pixels.shape[0] > 100 and image.occupied_mask().sum() > 500
    assert (out / "map.png").read_bytes()[:4] == b"\x89PNG"
    (pgm,) = out.glob("map.*.pgm")  # the image version the YAML names
    assert f"image: {pgm.name}\n" in (out / "map.yaml").read_text()
    # The log's reference poses in the truth's colour, under the estimate, named in the legend.
    trajectory = cv2.imread(str(out / "trajectory.png"))
    assert trajectory is not None and trajectory.shape[1] >= 800
    for colour in (figure.TRUTH, figure.SLAM, figure.ODOMETRY):
        assert has_swatch(trajectory, colour), colour
        assert has_colour(trajectory, colour, 100), colour
    assert sorted(summary["files"]) == sorted(
        str(out / n) for n in ("map.yaml", pgm.name, "map.png", "trajectory.png")
    )


def test_eval_slam_table_on_breezyslam(
    shared_data: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = shared_data / "slam/breezyslam/exp1.dat"
    code = main(
        [
            "eval",
            "slam",
            "--log",
            str(log),
            "--format",
            "breezyslam",
            "--particles",
            "4",
            "--scans",
            "80",
            "--map-mode",
            "shared",
            "--odometry-noise",
            "0.1",
            "0.1",
            "0.1",
            "0.1",
            "--out",
            str(tmp_path),
        ]
    )
    assert code == 0
    captured = capsys.readouterr()
    assert "update time        median" in captured.out
    assert "particles          4 (shared maps)" in captured.out
    assert "relative error" not in captured.out  # exp1 has no reference poses
    assert "scan 80/80" in captured.err  # progress goes to stderr
    first = load_map(tmp_path / "map.yaml").pixels
    # The pictures: the map enlarged to a readable size, the paths over it in the shared colours, with a
    # legend; map.pgm stays the map itself, cell for cell.
    for name, colours in (
        ("map.png", (figure.SLAM, (0, 0, 0))),
        ("trajectory.png", (figure.SLAM, figure.ODOMETRY, (0, 0, 0))),
    ):
        picture = cv2.imread(str(tmp_path / name))
        assert picture is not None and picture.shape[1] >= 800, name
        for colour in colours:
            assert has_swatch(picture, colour), (name, colour)
        assert has_colour(picture, figure.SLAM, 100), name
    (pgm,) = tmp_path.glob("map.*.pgm")  # the image version the YAML names
    assert first.shape == cv2.imread(str(pgm), cv2.IMREAD_UNCHANGED).shape
    # A second run keeps the first map as map.prev.*.
    main(
        [
            "eval",
            "slam",
            "--log",
            str(log),
            "--format",
            "breezyslam",
            "--particles",
            "2",
            "--scans",
            "30",
            "--out",
            str(tmp_path),
            "--json",
        ]
    )
    np.testing.assert_array_equal(load_map(tmp_path / "map.prev.yaml").pixels, first)
    assert load_map(tmp_path / "map.yaml").pixels.shape != first.shape  # 30 scans map less than 80


def test_eval_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.dat"
    bad.write_text("1 2 3\n")
    assert main(["eval", "slam", "--log", str(bad), "--format", "breezyslam", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert f"{bad}:1: truncated line" in err and "Traceback" not in err
    assert main(["eval", "slam", "--log", str(tmp_path / "none.dat"), "--format", "breezyslam"]) == 1
    assert "cannot read the log" in capsys.readouterr().err


def test_eval_without_what_says_what(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["eval"]) == 2
    assert "slam" in capsys.readouterr().out


def tiny_log(folder: Path) -> Path:
    """A two-record radish log: enough for the CLI to check and report its options."""
    log = folder / "tiny_scans.txt"
    ranges = " ".join(["2.0"] * 180)
    log.write_text(f"0.0 0 0 0 0 0 0 180 {ranges}\n1.0 0.1 0 0 0.1 0 0 180 {ranges}\n")
    return log


def test_eval_span_must_be_a_scan_or_more(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tiny_log(tmp_path)
    args = ["eval", "slam", "--log", str(log), "--format", "radish", "--out", str(tmp_path / "out")]
    assert main([*args, "--span", "0"]) == 1
    err = capsys.readouterr().err
    assert "--span: must be at least 1 scan, got 0" in err and "Traceback" not in err


def test_eval_degenerate_noise_scale_is_checked_and_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tiny_log(tmp_path)
    args = ["eval", "slam", "--log", str(log), "--format", "radish", "--out", str(tmp_path / "out"), "--json"]
    for bad in ("0", "1.5"):
        assert main([*args, "--degenerate-noise-scale", bad]) == 1
        err = capsys.readouterr().err
        assert "--degenerate-noise-scale: must be in (0, 1]" in err and "Traceback" not in err
    assert main(args) == 0
    assert json.loads(capsys.readouterr().out)["degenerate_noise_scale"] == 1.0  # radish: the paper's draw
    assert main([*args, "--degenerate-noise-scale", "0.15"]) == 0
    assert json.loads(capsys.readouterr().out)["degenerate_noise_scale"] == 0.15


def test_eval_edge_information_is_checked_and_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tiny_log(tmp_path)
    args = ["eval", "slam", "--log", str(log), "--format", "radish", "--out", str(tmp_path / "out"), "--json"]
    for bad, message in (
        (["--edge-information", "normals"], "--edge-information: needs --edge-match-sigma"),
        (["--edge-match-sigma", "0"], "--edge-match-sigma: must be in (0, 1] metres"),
        (["--edge-departure-floor"], "--edge-departure-floor: needs --edge-match-sigma"),
        (
            ["--edge-match-sigma", "0.3", "--edge-normal-radius-per-m", "0.1"],
            "--edge-normal-radius-per-m: needs --edge-information normals or scan",
        ),
        (
            ["--edge-match-sigma", "0.3", "--edge-scan-mean"],
            "--edge-scan-mean: needs --edge-information scan",
        ),
        (
            ["--edge-match-sigma", "0.3", "--edge-scan-coarse-iterations", "5"],
            "--edge-scan-coarse-iterations: needs --edge-information scan",
        ),
        (
            ["--edge-match-sigma", "0.3", "--edge-information", "scan", "--edge-scan-gate-chi2", "5"],
            "--edge-scan-gate-chi2: needs --edge-scan-mean",
        ),
        (
            ["--edge-match-sigma", "0.3", "--edge-scan-fallback"],
            "--edge-scan-fallback: needs --edge-information scan",
        ),
        (
            ["--edge-match-sigma", "0.3", "--loop-closure", "off"],
            "--edge-match-sigma: needs --loop-closure on",
        ),
    ):
        assert main([*args, *bad]) == 1
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["edge_match_sigma_m"] is None and summary["edge_information"] == "match"
    assert main([*args, "--edge-match-sigma", "0.3", "--edge-information", "normals"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["edge_match_sigma_m"] == 0.3 and summary["edge_information"] == "normals"
    assert main([*args, "--edge-match-sigma", "0.3", "--edge-information", "scan", "--edge-scan-mean"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["edge_information"] == "scan" and summary["edge_scan_mean"] is True


def test_eval_medial_window_is_checked_and_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tiny_log(tmp_path)
    args = ["eval", "slam", "--log", str(log), "--format", "radish", "--out", str(tmp_path / "out"), "--json"]
    assert main([*args, "--medial-window-cells", "9"]) == 1
    err = capsys.readouterr().err
    assert "--medial-window-cells: must be in [0, 8]" in err and "Traceback" not in err
    assert main(args) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["medial_window_cells"] == 0
    assert len(summary["grid_phase_m"]) == 2 and all(0.0 <= p < 0.05 for p in summary["grid_phase_m"])
    assert main([*args, "--medial-window-cells", "3"]) == 0
    assert json.loads(capsys.readouterr().out)["medial_window_cells"] == 3
