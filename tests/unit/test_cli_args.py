"""The command line refuses what cannot be meant, before anything runs: durations that are not above zero,
faults at impossible times; ``-v`` goes after the command as well as before; JSON is strict."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agent import cli
from agent.commands.args import dumps_json


def strict_loads(text: str) -> Any:
    def refuse(token: str) -> Any:
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.parametrize("seconds", ["0", "-1", "nan", "inf", "-inf", "soon"])
@pytest.mark.parametrize(
    "command", [["sim"], ["run", "--config", "robot.toml"], ["eval", "slam", "--world", "env1.toml"]]
)
def test_seconds_must_be_a_finite_number_above_zero(
    command: list[str], seconds: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        cli.main([*command, "--seconds", seconds])
    assert exit_.value.code == 2
    assert "argument --seconds" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # nothing written


@pytest.mark.parametrize(
    "spec", ["laser@nan", "laser@inf+1", "laser@1+inf", "camera@1+nan", "laser@-1", "camera@2+0", "wheel@3"]
)
def test_a_fault_at_an_impossible_time_is_a_usage_error(spec: str, capsys: Any) -> None:
    with pytest.raises(SystemExit) as exit_:
        cli.main(["sim", "--fault", spec])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "argument --fault" in err and spec in err


@pytest.mark.parametrize("spec", ["laser@10", "servo@5+1"])
def test_a_fault_after_the_end_of_the_run_is_refused_before_it_starts(
    spec: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: Any
) -> None:
    monkeypatch.chdir(tmp_path)
    code = cli.main(["sim", "--seconds", "5", "--fault", spec])
    assert code == 2
    err = capsys.readouterr().err
    assert err.startswith("usage: vlp-agent sim")
    assert "starts after the run ends (--seconds 5)" in err
    assert list(tmp_path.iterdir()) == []  # the robot never started, nothing written


@pytest.mark.parametrize(
    ("argv", "level"),
    [
        (["devices"], 0),
        (["-v", "devices"], 1),
        (["devices", "-v"], 1),
        (["-v", "devices", "-v"], 2),
        (["eval", "vlp", "-vv"], 2),
        (["calibrate", "leds", "-v"], 1),
        (["calibrate", "-v", "leds"], 1),
    ],
)
def test_verbose_goes_before_or_after_the_command(argv: list[str], level: int) -> None:
    args = cli.build_parser(argv).parse_args(argv)
    assert args.verbose + getattr(args, "verbose_after", 0) == level


def test_json_output_is_strict_nan_and_infinity_become_null() -> None:
    value = {
        "a": math.nan,
        "b": [1.0, math.inf, {"c": -math.inf}],
        "d": (np.float64("nan"), np.float32(2.5), np.int64(3)),
        "e": np.array([1.0, np.nan]),
        "f": "NaN",
    }
    text = dumps_json(value, sort_keys=True)
    assert strict_loads(text) == {
        "a": None,
        "b": [1.0, None, {"c": None}],
        "d": [None, 2.5, 3],
        "e": [1.0, None],
        "f": "NaN",
    }
    with pytest.raises(ValueError, match="non-standard"):
        strict_loads(json.dumps({"a": math.nan}))  # what the commands printed before


def test_sim_help_names_the_config_it_loads(capsys: Any) -> None:
    from agent.commands.sim import DEFAULT_CONFIG

    with pytest.raises(SystemExit):
        cli.main(["sim", "--help"])
    text = "".join(capsys.readouterr().out.split())  # argparse wraps long paths
    assert f"(default:{DEFAULT_CONFIG})" in text
    assert DEFAULT_CONFIG.is_file()


def test_calibrate_help_shows_the_step_as_optional(capsys: Any) -> None:
    with pytest.raises(SystemExit):
        cli.main(["calibrate", "--help"])
    usage = capsys.readouterr().out.splitlines()[0]
    assert usage == "usage: vlp-agent calibrate [options] [STEP [step options]]"
    # And indeed optional: without a step the parser gives the wizard (step None).
    assert cli.build_parser(["calibrate"]).parse_args(["calibrate", "--sim"]).step is None


def test_default_outputs_in_the_current_folder_are_ignored_by_git() -> None:
    import shutil
    import subprocess

    from calibration.context import DEFAULT_DIR

    repo = Path(__file__).resolve().parents[2]
    if shutil.which("git") is None or not (repo / ".git").exists():
        pytest.skip("not a git checkout")
    sim_out = cli.build_parser(["sim"]).parse_args(["sim"]).out
    written = [
        f"{sim_out}/trajectory.png",  # vlp-agent sim
        f"{DEFAULT_DIR}/wheels.toml",  # vlp-agent calibrate without --dir
        "vlp_eval_env1.png",  # vlp-agent eval vlp without --png
        "eval-slam-env1-vlp/map.pgm",  # vlp-agent eval slam --world env1 --vlp-fixes without --out
    ]
    for path in written:
        check = subprocess.run(["git", "check-ignore", "-q", path], cwd=repo, check=False)
        assert check.returncode == 0, f"{path} is not in .gitignore"
