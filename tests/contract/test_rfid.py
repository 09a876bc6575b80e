"""Contract suite for RFID readers: what every backend must do, run on the fake readers over a pty and, when
``VLP_TEST_RFID_PORT`` names a serial port, on a real reader (``VLP_TEST_RFID_PROTOCOL``: id12la, rdm6300 or
mercury; default id12la). On hardware, hold a tag at the reader while the suite runs; set
``VLP_TEST_RFID_TAG`` to its id to also check the id.

The fault tests (unplug, junk, bad checksums, a module that goes quiet) need the fake's switches and run on
the fake only. Waits poll for a condition with a generous deadline; nothing here measures time.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from drivers.errors import ConfigError, DeviceError, DeviceNotFound, DeviceTimeout
from drivers.fakes.pty import PtyServer
from drivers.fakes.rfid import FakeRfidReader, wire_tag_id
from drivers.registry import backend_class
from drivers.rfid import RfidReader
from drivers.rfid.serial_reader import SerialRfidReader
from drivers.samples import TagRead
from drivers.sim.simulation import Simulation
from drivers.sim.world import Person, RfidModel, World

HW_PORT = os.environ.get("VLP_TEST_RFID_PORT")
HW_PROTOCOL = os.environ.get("VLP_TEST_RFID_PROTOCOL", "id12la")
HW_TAG = os.environ.get("VLP_TEST_RFID_TAG")

PROTOCOLS = ["id12la", "rdm6300", "mercury"]
NEAR_TAG = "7C0055F8C4"  # 0.5 m ahead of the robot
BEHIND_TAG = "alice"  # 1 m behind: read by Mercury's second antenna; a 125 kHz reader reads only the nearest
FAR_TAG = "E2003412000000000000AAAA"  # 11 m away, never in range
WAIT_S = 10.0


def wait_for(condition: Callable[[], bool], what: str, timeout_s: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}")
        time.sleep(0.01)


def make_world(protocol: str) -> World:
    return World(
        "rfid-contract",
        rfid=RfidModel(protocol=protocol, range_m=1.5, repeat_s=0.05),
        people=(
            Person("near", NEAR_TAG, ((0.5, 0.0),)),
            Person("behind", BEHIND_TAG, ((-1.0, 0.1),)),
            Person("far", FAR_TAG, ((8.0, 8.0),)),
        ),
    )


@dataclass
class Rig:
    reader: SerialRfidReader
    protocol: str
    expected: set[str] | None  # tag ids that may be read; None on hardware without VLP_TEST_RFID_TAG
    opened_ns: int
    fake: FakeRfidReader | None = None
    server: PtyServer | None = None


@dataclass
class FakeRig:
    protocol: str
    sim: Simulation
    fake: FakeRfidReader
    server: PtyServer
    link: Path

    def reader(self, **options: object) -> SerialRfidReader:
        options.setdefault("command_timeout_s", 0.5)
        return SerialRfidReader(str(self.link), protocol=self.protocol, **options)  # type: ignore[arg-type]

    def expected(self) -> set[str]:
        ids = {wire_tag_id(NEAR_TAG, self.protocol)}
        if self.protocol == "mercury":
            ids.add(wire_tag_id(BEHIND_TAG, self.protocol))
        return ids


@pytest.fixture(params=PROTOCOLS)
def fake_rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[FakeRig]:
    protocol = request.param
    sim = Simulation(make_world(protocol))
    fake = FakeRfidReader(sim, antennas=2, seed=1)
    link = tmp_path / "rfid"
    server = PtyServer(fake, link=link)
    server.start()
    try:
        yield FakeRig(protocol, sim, fake, server, link)
    finally:
        server.close()


@pytest.fixture
def mercury_rig(tmp_path: Path) -> Iterator[FakeRig]:
    sim = Simulation(make_world("mercury"))
    fake = FakeRfidReader(sim, antennas=2, keepalive_s=0.1, seed=2)
    link = tmp_path / "rfid"
    server = PtyServer(fake, link=link)
    server.start()
    try:
        yield FakeRig("mercury", sim, fake, server, link)
    finally:
        server.close()


@pytest.fixture(params=[*PROTOCOLS, "hardware"])
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Rig]:
    if request.param == "hardware":
        if not HW_PORT:
            pytest.skip("set VLP_TEST_RFID_PORT (and VLP_TEST_RFID_PROTOCOL) to run on a real reader")
        reader = SerialRfidReader(HW_PORT, protocol=HW_PROTOCOL)
        opened_ns = time.monotonic_ns()
        reader.open()
        try:
            yield Rig(reader, HW_PROTOCOL, {HW_TAG.upper()} if HW_TAG else None, opened_ns)
        finally:
            reader.close()
        return
    protocol = request.param
    fake = FakeRfidReader(Simulation(make_world(protocol)), antennas=2, seed=3)
    with PtyServer(fake, link=tmp_path / "rfid") as server:
        reader = SerialRfidReader(server.path, protocol=protocol, command_timeout_s=0.5)
        opened_ns = time.monotonic_ns()
        reader.open()
        try:
            expected = {wire_tag_id(NEAR_TAG, protocol)}
            if protocol == "mercury":
                expected.add(wire_tag_id(BEHIND_TAG, protocol))
            yield Rig(reader, protocol, expected, opened_ns, fake, server)
        finally:
            reader.close()


def collect(reader: RfidReader, until: Callable[[list[TagRead]], bool], what: str) -> list[TagRead]:
    reads: list[TagRead] = []
    deadline = time.monotonic() + WAIT_S
    while not until(reads):
        if time.monotonic() > deadline:
            pytest.fail(f"gave up waiting for {what}; got {reads[-5:]}")
        tag = reader.read(timeout_s=0.2)
        if tag is not None:
            reads.append(tag)
    return reads


# ---------------------------------------------------------------------------------------------------
# the contract (fake and hardware)
# ---------------------------------------------------------------------------------------------------


def test_reads_the_tags_in_range(rig: Rig) -> None:
    wanted = rig.expected or set()
    reads = collect(
        rig.reader,
        lambda got: bool(got) and wanted <= {t.tag_id for t in got} and len(got) >= 4,
        f"reads of {sorted(wanted) or 'any tag'}",
    )
    after = time.monotonic_ns()
    for tag in reads:
        if rig.expected is not None:
            assert tag.tag_id in rig.expected
        assert tag.reader == "rfid"
        assert rig.opened_ns <= tag.host_time_ns <= after
        if rig.protocol == "mercury":
            assert tag.rssi_dbm is not None and -110 <= tag.rssi_dbm <= -20
            assert tag.antenna is not None and 1 <= tag.antenna <= 15
        else:
            assert tag.rssi_dbm is None and tag.antenna is None
    times = [t.host_time_ns for t in reads]
    assert times == sorted(times)
    health = rig.reader.health()
    assert health.connected
    assert health.counters["tag_reads"] >= len(reads)
    assert health.counters["frames"] >= len(reads)


def test_close_is_idempotent_and_reading_a_closed_reader_raises(rig: Rig) -> None:
    rig.reader.close()
    rig.reader.close()
    assert not rig.reader.health().connected
    with pytest.raises(DeviceError):
        rig.reader.read(timeout_s=0.1)


def test_reads_iterator_ends_when_the_reader_closes(rig: Rig) -> None:
    got = []
    for tag in rig.reader.reads(timeout_s=WAIT_S):
        got.append(tag)
        if len(got) == 2:
            rig.reader.close()
    assert len(got) == 2  # the iterator ended at close, and nothing queued before it was handed out


# ---------------------------------------------------------------------------------------------------
# the fake's geometry
# ---------------------------------------------------------------------------------------------------


def test_mercury_reports_rssi_falling_with_distance_and_antenna_by_bearing(mercury_rig: FakeRig) -> None:
    near, behind = wire_tag_id(NEAR_TAG, "mercury"), wire_tag_id(BEHIND_TAG, "mercury")
    with mercury_rig.reader() as reader:
        reads = collect(
            reader,
            lambda got: sum(t.tag_id == near for t in got) >= 5 and sum(t.tag_id == behind for t in got) >= 5,
            "five reads of each tag",
        )
    assert wire_tag_id(FAR_TAG, "mercury") not in {t.tag_id for t in reads}
    assert {t.antenna for t in reads if t.tag_id == near} == {1}  # ahead: the forward antenna
    assert {t.antenna for t in reads if t.tag_id == behind} == {2}  # behind: the rear antenna

    def mean_rssi(tag_id: str) -> float:
        values = [t.rssi_dbm for t in reads if t.tag_id == tag_id and t.rssi_dbm is not None]
        return sum(values) / len(values)

    # 0.5 m vs 1 m with 1 dB of noise: free-space loss alone puts the near tag 6 dB stronger.
    assert mean_rssi(near) > mean_rssi(behind) + 3.0


@pytest.mark.parametrize("fake_rig", ["id12la", "rdm6300"], indirect=True)
def test_ascii_reader_reads_only_the_nearest_tag(fake_rig: FakeRig) -> None:
    with fake_rig.reader() as reader:
        reads = collect(reader, lambda got: len(got) >= 6, "six reads")
    assert {t.tag_id for t in reads} == {NEAR_TAG}


# ---------------------------------------------------------------------------------------------------
# faults (fake only)
# ---------------------------------------------------------------------------------------------------


def test_junk_between_frames_is_skipped_and_counted(fake_rig: FakeRig) -> None:
    junk = b"\x00\x13 line noise \x02\x02\xff\x80\x7f" * 3
    with fake_rig.reader() as reader:
        collect(reader, lambda got: len(got) >= 2, "reads before the junk")
        for _ in range(3):
            fake_rig.fake.inject(junk)
            wait_for(lambda: fake_rig.fake.injected_pending == 0, "the junk to go out")
        reads = collect(reader, lambda got: len(got) >= 10, "reads after the junk")
        counters = reader.health().counters
    assert {t.tag_id for t in reads} <= fake_rig.expected()
    assert counters["discarded_bytes"] >= 3 * len(junk)
    assert counters["resyncs"] >= 1


def test_bad_checksums_are_dropped_and_counted(fake_rig: FakeRig) -> None:
    with fake_rig.reader() as reader:
        collect(reader, lambda got: len(got) >= 2, "reads before the bad frames")
        fake_rig.fake.corrupt_next(4)
        wait_for(lambda: reader.health().counters.get("bad_checksums", 0) >= 4, "four bad checksums")
        reads = collect(reader, lambda got: len(got) >= 4, "reads after the bad frames")
    assert {t.tag_id for t in reads} <= fake_rig.expected()


def test_unplug_is_reported_and_the_reader_reconnects(fake_rig: FakeRig) -> None:
    with fake_rig.reader(reconnect_interval_s=0.05) as reader:
        collect(reader, lambda got: len(got) >= 1, "a read before the unplug")
        fake_rig.server.unplug()
        unplugged = time.monotonic_ns()
        fake_rig.fake.power_cycle()  # a module loses power with its cable
        wait_for(lambda: not reader.health().connected, "the disconnect to show in health")
        health = reader.health()
        assert health.counters["disconnects"] == 1
        # The loss itself, or (once the reconnect loop has tried) the port that is not there.
        assert health.last_error is not None
        assert health.last_error.startswith(("DeviceDisconnected", "DeviceNotFound")), health.last_error
        stale = reader.drain()
        assert all(t.host_time_ns < unplugged for t in stale)  # nothing is read while the port is gone
        fake_rig.server.replug()
        wait_for(lambda: reader.health().connected, "the reconnect")
        replugged = time.monotonic_ns()
        reader.drain()
        reads = collect(
            reader, lambda got: any(t.host_time_ns > replugged for t in got), "a read after replug"
        )
        health = reader.health()
    assert health.counters["reconnects"] == 1
    assert {t.tag_id for t in reads} <= fake_rig.expected()


def test_missing_port_is_device_not_found(tmp_path: Path) -> None:
    reader = SerialRfidReader(str(tmp_path / "no-such-port"), protocol="rdm6300")
    with pytest.raises(DeviceNotFound):
        reader.open()
    assert not reader.is_open


def test_debounce_reports_a_tag_once_per_presence(fake_rig: FakeRig) -> None:
    with fake_rig.reader(debounce_s=60.0) as reader:
        first = reader.read(timeout_s=WAIT_S)
        assert first is not None
        wait_for(lambda: reader.health().counters.get("debounced", 0) >= 6, "repeats to be debounced")
        later = reader.drain()
    # With one tag (125 kHz) every repeat is suppressed; Mercury may add the second tag's first read.
    assert first.tag_id not in {t.tag_id for t in later}
    assert len(later) <= len(fake_rig.expected()) - 1


def test_a_consumer_that_stalls_loses_the_oldest_reads_counted(fake_rig: FakeRig) -> None:
    with fake_rig.reader(queue_size=3) as reader:
        wait_for(lambda: reader.health().counters.get("dropped", 0) >= 2, "the queue to overflow")
        queued = reader.drain()
    assert len(queued) <= 3


def test_mercury_connect_sequence(mercury_rig: FakeRig) -> None:
    with mercury_rig.reader(read_power_dbm=20.0, antenna_ports=(1, 2)) as reader:
        assert reader.version is not None and reader.version.firmware == "01.03.01.47"
        assert mercury_rig.fake.streaming
    wait_for(lambda: len(mercury_rig.fake.received) == 9, "the stop request sent by close()")
    sent = [(r.opcode, r.data) for r in mercury_rig.fake.received]
    assert [op for op, _ in sent] == [0x2F, 0x03, 0x97, 0x93, 0x91, 0x92, 0x9A, 0x2F, 0x2F]
    assert sent[0][1] == bytes.fromhex("000002")  # stop a read left running
    assert sent[2][1] == b"\x0d"  # North America
    assert sent[4][1] == bytes.fromhex("0201010202")  # search list: antennas 1 and 2
    assert sent[5][1] == (2000).to_bytes(2, "big")  # 20.00 dBm
    assert sent[7][1][2] == 0x01  # start the continuous read
    assert sent[8][1] == bytes.fromhex("000002")  # close() leaves the module idle
    assert not mercury_rig.fake.streaming


def test_mercury_reader_that_does_not_answer_is_a_timeout(mercury_rig: FakeRig) -> None:
    mercury_rig.fake.silent = True
    reader = mercury_rig.reader(command_timeout_s=0.3)
    with pytest.raises(DeviceTimeout, match="version query"):
        reader.open()
    assert not reader.is_open


def test_mercury_reader_that_goes_quiet_is_restarted(mercury_rig: FakeRig) -> None:
    fake = mercury_rig.fake
    with mercury_rig.reader(
        keepalive_timeout_s=0.3, command_timeout_s=1.0
    ) as reader:  # 1 s: the open must not fail on a loaded machine
        collect(reader, lambda got: len(got) >= 2, "reads before the silence")
        seen = fake.requests_received
        fake.silent = True
        wait_for(lambda: not reader.health().connected, "the stall to show in health")
        wait_for(lambda: fake.requests_received >= seen + 2, "the restart's stop and version requests")
        health = reader.health()
        assert health.counters["stalls"] >= 1
        assert health.last_error is not None and "DeviceTimeout" in health.last_error
        fake.power_cycle()  # it was a brown-out: the module comes back idle
        fake.silent = False
        wait_for(lambda: reader.health().connected, "the restart")
        restarted = time.monotonic_ns()
        collect(reader, lambda got: any(t.host_time_ns > restarted for t in got), "a read after the restart")
        assert reader.health().counters["restarts"] >= 1
        assert fake.streaming


def test_mercury_reader_that_was_only_busy_recovers_without_a_restart(mercury_rig: FakeRig) -> None:
    fake = mercury_rig.fake
    with mercury_rig.reader(keepalive_timeout_s=0.3, command_timeout_s=5.0) as reader:
        collect(reader, lambda got: len(got) >= 2, "reads before the silence")
        seen = fake.requests_received
        fake.silent = True
        wait_for(lambda: not reader.health().connected, "the stall to show in health")
        # The restart's stop and version went unanswered; the driver now waits for the version answer.
        wait_for(lambda: fake.requests_received >= seen + 2, "the restart's stop and version requests")
        fake.silent = False  # still streaming: the next keep-alive or record proves it alive
        wait_for(lambda: reader.health().connected, "the recovery")
        counters = reader.health().counters
    assert counters["recoveries"] >= 1
    assert counters.get("restarts", 0) == 0
    # close() interrupted the wait for the version answer and left the module idle.
    wait_for(lambda: not fake.streaming, "the stop request sent by close()")


def test_mercury_status_errors_fail_the_open(mercury_rig: FakeRig) -> None:
    # The module refuses more than 27 dBm; the driver refuses to ask for it in the first place.
    with pytest.raises(ConfigError, match="read_power_dbm"):
        mercury_rig.reader(read_power_dbm=30.0)


# ---------------------------------------------------------------------------------------------------
# registry
# ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", PROTOCOLS)
def test_registry_names_the_serial_reader(backend: str) -> None:
    cls = backend_class("rfid", backend)
    assert cls is SerialRfidReader
    reader = cls("loop://", protocol=backend)
    assert reader.protocol == backend
    assert reader.baudrate == (115200 if backend == "mercury" else 9600)


def test_any_pyserial_url_works(tmp_path: Path) -> None:
    # loop:// echoes what is written; a 125 kHz reader writes nothing, so nothing is read.
    with SerialRfidReader("loop://", protocol="id12la") as reader:
        assert reader.health().connected
        assert reader.read(timeout_s=0.1) is None
    with pytest.raises(ConfigError, match=r"rfid\.port"):
        SerialRfidReader("nosuchscheme://x", protocol="id12la").open()


def test_unknown_protocol_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"rfid\.protocol"):
        SerialRfidReader("loop://", protocol="em4100")
