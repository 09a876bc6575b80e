"""``vlp-agent bridge`` and ``vlp-agent fleet``: help, usage errors and config errors, without a network."""

from __future__ import annotations

import json
import socket
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


def test_bridge_on_an_endpoint_in_use_says_which(tmp_path: Path, capsys: Any) -> None:
    pytest.importorskip("zenoh")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        config = tmp_path / "bridge.toml"
        config.write_text(
            f'[bridge]\nrobot = "r1"\nsocket = "{tmp_path / "a.sock"}"\n'
            f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        )
        assert cli.main(["bridge", "--config", str(config), "--json"]) == 1
    captured = capsys.readouterr()
    assert "cannot open the Zenoh session" in captured.err and f"127.0.0.1:{port}" in captured.err
    assert json.loads(captured.out)["error"] is not None
