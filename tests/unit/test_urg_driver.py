"""The URG driver against the fake URG on a pseudo-terminal: connect, GD, MD streaming, clock, and faults
(unplug/replug, junk, bad checksums, a silent or rebooted sensor, close). Plus the clock estimator alone."""

from __future__ import annotations

import itertools
import logging
import math
import os
import pty
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceError,
    DeviceNotFound,
    DeviceStatusError,
    DeviceTimeout,
)
from drivers.fakes.pty import PtyServer
from drivers.fakes.urg import FakeUrg
from drivers.laser.urg import (
    DeviceClock,
    UrgCommandError,
    UrgHardwareFault,
    UrgLaser,
    UrgLaserOff,
    UrgModeError,
    UrgParameterError,
    raise_for_status,
)
from drivers.samples import Scan
from drivers.sim.simulation import Simulation
from drivers.sim.world import LaserModel, Pose2D, RobotSpec, Wall, World
from firmware_protocol import scip

WRAP = 1 << 24
STEP_RAD = 2 * math.pi / 1024


def room() -> World:
    """A 5 m x 3.5 m room with a doorway (open space: no-echo beams) and a pillar."""
    walls = (
        Wall(-2.0, -1.5, 3.0, -1.5),
        Wall(3.0, -1.5, 3.0, 2.0),
        Wall(3.0, 2.0, 0.5, 2.0),
        Wall(-0.5, 2.0, -2.0, 2.0),
        Wall(-2.0, 2.0, -2.0, -1.5),
        Wall(1.0, 0.3, 1.2, 0.5),
    )
    return World("urg-test room", walls=walls, robot=RobotSpec(start=Pose2D(0.2, 0.1, 0.3)),
                 laser=LaserModel(range_noise_mm=10.0))  # fmt: skip


# The driver's reply timeout in tests that are not about timeouts: a deadline for behaviour, not speed (a
# starved CI machine once kept the fake from answering SCIP2.0 within 2 s).
REPLY_TIMEOUT_S = 5.0


def device_ms(scan: Scan) -> int:
    assert scan.device_time_ms is not None, "a URG scan always carries the sensor's clock"
    return scan.device_time_ms


