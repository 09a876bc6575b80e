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


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["fleet", "goal", "r 1", "1", "2", "--connect", "tcp/127.0.0.1:1"], "not a robot name"),
        (["fleet", "goal", "r1", "nan", "2", "--connect", "tcp/127.0.0.1:1"], "finite"),
        (["fleet", "goal", "r1", "1", "2", "--goal-id", "70000", "--connect", "tcp/127.0.0.1:1"], "0..65535"),
        (["fleet", "goal", "r1", "1", "2"], "--connect"),
    ],
)
def test_fleet_goal_usage_errors(argv: list[str], says: str, capsys: Any) -> None:
    assert cli.main(argv) == 2
    assert says in capsys.readouterr().err


def test_fleet_goal_with_no_bridge_of_that_robot_says_it_was_not_sent(capsys: Any) -> None:
    pytest.importorskip("zenoh")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = ["fleet", "goal", "r9", "1", "2", "--listen", f"tcp/127.0.0.1:{port}", "--timeout", "0.5"]
    assert cli.main([*argv, "--json"]) == 3
    out = json.loads(capsys.readouterr().out)
    assert out["sent"] is False and out["final"] is None and out["timed_out"] is True


def test_fleet_list_shows_a_robot_silent_for_stale_s_as_gone() -> None:
    import time

    from agent.fleet import payloads
    from agent.fleet.bridge_config import ZenohConfig
    from agent.fleet.local_protocol import PoseMessage
    from agent.fleet.view import FleetView

    class Sample:
        def __init__(self, key: str, data: bytes) -> None:
            self.key_expr = key
            self.payload = type("Z", (), {"to_bytes": lambda _self: data})()

    view = FleetView(ZenohConfig("peer", (), ("tcp/127.0.0.1:1",)), stale_s=2.0)
    pose = PoseMessage(1, 1.0, 2.0, 0.0, 0.01, 0.01, 1)
    view._on("pose", Sample("fleet/r2/pose", payloads.encode_pose("r2", pose)))
    view._on("pose", Sample("fleet/r3/pose", b"not json"))
    now = time.monotonic()
    (r2,) = view.seen(now)
    assert r2.state == "unknown" and r2.poses == 1 and view.rejected == 1
    (r2,) = view.seen(now + 2.5)
    assert r2.state == "gone" and r2.as_dict()["state"] == "gone" and r2.as_dict()["silent_s"] >= 2.5


def test_fleet_router_runs_for_its_seconds_and_names_an_endpoint_it_cannot_open(capsys: Any) -> None:
    pytest.importorskip("zenoh")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert (
        cli.main(["fleet", "router", "--listen", f"tcp/127.0.0.1:{port}", "--seconds", "0.2", "--json"]) == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["listen"] == [f"tcp/127.0.0.1:{port}"] and out["error"] is None
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        busy = taken.getsockname()[1]
        code = cli.main(["fleet", "router", "--listen", f"tcp/127.0.0.1:{busy}", "--seconds", "5", "--json"])
    assert code == 1
    captured = capsys.readouterr()
    assert json.loads(captured.out)["error"] and f"127.0.0.1:{busy}" in captured.err


def test_the_connect_retry_is_configured() -> None:
    pytest.importorskip("zenoh")
    from agent.fleet.bridge_config import parse_bridge_config

    config = parse_bridge_config(
        {
            "bridge": {"robot": "r1", "socket": "/x"},
            "zenoh": {"connect": ["tcp/127.0.0.1:1"], "retry_max_s": 2},
        }
    )
    assert config.zenoh.retry_max_s == 2.0
    retry = json.loads(config.zenoh.zenoh_config().get_json("connect/retry"))
    assert (retry["period_init_ms"], retry["period_max_ms"]) == (100, 2000)
