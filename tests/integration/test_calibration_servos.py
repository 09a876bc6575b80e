"""`vlp-agent calibrate servos` on the simulated bus: servos found at their own rates and ids, set to the
config's, and then usable by the agent's own driver (dynamixel-sdk) at the new rate."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest

from calibration.report import CalibrationError
from calibration.servos import Bus, apply, plan_changes, scan
from drivers.errors import DeviceNotFound
from drivers.fakes.dynamixel import BaudAwareDynamixelBus
from drivers.fakes.pty import PtyServer
from drivers.servos.control_table import XL430_W250, OperatingMode
from drivers.servos.dynamixel import DynamixelWheels
from drivers.sim.simulation import Simulation
from drivers.sim.worldfile import load_world
from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[2]
ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def run_servos_step(folder: Path) -> dict[str, Any]:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "agent.cli",
            "calibrate",
            "servos",
            "--sim",
            "--json",
            "--dir",
            str(folder),
            "--max-id",
            "12",
        ],
        capture_output=True,
        stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
        text=True,
        timeout=120,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    result: dict[str, Any] = strict_loads(out.stdout)
    return result


def test_servos_step_sets_up_the_bus_and_writes_the_config_keys(tmp_path: Path) -> None:
    result = run_servos_step(tmp_path)
    assert result["ok"]
    found = {(s["id"], s["baud"]) for s in result["found"]}
    assert found == {(1, 57600), (3, 1_000_000)}
    assert {s["return_delay"] for s in result["found"]} == {250}  # 0.5 ms, from the box
    after = {(s["id"], s["baud"], s["mode"], s["return_delay"]) for s in result["after"]}
    assert after == {(1, 1_000_000, 1, 0), (2, 1_000_000, 1, 0)}
    assert {c["name"]: c["ok"] for c in result["checks"]}["wheel servos with Return Delay Time 0"]
    keys = tomllib.loads((tmp_path / "servos.toml").read_text())["servos"]
    assert keys == {"baudrate": 1_000_000, "left_id": 1, "right_id": 2}
    assert (tmp_path / "servos.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # A second run replaces the file atomically and keeps the first as the backup.
    first = (tmp_path / "servos.toml").read_text()
    (tmp_path / "servos.toml").write_text(first + "# edited by hand\n")
    run_servos_step(tmp_path)
    assert (tmp_path / "servos.toml.bak").read_text() == first + "# edited by hand\n"
    assert (tmp_path / "servos.toml").read_text() != (tmp_path / "servos.toml.bak").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "servos.png",
        "servos.png.bak",
        "servos.toml",
        "servos.toml.bak",
    ]


def test_after_setup_the_agents_driver_runs_the_wheels() -> None:
    world = load_world(ENV1)
    sim = Simulation(world)
    fake = BaudAwareDynamixelBus(sim)
    fake.set_servo(1, baud_index=1, mode=int(OperatingMode.POSITION))  # 57600, from the box
    fake.set_servo(2, new_id=7, baud_index=2, mode=int(OperatingMode.POSITION))  # a spare at 115200
    server = PtyServer(fake)
    server.start()
    fake.attach(server.path)
    try:
        with Bus(server.path) as bus:
            found = scan(bus, (57600, 115200, 1_000_000), max_id=10)
            assert {(f.id, f.baud) for f in found} == {(1, 57600), (7, 115200)}
            apply(bus, plan_changes(found, {1: "left", 7: "right"}, 1, 2, 1_000_000), lambda line: None)
        with pytest.raises(DeviceNotFound):
            DynamixelWheels(server.path, baudrate=57600, latency_timer_ms=50, retries=0).open()
        wheels = DynamixelWheels(server.path, baudrate=1_000_000, latency_timer_ms=50)
        with wheels:
            assert wheels.ping() == {1: 1060, 2: 1060}
            wheels.set_velocity(2.0, 2.0)
            # A sync write has no reply: a read after it (answered in order) shows it has arrived.
            wheels.read()
            assert fake.register(1, "Operating Mode") == 1
            assert fake.register(2, "Goal Velocity") != 0
    finally:
        server.close()
        fake.close()


def test_servos_step_with_a_robot_config(tmp_path: Path) -> None:
    """The robot path: the port, rate and ids come from the robot's config file (a fake bus on a pty here)."""
    fake = BaudAwareDynamixelBus(None, ids=(4, 9))
    fake.set_servo(4, baud_index=1)  # 57600
    fake.set_servo(9, baud_index=1)
    server = PtyServer(fake)
    server.start()
    fake.attach(server.path)
    config = tmp_path / "robot.toml"
    config.write_text(
        f'[servos]\nbackend = "dynamixel"\nport = "{server.path}"\nbaudrate = 1000000\n'
        'left_id = 1\nright_id = 2\n[output]\nurl = "loop://"\n'
    )
    try:
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "agent.cli",
                "calibrate",
                "servos",
                "--config",
                str(config),
                "--json",
                "--dir",
                str(tmp_path / "out"),
                "--max-id",
                "12",
                "--assign",
                "9:left",
                "--assign",
                "4:right",
                "--reply-timeout-ms",
                "250",
            ],
            capture_output=True,
            stdin=subprocess.DEVNULL,  # nobody to answer: a step on --sim asks nothing
            text=True,
            timeout=120,
            cwd=REPO,
            check=False,
        )
        assert out.returncode == 0, out.stderr
        assert "Traceback" not in out.stderr, out.stderr[-3000:]
        r = strict_loads(out.stdout)
        assert {(s["id"], s["baud"]) for s in r["after"]} == {(1, 1_000_000), (2, 1_000_000)}
        # Servo 9 (the left wheel) is now id 1, servo 4 is id 2.
        assert fake.servo(1).get("ID") == 1 and fake.servo(2).get("ID") == 2
        assert fake.register(1, "Baud Rate") == 3 and fake.register(2, "Operating Mode") == 1
        assert [fake.register(i, "Return Delay Time") for i in (1, 2)] == [0, 0]
    finally:
        server.close()
        fake.close()


def test_a_lost_reply_is_asked_for_again_but_a_moving_write_is_sent_once() -> None:
    fake = BaudAwareDynamixelBus(None, ids=(4,))
    fake.set_servo(4, baud_index=1)  # 57600
    server = PtyServer(fake)
    server.start()
    fake.attach(server.path)
    mode = XL430_W250["Operating Mode"]
    try:
        # The replies lost here are the ones the fake breaks; a generous deadline keeps a reply that is only
        # late (the fake's thread behind a busy CPU) from counting as a lost one.
        with Bus(server.path, reply_timeout_s=0.5) as bus:
            bus.set_baud(57600)
            # Two replies lost (their CRC broken on the way): the third try is answered.
            fake.corrupt_next_reply(2)
            assert bus.read(4, mode) == fake.register(4, "Operating Mode")
            fake.corrupt_next_reply(2)
            bus.write(4, XL430_W250["Torque Enable"], 0)
            # Lost every time: the error says how often it asked.
            fake.corrupt_next_reply(Bus.RETRIES + 1)
            with pytest.raises(CalibrationError, match=r"did not answer READ Operating Mode .*\(3 tries\)"):
                bus.read(4, mode)
            # A write to ID takes even when its reply is lost; sent again it would go to an id that is gone.
            fake.corrupt_next_reply(1)
            with pytest.raises(CalibrationError, match=r"did not answer WRITE ID at 57600 bps$"):
                bus.write(4, XL430_W250["ID"], 6)
            assert fake.ids == (6,)
    finally:
        server.close()
        fake.close()