def wait_for(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Poll ``predicate`` until it holds or ``timeout_s`` passes (a deadline for behaviour, not speed)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def sim() -> Simulation:
    return Simulation(room(), seed=0)  # the real monotonic clock, the one PtyServer passes the fake


@pytest.fixture
def fake(sim: Simulation) -> FakeUrg:
    return FakeUrg(sim, seed=0)


@pytest.fixture
def server(fake: FakeUrg, tmp_path: Path) -> Iterator[PtyServer]:
    with PtyServer(fake, link=tmp_path / "urg") as srv:
        yield srv


@pytest.fixture
def laser(server: PtyServer) -> Iterator[UrgLaser]:
    dev = UrgLaser(server.path, timeout_s=2.0)
    dev.open()
    yield dev
    dev.close()


# -- connect -----------------------------------------------------------------------------------------------


def test_connect_sequence_reads_device_facts(fake: FakeUrg, laser: UrgLaser) -> None:
    sent = [c.split(b";")[0] for c in fake.commands]
    assert sent == [b"QT", b"SCIP2.0", b"VV", b"PP", b"II", b"TM0", *[b"TM1"] * 5, b"TM2", b"BM"]
    info = laser.info()
    assert info.model == "URG-04LX-UG01(Simple-URG)(Hokuyo Automatic Co.,Ltd.)"
    assert (info.serial, info.firmware, info.protocol) == ("H0000001", "3.4.03(17/Dec./2012)", "SCIP 2.0")
    assert (info.min_range_mm, info.max_range_mm) == (20, 5600)
    assert (info.steps_per_rev, info.first_step, info.last_step, info.front_step) == (1024, 44, 725, 384)
    assert info.scan_period_s == pytest.approx(0.1)
    assert fake.laser_on
    health = laser.health()
    assert health.connected and "bad_frames" not in health.counters
    assert laser.clock.offset_ns(time.monotonic_ns()) is not None  # TM gave the clock before any scan


@pytest.mark.parametrize("state", ["scip1", "time_adjust", "streaming", "fresh"])
def test_connect_from_any_sensor_state(sim: Simulation, tmp_path: Path, state: str) -> None:
    fake = FakeUrg(sim, boot_in_scip1=state == "scip1")
    now = time.monotonic()
    if state == "time_adjust":
        fake.receive(b"TM0\n", now)
    elif state == "streaming":
        fake.receive(b"MD0044072501000;old\n", now)
    with PtyServer(fake, link=tmp_path / "urg") as srv:
        if state == "streaming":
            time.sleep(0.25)  # scans of the old stream wait in the pty when the driver opens it
        with UrgLaser(srv.path, timeout_s=REPLY_TIMEOUT_S) as laser:
            assert laser.scan_once(1.0).ranges_mm.size == 682
        sent = [c.split(b";")[0] for c in fake.commands]
        assert b"SCIP2.0" in sent
        assert (b"TM2" in sent[: sent.index(b"SCIP2.0")]) == (state == "time_adjust")


def test_open_fails_cleanly(tmp_path: Path, sim: Simulation) -> None:
    with pytest.raises(DeviceNotFound):
        UrgLaser(str(tmp_path / "no-such-port")).open()
    fake = FakeUrg(sim)
    fake.silent = True
    with PtyServer(fake) as srv, pytest.raises(DeviceNotFound, match=r"no SCIP 2\.0 answer"):
        UrgLaser(srv.path, timeout_s=0.2).open()
    fake.silent = False
    fake.hardware_fault = True
    with PtyServer(fake) as srv:
        laser = UrgLaser(srv.path, timeout_s=REPLY_TIMEOUT_S)
        with pytest.raises(UrgHardwareFault) as info:
            laser.open()
        assert info.value.status == "01" and not laser.is_open
        with pytest.raises(ConfigError, match="first_step"):
            UrgLaser(srv.path, first_step=10).open()  # below the sensor's AMIN
    with pytest.raises(ConfigError):
        UrgLaser("loop://", cluster=0)


@pytest.mark.parametrize(("frame", "cls"), [
    (scip.encode_reply(b"GD0044072501", "10"), UrgLaserOff),
    (scip.encode_reply(b"GD0044099901", "04"), UrgParameterError),
    (scip.encode_reply(b"MD0044072501x00", "06"), UrgParameterError),
    (scip.encode_reply(b"XX", "0E"), UrgCommandError),
    (scip.encode_reply(b"MD0044072501000", "55"), UrgHardwareFault),
    (scip.encode_reply(b"BM", "01"), UrgHardwareFault),
    (scip.encode_reply(b"TM1", "04"), UrgModeError),
    (b"QT\nE\n\n", UrgModeError),
])  # fmt: skip
def test_status_errors_are_typed(frame: bytes, cls: type[DeviceStatusError]) -> None:
    reply = scip.parse_reply(frame)
    with pytest.raises(cls) as info:
        raise_for_status(reply, "laser")
    assert isinstance(info.value, DeviceStatusError) and info.value.status == reply.status
    assert reply.echo in str(info.value)


# -- one-shot scans ----------------------------------------------------------------------------------------


def test_scan_once_gives_the_world_seen_by_the_laser(sim: Simulation, fake: FakeUrg, laser: UrgLaser) -> None:
    scan = laser.scan_once(timeout_s=1.0)
    assert scan.ranges_mm.dtype == np.int32 and scan.ranges_mm.size == 682
    assert scan.angle_min_rad == pytest.approx((44 - 384) * STEP_RAD)
    assert scan.angle_increment_rad == pytest.approx(STEP_RAD)
    assert math.degrees(scan.angles_rad()[-1] - scan.angles_rad()[0]) == pytest.approx(239.4, abs=0.1)
    assert (scan.min_range_mm, scan.max_range_mm) == (20, 5600)
    assert scan.device_time_ms is not None
    assert scan.device_time_ms % WRAP == fake.emitted[-1].device_time_ms
    # The robot stands still, so the truth is the ray cast along the scan's own angles.
    truth_mm = sim.laser_ranges_m(scan.angles_rad()) * 1000.0
    open_space = ~np.isfinite(truth_mm)
    assert open_space.any() and np.all(scan.ranges_mm[open_space] == 0)  # URG-04LX "no echo" code
    seen = np.isfinite(truth_mm)
    assert np.all(scan.valid_mask()[seen])
    error_mm = np.abs(scan.ranges_mm[seen] - truth_mm[seen])
    assert np.median(error_mm) < 12.0 and error_mm.max() < 60.0  # 10 mm Gaussian noise
    # While not streaming, GD leaves the laser on and the sensor idle.
    assert not laser.streaming and not fake.streaming


def test_scan_window_and_clusters(server: PtyServer) -> None:
    with UrgLaser(server.path, first_step=300, last_step=468, cluster=3, timeout_s=2.0) as laser:
        scan = laser.scan_once(1.0)
    assert scan.ranges_mm.size == math.ceil((468 - 300 + 1) / 3)
    assert scan.angle_min_rad == pytest.approx((301 - 384) * STEP_RAD)  # the centre of the first cluster
    assert scan.angle_increment_rad == pytest.approx(3 * STEP_RAD)


def test_scan_once_switches_the_laser_back_on(fake: FakeUrg, laser: UrgLaser) -> None:
    laser.start()
    laser.read(1.0)
    laser.stop()  # QT: laser off
    assert wait_for(lambda: not fake.laser_on, 1.0)
    assert laser.scan_once(1.0).ranges_mm.size == 682
    sent = [c.split(b";")[0] for c in fake.commands]
    assert sent[-3:] == [b"GD0044072501", b"BM", b"GD0044072501"]


def test_a_faulty_sensor_refuses_with_typed_errors(fake: FakeUrg, laser: UrgLaser) -> None:
    fake.hardware_fault = True
    with pytest.raises(UrgHardwareFault) as info:
        laser.start()
    assert info.value.status == "50" and info.value.command.startswith("MD0044072501000;")
    assert not laser.streaming
    with pytest.raises(UrgHardwareFault):
        laser.scan_once(1.0)
    fake.hardware_fault = False
    assert laser.scan_once(1.0).ranges_mm.size == 682 and laser.connected


# -- streaming ---------------------------------------------------------------------------------------------


def test_md_streaming_timestamps_and_alignment(fake: FakeUrg, laser: UrgLaser) -> None:
    laser.start()
    assert laser.streaming and fake.streaming
    scans = [laser.read(REPLY_TIMEOUT_S) for _ in range(10)]
    device = [device_ms(s) for s in scans]
    steps = [b - a for a, b in itertools.pairwise(device)]
    assert all(step > 0 and step % 100 == 0 for step in steps)  # one scan per 100 ms revolution
    assert np.all(np.diff([s.host_time_ns for s in scans]) > 0)
    assert np.all(np.diff([s.sequence for s in scans]) > 0)
    # host_time_ns is when step 0 was measured: compare with the fake's own record of it.
    truth = {e.device_time_ms: e.step0_time_s for e in fake.emitted}
    errors_ms = [(s.host_time_ns / 1e9 - truth[d % WRAP]) * 1e3 for s, d in zip(scans, device, strict=True)]
    assert max(abs(e) for e in errors_ms) < 20.0, errors_ms
    assert "clock_inconsistent" not in laser.health().counters

    laser.stop()
    assert not laser.streaming
    assert wait_for(lambda: not fake.streaming, 1.0)
    with pytest.raises(DeviceError, match="not streaming"):
        for _ in range(10):  # scans still queued come first
            laser.read(0.2)


def test_a_server_that_polls_rarely_still_sends_each_scan_when_it_falls_due(
    sim: Simulation, tmp_path: Path
) -> None:
    # The fake says when its next scan is due (next_output_in) and its server sleeps until then: with a
    # poll interval of 5 s every scan still arrives within a few milliseconds of its completion.
    fake = FakeUrg(sim, seed=0)
    assert fake.next_output_in(time.monotonic()) is None  # nothing queued, no stream
    with PtyServer(fake, link=tmp_path / "urg", poll_interval_s=5.0) as srv:
        laser = UrgLaser(srv.path, timeout_s=REPLY_TIMEOUT_S)
        laser.open()
        try:
            laser.start()
            due_in = fake.next_output_in(time.monotonic())
            assert due_in is not None and 0.0 <= due_in <= 0.2  # the next scan, within two revolutions
            scans, read_at = [], []
            for _ in range(6):
                scans.append(laser.read(1.0))
                read_at.append(time.monotonic())
            steps = [device_ms(b) - device_ms(a) for a, b in itertools.pairwise(scans)]
            assert steps == [100] * 5  # none skipped, none waiting for the 5 s poll
            # In the driver's hands soon after the sweep ended (step 0 plus at most one revolution): the
            # transfer and the scheduling of a loaded test machine, not a poll interval.
            step0 = {e.device_time_ms: e.step0_time_s for e in fake.emitted}
            late_ms = [
                (t - (step0[device_ms(s) % WRAP] + fake.period_s)) * 1e3
                for s, t in zip(scans, read_at, strict=True)
            ]
            assert max(late_ms) < 60.0, late_ms
            laser.stop()
        finally:
            laser.close()


def test_a_server_that_sleeps_long_stops_at_once_and_leaves_the_next_pty_alone(
    sim: Simulation, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Its thread used to sit out its 5 s poll after unplug() had given up waiting for it (2 s) and closed
    # the pty under it; woken by that close, it read on fd numbers the next test's pty could already have
    # taken, and swallowed that test's first QT ("no reply to 'QT'" at open).
    alive_at_close: list[bool] = []
    real_close = os.close

    def close(fd: int) -> None:
        alive_at_close.append(thread.is_alive())
        real_close(fd)

    with PtyServer(FakeUrg(sim, seed=0), link=tmp_path / "old", poll_interval_s=5.0) as old:
        assert old._thread is not None
        thread = old._thread
        monkeypatch.setattr(os, "close", close)
    monkeypatch.undo()
    assert alive_at_close and not any(alive_at_close)  # the thread had left before its fds were closed
    with (
        PtyServer(FakeUrg(sim, seed=0), link=tmp_path / "urg") as srv,
        UrgLaser(srv.path, timeout_s=REPLY_TIMEOUT_S) as laser,
    ):
        assert laser.info().model


def test_device_clock_wrap_is_unwrapped(sim: Simulation, tmp_path: Path) -> None:
    fake = FakeUrg(sim, clock_start_ms=WRAP - 500)
    with (
        PtyServer(fake, link=tmp_path / "urg") as srv,
        UrgLaser(srv.path, timeout_s=REPLY_TIMEOUT_S) as laser,
    ):
        laser.start()
        scans = [laser.read(REPLY_TIMEOUT_S) for _ in range(10)]
    device = np.asarray([s.device_time_ms for s in scans], dtype=np.int64)
    assert device[0] < WRAP < device[-1]
    assert np.all(np.diff(device) > 0) and np.all(np.diff(device) % 100 == 0)
    raw = [e.device_time_ms for e in fake.emitted]
    assert min(raw) < 1000 and max(raw) > WRAP - 1000  # the wire really wrapped
    assert "clock_resets" not in laser.health().counters


def test_scans_arrive_over_a_19200_bps_serial_line(
    sim: Simulation, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # An RS-232 URG-04LX at 19200 bit/s: a 2143-byte scan takes 1.1 s on the line, more than the stall
    # timeout, and the sensor measures ten scans a second it cannot send.
    fake = FakeUrg(sim, seed=0, link_bitrate=19200)
    with PtyServer(fake, link=tmp_path / "urg") as srv:
        with caplog.at_level(logging.WARNING, logger="drivers.laser.urg"):
            # A pty moves bytes at once: say that this one stands for a serial line.
            laser = UrgLaser(srv.path, baudrate=19200, serial_line=True, timeout_s=2.0, stall_timeout_s=1.0)
        warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
        assert (
            len(warnings) == 1 and "laser.baudrate = 19200" in warnings[0] and "1 scan in 12" in warnings[0]
        )
        assert laser.scan_transfer_s == pytest.approx(2144 * 10 / 19200)
        assert laser.stall_limit_s == pytest.approx(2 * (0.1 + 2144 * 10 / 19200))
        with laser:
            laser.start()
            scans = [laser.read(3.0) for _ in range(3)]
            counters = laser.health().counters
    assert all(s.ranges_mm.size == 682 for s in scans)
    steps = [device_ms(b) - device_ms(a) for a, b in itertools.pairwise(scans)]
    # The sensor sends the first scan finished once the line is free: one in 12 revolutions.
    assert all(1100 <= step <= 1300 and step % 100 == 0 for step in steps), steps
    assert "stream_restarts" not in counters
    assert counters["scans_missed"] == sum(step // 100 - 1 for step in steps)


def test_the_line_rate_is_only_a_limit_on_a_serial_port(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    acm = tmp_path / "ttyACM0"
    acm.touch()
    pty_master, pty_slave = pty.openpty()
    (tmp_path / "urg").symlink_to(acm)  # what the udev rule makes of a USB URG
    with caplog.at_level(logging.WARNING, logger="drivers.laser.urg"):
        usb = UrgLaser(str(tmp_path / "urg"), baudrate=19200)
        fake = UrgLaser(os.ttyname(pty_slave), baudrate=19200)
        loop = UrgLaser("loop://", baudrate=19200)
    os.close(pty_master)
    os.close(pty_slave)
    assert not caplog.records  # none of them has a line rate
    for laser in (usb, fake, loop):
        assert laser.link_bytes_per_s is None and laser.scan_transfer_s == 0.0 and laser.stall_limit_s == 1.0
    # An RS-232 URG at 115200 bit/s: 0.19 s per scan, one in two of its scans (said so), and the watchdog
    # still at its 1 s, which is more than two such scan intervals.
    with caplog.at_level(logging.WARNING, logger="drivers.laser.urg"):
        rs232 = UrgLaser("/dev/ttyUSB0", baudrate=115200)
    assert "laser.baudrate = 115200" in caplog.text and "1 scan in 2 " in caplog.text
    assert rs232.scan_transfer_s == pytest.approx(2144 * 10 / 115200) and rs232.stall_limit_s == 1.0
    caplog.clear()
    # A narrower window or clusters make the scan smaller, and a 19200 bit/s line then carries it.
    narrow = UrgLaser("/dev/ttyS0", baudrate=19200, first_step=300, last_step=468, cluster=4)
    assert narrow.scan_transfer_s < 0.1 and not caplog.records
    with pytest.raises(ConfigError, match="baudrate"):
        UrgLaser("/dev/ttyS0", baudrate=0)


# -- faults ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("power_cycle", [True, False])
def test_unplug_and_replug(sim: Simulation, tmp_path: Path, power_cycle: bool) -> None:
    fake = FakeUrg(sim, clock_start_ms=1_000_000)
    with (
        PtyServer(fake, link=tmp_path / "urg") as server,
        UrgLaser(server.path, timeout_s=REPLY_TIMEOUT_S) as laser,
    ):
        _unplug_and_replug(server, fake, laser, power_cycle)


def _unplug_and_replug(server: PtyServer, fake: FakeUrg, laser: UrgLaser, power_cycle: bool) -> None:
    laser.start()
    before = laser.read(1.0)
    worker = laser._thread
    assert worker is not None
    server.unplug()
    if power_cycle:
        fake.power_cycle()  # a bus-powered URG loses its state with the cable
    assert wait_for(lambda: not laser.connected, 3.0)
    health = laser.health()
    assert not health.connected and health.counters["disconnects"] == 1
    assert health.last_error is not None and "disconnected" in health.last_error
    with pytest.raises(DeviceDisconnected):
        laser.read(0.5)
    with pytest.raises(DeviceDisconnected):
        laser.scan_once(0.5)
    with pytest.raises(DeviceDisconnected):
        laser.start()
    time.sleep(0.6)  # at least one reopen attempt fails while the device is away
    assert worker.is_alive()

    server.replug()
    assert wait_for(lambda: laser.connected, 5.0)
    after = [laser.read(1.0) for _ in range(3)]
    assert worker.is_alive() and laser.streaming
    counters = laser.health().counters
    assert counters["reconnects"] == 1 and counters["disconnects"] == 1
    device = [device_ms(s) for s in after]
    assert device == sorted(device) and len(set(device)) == 3
    if power_cycle:
        # The sensor's clock restarted: a new epoch, recognised by the TM check at reconnect.
        assert counters["clock_resets"] == 1 and max(device) < device_ms(before)
    else:
        assert "clock_resets" not in counters and min(device) > device_ms(before)
    assert after[0].sequence > before.sequence


def test_junk_and_bad_checksums_between_frames(fake: FakeUrg, server: PtyServer) -> None:
    # What is checked is which scans get through, not how fast: on a loaded machine (another process busy
    # on both cores) a scan can come a second late. So the reads wait long, the stall watchdog (tested
    # below) cannot restart the stream in the middle, the queue holds every scan a starved reader has not
    # taken yet, and the scans delivered are compared with those the fake really sent (a starved fake
    # skips scans itself, as the sensor does when its host stops reading).
    with UrgLaser(server.path, timeout_s=2.0, stall_timeout_s=60.0, queue_size=64) as laser:
        laser.start()
        first = laser.read(5.0)
        junk = b"\x00\xffnoise\n\nQT\n"
        fake.inject(junk)
        fake.corrupt_next(2)
        scans = [laser.read(5.0) for _ in range(6)]
        counters = laser.health().counters
    assert counters["bad_frames"] >= 3
    assert counters["discarded_bytes"] >= len(junk) + 2 * 2134
    device = [device_ms(first)] + [device_ms(s) for s in scans]
    assert device == sorted(device)
    sent = [e for e in fake.emitted if device[0] <= e.device_time_ms <= device[-1]]
    assert sum(e.corrupted for e in sent) == 2
    # Exactly the two corrupted scans are missing from what the sensor sent, and nothing was dropped.
    assert device == [e.device_time_ms for e in sent if not e.corrupted]
    assert "scans_dropped" not in counters and "stream_restarts" not in counters
    # Every revolution without a scan is counted: the corrupted two and any the fake skipped.
    assert counters["scans_missed"] == (device[-1] - device[0]) // 100 - len(scans) >= 2


def test_silent_sensor_times_out_without_hanging(fake: FakeUrg, laser: UrgLaser) -> None:
    laser.start()
    laser.read(1.0)
    fake.silent = True
    started = time.monotonic()
    with pytest.raises(DeviceTimeout):
        laser.read(0.3)
    with pytest.raises(DeviceTimeout):
        laser.stop()  # QT goes unanswered
    with pytest.raises(DeviceTimeout):
        laser.scan_once(0.3)  # GD goes unanswered
    assert time.monotonic() - started < 5.0  # bounded by the timeouts, not stuck
    assert laser.health().counters["command_timeouts"] >= 2
    fake.silent = False
    laser.start()
    assert laser.read(1.0).ranges_mm.size == 682


def test_a_stalled_stream_is_restarted(server: PtyServer, fake: FakeUrg) -> None:
    with UrgLaser(server.path, timeout_s=2.0, stall_timeout_s=0.5) as laser:
        laser.start()
        before = laser.read(1.0)
        fake.power_cycle()  # a brown-out: the stream stops, the port stays
        scan = laser.read(3.0)  # the watchdog notices, sends QT and MD again
        counters = laser.health().counters
        assert counters["stream_restarts"] >= 1 and counters["clock_resets"] == 1
        assert scan.ranges_mm.size == 682 and fake.streaming
    # The revolutions between the two scans, by the fake's motor (its clock restarted, the motor did not),
    # were all missed: the stall and the restart.
    step0 = [e.step0_time_s for e in fake.emitted]
    i_before = [e.device_time_ms for e in fake.emitted].index(device_ms(before) % WRAP)
    i_after = len(step0) - 1 - [e.device_time_ms for e in fake.emitted][::-1].index(device_ms(scan) % WRAP)
    revolutions = round((step0[i_after] - step0[i_before]) / fake.period_s)
    assert revolutions >= 5 and counters["scans_missed"] == revolutions - 1


def test_a_silent_spell_is_counted_and_the_stream_taken_back_at_once(
    server: PtyServer, fake: FakeUrg
) -> None:
    stall_s = 2.0
    # Retries of an unanswered restart as slow as the watchdog: only the stream's return can be quick.
    with UrgLaser(
        server.path, timeout_s=0.3, stall_timeout_s=stall_s, reconnect_interval_s=stall_s, queue_size=64
    ) as laser:
        laser.start()
        scans = [laser.read(1.0)]
        fake.silent = True  # the sensor hangs; its motor turns on and the stream is still set up in it
        # The watchdog tries a restart; its QT goes unanswered.
        assert wait_for(lambda: laser.health().counters.get("command_timeouts", 0) >= 1, stall_s + 3.0)
        while True:  # the scans that came before the silence (a loaded machine may not have read them yet)
            try:
                scans.append(laser.read(0.0))
            except DeviceTimeout:
                break
        before = scans[-1]
        fake.silent = False
        back = time.monotonic()
        scans.append(laser.read(stall_s + 2.0))
        waited_s = time.monotonic() - back
        counters = laser.health().counters
    # The stream the sensor still runs is taken as it comes back: no waiting for the next restart, a
    # whole stall timeout after the last one, and no second restart (which would cost five scans).
    assert waited_s < stall_s / 2, waited_s
    assert counters["stream_restarts"] == 1, counters
    silence = (device_ms(scans[-1]) - device_ms(before)) // 100 - 1
    assert silence >= stall_s / fake.period_s, silence
    steps = [(device_ms(b) - device_ms(a)) // 100 for a, b in itertools.pairwise(scans)]
    assert counters["scans_missed"] == sum(step - 1 for step in steps), (counters, steps)


def test_close_is_idempotent_and_ends_the_thread(fake: FakeUrg, laser: UrgLaser) -> None:
    laser.start()
    laser.read(1.0)
    worker = laser._thread
    assert worker is not None
    laser.close()
    laser.close()
    assert not worker.is_alive()
    assert not laser.connected and not laser.health().connected
    with pytest.raises(DeviceDisconnected):
        laser.read(0.1)
    with pytest.raises(DeviceError):
        laser.scan_once(0.1)
    assert wait_for(lambda: not fake.streaming, 1.0)  # QT on the way out


# -- the clock estimator alone -----------------------------------------------------------------------------


def _scan_arrivals(offset_ns: float, device_ms: np.ndarray, delay_ns: float, rng: np.random.Generator,
                   drift: float = 0.0) -> np.ndarray:  # fmt: skip
    """Host receive times: step 0 in host time (with a relative clock drift), the scan's sweep, and an
    exponential queueing delay of mean 3 ms."""
    step0_ns = offset_ns + device_ms * 1e6 * (1.0 + drift)
    return step0_ns + delay_ns + rng.exponential(3e6, device_ms.size) + 5e4


def test_clock_offset_from_round_trips_and_scans() -> None:
    rng = np.random.default_rng(0)
    offset = 7_654_321_000_000.0
    clock = DeviceClock()
    for i in range(5):
        true_ms = 16_777_000.25 + 7.3 * i
        send = int(offset + true_ms * 1e6 - rng.uniform(2e5, 1.5e6))
        recv = int(offset + true_ms * 1e6 + rng.uniform(2e5, 1.5e6))
        unwrapped = clock.unwrap(int(true_ms) % WRAP, (send + recv) // 2, tolerance_ms=5.0)
        clock.observe_round_trip(unwrapped, send, recv)
    estimate = clock.offset_ns(int(offset + 16_777_100 * 1e6))
    assert estimate is not None and abs(estimate - offset) < 1.5e6  # within the round trips
    delay = 726 / 1024 * 100e6
    device = 16_777_100 + 100 * np.arange(60)  # crosses 2^24
    arrivals = _scan_arrivals(offset, device, delay, rng)
    errors = []
    for d, h in zip(device, arrivals, strict=True):
        unwrapped = clock.unwrap(int(d) % WRAP, int(h), delay)
        assert unwrapped == d
        clock.observe_scan(unwrapped, int(h), delay)
        errors.append(clock.host_ns(unwrapped, int(h)) - (offset + d * 1e6))
    assert max(abs(e) for e in errors[20:]) < 1e6  # sub-millisecond once some scan came quickly
    assert clock.resets == 0 and clock.inconsistent == 0


def test_clock_follows_drift_and_long_gaps() -> None:
    rng = np.random.default_rng(1)
    offset, drift = 1e12, 80e-6  # the sensor's crystal 80 ppm off the host's
    delay = 726 / 1024 * 100e6
    clock = DeviceClock()
    device = np.concatenate([100 * np.arange(3000), 30_000_000 + 100 * np.arange(100)])  # 8 h gap > one wrap
    arrivals = _scan_arrivals(offset, device, delay, rng, drift)
    errors = []
    for d, h in zip(device, arrivals, strict=True):
        unwrapped = clock.unwrap(int(d) % WRAP, int(h), delay)
        assert unwrapped == d
        clock.observe_scan(unwrapped, int(h), delay)
        truth = offset + d * 1e6 * (1.0 + drift)
        error = clock.host_ns(unwrapped, int(h)) - truth
        # Never earlier than the truth (every bound stays valid under drift), never later than this very
        # scan's own queueing delay.
        assert -1e3 <= error <= h - (truth + delay) + 1e3
        errors.append(error)
    assert max(errors[20:3000]) < 1e6 and max(errors[-80:]) < 1e6
    assert clock.resets == 0


def test_clock_restart_and_stale_data() -> None:
    delay = 70e6
    clock = DeviceClock()
    for k in range(10):
        recv = int(1e12 + k * 1e8 + delay)
        clock.observe_scan(clock.unwrap(500_000 + 100 * k, recv, delay), recv, delay)
    # Data that waited 2 s in a buffer is old, not a new clock.
    late = clock.unwrap(500_500, int(1e12 + 9e8 + 2e9 + delay), delay)
    assert late == 500_500 and clock.resets == 0
    # A reading far from the prediction: the sensor restarted; a new epoch starts at its raw value.
    assert clock.unwrap(1234, int(1e12 + 1e10), delay) == 1234 and clock.resets == 1
    # Within a TM round trip's tolerance, even a small jump back is a restart.
    clock.observe_scan(1234, int(1e12 + 1e10), delay)
    assert clock.unwrap(1000, int(1e12 + 1e10 + delay), tolerance_ms=50.0) == 1000 and clock.resets == 2


def test_a_command_the_sensor_does_not_take_is_a_timeout_not_a_crash(laser: UrgLaser) -> None:
    """A write timeout (the sensor's side of the line not read: a stalled device or a starved machine) is a
    DeviceTimeout like a missing reply, which the laser loop handles; raised as pyserial's own exception it
    ended the loop that opened the laser."""
    import serial

    port = laser._port
    assert port is not None

    def stuck(data: bytes) -> int:
        raise serial.SerialTimeoutException("Write timeout")

    port.write = stuck  # type: ignore[method-assign]
    with pytest.raises(DeviceTimeout, match="not taken"):
        laser._transact(scip.encode_vv())
