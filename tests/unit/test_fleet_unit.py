"""The bridge's systemd unit (systemd/vlp-agent-bridge.service) and the drop-in ``vlp-agent bridge
--print-unit`` makes from a bridge config: IP denied except the configured endpoints. ``systemd-analyze
verify`` checks the unit with its drop-in when it is installed (skipped otherwise)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from agent.fleet.bridge_config import ZenohConfig
from agent.fleet.unit import drop_in, endpoint_address
from drivers.errors import ConfigError
from tests.unit.test_systemd_files import parse_unit

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "vlp-agent-bridge.service"
AGENT = "/opt/vlp-agent/venv/bin/vlp-agent"


def test_the_drop_in_allows_the_endpoints_addresses_and_nothing_else() -> None:
    z = ZenohConfig(
        "peer",
        listen=("tcp/0.0.0.0:7447", "tcp/192.168.1.21:7447"),
        connect=("tcp/192.168.1.20:7447", "udp/[fe80::1]:7447#iface=eth0", "tcp/192.168.1.20:7448"),
    )
    text = drop_in(z, "/etc/vlp-agent/bridge.toml", ["10.0.0.0/24"])
    unit = parse_unit(text)
    assert unit["Service"]["IPAddressAllow"] == ["192.168.1.20 fe80::1 192.168.1.21 10.0.0.0/24"]
    assert set(unit) == {"Service"}
    scouting = parse_unit(drop_in(ZenohConfig("peer", (), (), True), "x"))
    assert scouting["Service"]["IPAddressAllow"] == ["224.0.0.224"]
    assert (
        "IPAddressAllow" not in parse_unit(drop_in(ZenohConfig("peer", ("tcp/[::]:1",), ()), "x"))["Service"]
    )


@pytest.mark.parametrize("endpoint", ["tcp/router.local:7447", "tcp/1.2.3.4", "1.2.3.4:5", "tcp/:7447"])
def test_an_endpoint_that_is_not_an_ip_address_is_refused_with_the_reason(endpoint: str) -> None:
    with pytest.raises(ConfigError, match=r"endpoint|address"):
        endpoint_address(endpoint)


def test_the_units_network_is_denied_but_for_the_drop_in() -> None:
    unit = parse_unit(UNIT.read_text(encoding="utf-8"))
    service = unit["Service"]
    assert service["IPAddressDeny"] == ["any"] and "IPAddressAllow" not in service
    assert service["ExecStart"] == [f"{AGENT} bridge --config /etc/vlp-agent/bridge.toml"]
    assert service["User"] == ["vlp-agent"] and service["NoNewPrivileges"] == ["yes"]
    assert service["Restart"] == ["on-failure"] and service["RestartSec"] == ["1s"]
    assert "PrivateNetwork" not in service and "RuntimeDirectory" not in service  # the agent's, not ours


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_systemd_analyze_verifies_the_unit_with_its_generated_drop_in(tmp_path: Path) -> None:
    stub = tmp_path / "bin" / "vlp-agent"
    stub.parent.mkdir()
    stub.write_text("#!/bin/sh\nexit 0\n")
    stub.chmod(0o755)
    text = UNIT.read_text(encoding="utf-8").replace(f"ExecStart={AGENT} ", f"ExecStart={stub} ")
    assert f"ExecStart={stub} " in text
    unit = tmp_path / "vlp-agent-bridge.service"
    unit.write_text(text)
    config = tmp_path / "bridge.toml"
    config.write_text(
        '[bridge]\nrobot = "r1"\nsocket = "/run/vlp-agent/fleet.sock"\n[zenoh]\n'
        'listen = ["tcp/192.168.1.21:7447"]\nconnect = ["tcp/192.168.1.20:7447"]\n'
    )
    printed = subprocess.run(
        [sys.executable, "-m", "agent.cli", "bridge", "--config", str(config), "--print-unit"],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
        check=True,
    )
    drop_ins = tmp_path / "vlp-agent-bridge.service.d"
    drop_ins.mkdir()
    conf = drop_ins / "endpoints.conf"
    conf.write_text(printed.stdout)
    assert "IPAddressAllow=192.168.1.20 192.168.1.21\n" in printed.stdout
    env = {**os.environ, "SYSTEMD_UNIT_PATH": f"{tmp_path}:"}

    def verify() -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, env=env, timeout=120
        )

    ok = verify()
    assert ok.returncode == 0 and ok.stderr == "", ok.stderr
    # The check sees the drop-in: a value IPAddressAllow= cannot take is reported.
    conf.write_text(printed.stdout + "IPAddressAllow=router.local\n")
    bad = verify()
    assert "router.local" in bad.stderr
