"""systemd/install.sh into a temporary root (DESTDIR): the expected tree, idempotence, and an uninstall
that leaves nothing behind. Nothing on the running system may change: the useradd, groupadd, systemctl and
udevadm on PATH are stubs that record any call, and there must be none.

The venv path (pip installing the package and its dependencies into DESTDIR) needs a package index and
takes a while: it runs only with VLP_TEST_INSTALL_VENV=1.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import stat
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
INSTALL = REPO / "systemd" / "install.sh"
HOST_COMMANDS = ("useradd", "userdel", "groupadd", "groupdel", "systemctl", "udevadm")

EXPECTED_FILES = {
    "etc/systemd/system/vlp-agent.service": REPO / "systemd" / "vlp-agent.service",
    "etc/systemd/system/vlp-agent-bridge.service": REPO / "systemd" / "vlp-agent-bridge.service",
    "etc/udev/rules.d/99-vlp-agent.rules": REPO / "systemd" / "99-vlp-agent.rules",
    "opt/vlp-agent/share/doc/operations.md": REPO / "docs" / "operations.md",
}


@pytest.fixture
def stubs(tmp_path: Path) -> Path:
    """A directory of stand-ins for the commands that would change this machine; each logs its call."""
    bin_dir = tmp_path / "stub-bin"
    bin_dir.mkdir()
    for name in HOST_COMMANDS:
        stub = bin_dir / name
        stub.write_text(f'#!/bin/sh\necho "{name} $*" >> "{tmp_path}/host-calls"\n')
        stub.chmod(0o755)
    return bin_dir


@pytest.fixture
def root(tmp_path: Path) -> Path:
    destdir = tmp_path / "root"
    destdir.mkdir()
    return destdir


def run_install(
    root: Path, stubs: Path, *args: str, check: bool = True, destdir: bool = True
) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}"}
    env.pop("DESTDIR", None)
    if destdir:
        env["DESTDIR"] = str(root)
    result = subprocess.run(
        ["bash", str(INSTALL), *args], capture_output=True, text=True, env=env, timeout=600, check=False
    )
    if check:
        assert result.returncode == 0, result.stdout + result.stderr
    return result


def tree(root: Path) -> set[str]:
    """Every file and directory under root, relative, directories with a trailing slash."""
    return {str(p.relative_to(root)) + ("/" if p.is_dir() else "") for p in root.rglob("*")}


def host_calls(stubs: Path) -> str:
    log = stubs.parent / "host-calls"
    return log.read_text() if log.exists() else ""


def test_install_produces_the_expected_tree(root: Path, stubs: Path) -> None:
    out = run_install(root, stubs, "--no-venv").stdout

    files = {p for p in tree(root) if not p.endswith("/")}
    assert files == {*EXPECTED_FILES, "etc/vlp-agent/robot.toml", "opt/vlp-agent/install-manifest"}
    for relative, source in EXPECTED_FILES.items():
        installed = root / relative
        assert installed.read_bytes() == source.read_bytes(), relative
        assert stat.S_IMODE(installed.stat().st_mode) == 0o644, relative
    assert not (root / "opt" / "vlp-agent" / "venv").exists()

    # The default config: the example when the checkout has one, else a placeholder that says where to look.
    config = root / "etc" / "vlp-agent" / "robot.toml"
    example = REPO / "examples" / "turtlebot3.toml"
    if example.exists():
        assert config.read_bytes() == example.read_bytes()
    else:
        assert "docs/config.md" in config.read_text()
    tomllib.loads(config.read_text())  # either way, it is TOML

    # What it would do to the running system is said, not done.
    for command in (
        "groupadd --system i2c",
        "useradd --system --user-group",
        "udevadm control --reload-rules",
        "systemctl daemon-reload",
        "systemctl enable vlp-agent.service",
    ):
        assert command in out, command
    assert host_calls(stubs) == ""
    # The fleet bridge's unit is installed but never enabled or started by the install.
    assert "installed /etc/systemd/system/vlp-agent-bridge.service" in out
    assert "enable vlp-agent-bridge" not in out and "restart vlp-agent-bridge" not in out


def test_install_is_idempotent_and_keeps_an_edited_config(root: Path, stubs: Path) -> None:
    run_install(root, stubs, "--no-venv")
    manifest = (root / "opt/vlp-agent/install-manifest").read_text()
    before = tree(root)
    config = root / "etc/vlp-agent/robot.toml"
    config.write_text(config.read_text() + "\n# this robot's own setting\n")

    out = run_install(root, stubs, "--no-venv").stdout

    assert tree(root) == before
    assert (root / "opt/vlp-agent/install-manifest").read_text() == manifest
    assert config.read_text().endswith("# this robot's own setting\n")
    assert "kept the existing /etc/vlp-agent/robot.toml" in out


def test_uninstall_removes_everything_the_install_made(root: Path, stubs: Path) -> None:
    run_install(root, stubs, "--no-venv")
    out = run_install(root, stubs, "--uninstall").stdout
    assert tree(root) == set()
    assert "would run: systemctl disable --now vlp-agent.service" in out
    assert "would run: systemctl disable --now vlp-agent-bridge.service" in out
    assert host_calls(stubs) == ""
    # Twice is fine.
    run_install(root, stubs, "--uninstall")
    assert tree(root) == set()


def test_uninstall_keeps_state_and_an_edited_config_until_purge(root: Path, stubs: Path) -> None:
    run_install(root, stubs, "--no-venv")
    config = root / "etc/vlp-agent/robot.toml"
    config.write_text("# edited on the robot\n")
    maps = root / "var/lib/vlp-agent/maps"  # what the service would have made
    maps.mkdir(parents=True)
    (maps / "office.pgm").write_bytes(b"P5 1 1 255\n\0")

    run_install(root, stubs, "--uninstall")
    assert tree(root) == {
        "etc/",
        "etc/vlp-agent/",
        "etc/vlp-agent/robot.toml",
        "var/",
        "var/lib/",
        "var/lib/vlp-agent/",
        "var/lib/vlp-agent/maps/",
        "var/lib/vlp-agent/maps/office.pgm",
    }

    run_install(root, stubs, "--uninstall", "--purge")
    assert not (root / "etc/vlp-agent").exists()
    assert not (root / "var/lib/vlp-agent").exists()
    assert host_calls(stubs) == ""


def test_install_into_a_root_that_already_has_etc_leaves_it(root: Path, stubs: Path) -> None:
    # A real system has /etc/systemd/system and /etc/udev/rules.d: the uninstall must not remove them.
    (root / "etc/systemd/system").mkdir(parents=True)
    (root / "etc/udev/rules.d").mkdir(parents=True)
    (root / "etc/udev/rules.d/70-other.rules").write_text("# someone else's\n")
    before = tree(root)
    run_install(root, stubs, "--no-venv")
    run_install(root, stubs, "--uninstall")
    assert tree(root) == before


def test_unit_dir_option(root: Path, stubs: Path) -> None:
    run_install(root, stubs, "--no-venv", "--unit-dir", "/lib/systemd/system")
    assert (root / "lib/systemd/system/vlp-agent.service").exists()
    assert (root / "lib/systemd/system/vlp-agent-bridge.service").exists()
    assert not (root / "etc/systemd/system/vlp-agent.service").exists()
    run_install(root, stubs, "--uninstall")
    assert tree(root) == set()


def test_help_and_argument_errors(root: Path, stubs: Path) -> None:
    help_text = run_install(root, stubs, "--help").stdout
    for word in ("DESTDIR", "--uninstall", "--purge", "--no-venv", "--wheel", "/opt/vlp-agent/venv"):
        assert word in help_text
    for args, message in (
        (("--bogus",), "unknown argument"),
        (("--purge",), "--purge only goes with --uninstall"),
        (("--no-venv", "--wheel", "x.whl"), "contradict"),
        (("--unit-dir", "relative/dir"), "must be absolute"),
    ):
        result = run_install(root, stubs, *args, check=False)
        assert result.returncode != 0
        assert message in result.stderr
    assert tree(root) == set()


@pytest.mark.skipif(os.geteuid() == 0, reason="running as root: the root check does not apply")
def test_refuses_a_real_install_without_root(root: Path, stubs: Path) -> None:
    result = run_install(root, stubs, "--no-venv", check=False, destdir=False)
    assert result.returncode != 0
    assert "run as root" in result.stderr
    assert host_calls(stubs) == ""


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("VLP_TEST_INSTALL_VENV") != "1",
    reason="set VLP_TEST_INSTALL_VENV=1 (needs a package index)",
)
def test_venv_install_runs_the_installed_agent(root: Path, stubs: Path) -> None:
    had_build_dir = (REPO / "build").exists()
    run_install(root, stubs)
    agent = root / "opt/vlp-agent/venv/bin/vlp-agent"
    version = subprocess.run(
        [str(agent), "--version"], capture_output=True, text=True, timeout=120, check=True
    )
    assert version.stdout.startswith("vlp-agent ")
    # The package is built from a clean copy: no build/ left in the checkout.
    assert (REPO / "build").exists() == had_build_dir
    run_install(root, stubs, "--uninstall")
    assert tree(root) == set()


@pytest.mark.slow
def test_the_wheel_carries_the_default_config_and_worlds(tmp_path: Path) -> None:
    """A non-editable install runs `vlp-agent sim` and `vlp-agent fake urg` with their defaults from a
    folder outside the checkout: the config and worlds come from inside the wheel. Quick form (about
    30 s): the wheel, built as pip builds it (an isolated build: pip fetches setuptools), is unpacked into
    a folder that shadows the editable checkout, with the dependencies from this venv; .ci/wheel-check
    installs it into a fresh venv instead."""
    source = tmp_path / "src"
    shutil.copytree(
        REPO,
        source,
        symlinks=True,
        ignore=shutil.ignore_patterns(
            ".git", ".venv", "build", "dist", "*.egg-info", "__pycache__", ".*_cache"
        ),
    )
    build = ["wheel", "--quiet", "--no-deps", "--disable-pip-version-check"]
    subprocess.run(
        [sys.executable, "-m", "pip", *build, "-w", str(tmp_path / "dist"), str(source)],
        check=True,
        timeout=300,
        capture_output=True,
    )
    (wheel,) = (tmp_path / "dist").glob("vlp_agent-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
    for shipped in ("sim.toml", "worlds/office.toml", "worlds/env1.toml"):
        assert f"agent/examples/{shipped}" in names, shipped
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(site)
    outside = tmp_path / "outside"
    outside.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    run = [sys.executable, "-c", "import sys, agent.cli; sys.exit(agent.cli.main(sys.argv[1:]))"]
    where = subprocess.run(
        [sys.executable, "-c", "import agent.shipped as s; print(s.DEFAULT_SIM_CONFIG)"],
        capture_output=True,
        text=True,
        cwd=outside,
        env=env,
        timeout=60,
        check=True,
    )
    assert where.stdout.strip() == str(site / "agent" / "examples" / "sim.toml")  # not the checkout's

    sim = subprocess.run(
        [*run, "sim", "--seconds", "5", "--json"],
        capture_output=True,
        text=True,
        cwd=outside,
        env=env,
        timeout=120,
        check=False,
    )
    assert sim.returncode == 0, sim.stderr
    assert json.loads(sim.stdout)["world"] == "office"
    assert (outside / "vlp-sim-out" / "map.yaml").exists()

    fake = subprocess.Popen(
        [*run, "fake", "urg"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=outside, env=env
    )
    try:
        assert fake.stdout is not None
        assert fake.stdout.readline().startswith("/dev/pts/"), fake.stderr.read() if fake.stderr else ""
        fake.send_signal(signal.SIGINT)
        assert fake.wait(timeout=10) == 0
    finally:
        if fake.poll() is None:
            fake.kill()
            fake.wait()
