"""``vlp-agent bridge`` and ``vlp-agent fleet``: help, usage errors and config errors, without a network."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from agent import cli


def test_fleet_list_without_endpoints_is_a_usage_error(capsys: Any) -> None:
    assert cli.main(["fleet", "list", "--seconds", "1"]) == 2
    err = capsys.readouterr().err
    assert "--connect" in err and "usage:" in err


def test_bridge_with_a_bad_config_names_the_key(tmp_path: Path, capsys: Any) -> None:
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[bridge]\nrobot = "r1"\nsocket = "/tmp/x.sock"\n'
        '[zenoh]\nlisten = ["tcp/127.0.0.1:1"]\nmod = "peer"\n'
    )
    assert cli.main(["bridge", "--config", str(config)]) == 1
    err = capsys.readouterr().err
    assert "zenoh.mod: unknown key (did you mean 'mode'?)" in err


@pytest.mark.parametrize("argv", [["bridge", "--help"], ["fleet", "list", "--help"]])
def test_help_points_at_the_docs_and_the_endpoints(argv: list[str], capsys: Any) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 0
    out = capsys.readouterr().out
    assert "scouting" in out
