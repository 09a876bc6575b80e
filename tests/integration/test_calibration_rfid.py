"""`vlp-agent calibrate rfid --sim`: the scripted walk round the robot fits a likelihood table that the
robot config then reads (``[following] rfid_table``); a world whose reader has no antennas is refused."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from agent.config import parse_config
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]


def calibrate(tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "rfid",
            "--sim",
            "--json",
            "--dir",
            str(tmp_path),
            *args,
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,
        text=True,
        timeout=180,
        cwd=REPO,
        check=False,
    )


def test_the_walk_fits_a_table_the_config_reads(tmp_path: Path) -> None:
    world = REPO / "examples" / "worlds" / "follow_left_turn.toml"
    out = calibrate(tmp_path, "--world", str(world), "--seed", "3")
    assert out.returncode == 0, out.stderr[-3000:]
    r = strict_loads(out.stdout)
    assert r["ok"] and r["coverage"] >= 0.9, r
    # Both antennas read the tag most cycles; their RSSI difference follows the bearing, loosely.
    assert min(r["read_rate_per_port"]) > 0.8
    assert 0.3 < r["left_right_correlation"] < 0.9
    table_file = tmp_path / "rfid_table.toml"
    assert table_file.is_file() and (tmp_path / "rfid_table.png").is_file()
    config = parse_config(
        f'[servos]\nbackend = "dynamixel"\nport = "/dev/x"\n[output]\nurl = "/dev/y"\n'
        f'[following]\ntag_id = "E2000017221101441890ABCD"\nrfid_table = "{table_file}"\n'
    )
    table = config.following.table
    assert table.source == "calibrated" and table.ports == (1, 2) and table.grid.n_sectors == 16


def test_a_reader_without_antennas_is_refused(tmp_path: Path) -> None:
    out = calibrate(tmp_path)  # the default world, env1: a 125 kHz reader
    assert out.returncode == 1
    assert "no antennas to calibrate" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "rfid_table.toml").exists()
