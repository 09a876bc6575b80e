"""A fake RFID reader that speaks the real frames, for the tags simulated people carry.

:class:`FakeRfidReader` is a :class:`~drivers.fakes.pty.ByteDevice`: serve it with
``PtyServer(FakeRfidReader(sim))`` and point any client (our driver, a terminal, SparkFun-style code) at
the pty. What it sends depends on ``world.rfid.protocol``:

* ``id12la`` / ``rdm6300``: the reader takes no commands; while a tag is within ``world.rfid.range_m`` of
  the robot it sends that tag's frame every ``world.rfid.repeat_s`` (the RDM6300 repeats about every
  220 ms). A 125 kHz reader has no anti-collision, so only the nearest tag in range is read.
* ``mercury``: a ThingMagic M6e-style module. It answers the version query and the configuration commands
  of the connect sequence, and after the continuous-read command streams a tag record per tag in range every
  ``repeat_s`` (Gen2 anti-collision reads them all) plus a keep-alive every ``keepalive_s``, as the captures
  in SparkFun's "Example Communication Logs" show. RSSI falls with distance (log-distance path loss) and
  with the angle off the antenna's boresight; with two antennas, port 1 looks forward and port 2 back.
  When the world gives ``rfid.antenna_yaws_rad``, the reader has those antennas instead and works as an
  M6e Micro does: every repeat it reads each port of the antenna search list the host set (command 91h;
  port 1 alone until it sets one) in turn, and a tag is read on a port when its RSSI there, from the
  channel model of :mod:`drivers.sim.rfid_channel` (walls' reflections, scatterers, the wearer's body),
  reaches ``rfid.sensitivity_dbm``; the phase is the channel's.

Fault switches for tests: :attr:`FakeRfidReader.silent` (the reader stops answering and sending),
:meth:`FakeRfidReader.inject` (raw junk on the line), :meth:`FakeRfidReader.corrupt_next` (frames with a
broken checksum), :meth:`FakeRfidReader.power_cycle` (what a re-plugged module looks like: idle).

Tag ids: a person's ``tag_id`` that is already valid for the protocol (10 hex digits for 125 kHz, whole
16-bit words of hex for an EPC) is sent as is; any other string is mapped by :func:`wire_tag_id` to a stable
hex id, which is what a driver will report.
"""

from __future__ import annotations

import collections
import hashlib
import logging
import math
import re
import threading

import numpy as np

from drivers.sim.raycast import walls_array
from drivers.sim.rfid_channel import AntennaSite, RfidChannel
from drivers.sim.simulation import Simulation, TagInRange
from firmware_protocol.rfid import (
    GEN2_PROTOCOL,
    AsciiFormat,
    MercuryOpcode,
    MercuryRequest,
    MercuryRequestDecoder,
    MercuryStatus,
    MercuryTagRead,
    MercuryVersion,
    crc16_gen2,
    encode_ascii_frame,
    encode_response,
    encode_tag_read,
    encode_version_response,
)

__all__ = ["DEFAULT_VERSION", "FakeRfidReader", "wire_tag_id"]

log = logging.getLogger(__name__)

# The version answer of the M6e Nano in SparkFun's logs ("1-Connect to serial port.txt"): bootloader
# 14120800, hardware 30000002, firmware date 2015-03-10, firmware 01.03.01.47, protocols bit mask 0x10 (Gen2).
DEFAULT_VERSION = MercuryVersion(
    bytes.fromhex("14120800"),
    bytes.fromhex("30000002"),
    bytes.fromhex("20150310"),
    bytes.fromhex("01030147"),
    0x00000010,
)

_ASCII_ID = re.compile(r"[0-9A-Fa-f]{10}")
_EPC_ID = re.compile(r"(?:[0-9A-Fa-f]{4}){1,15}")
_MAX_POWER_CDBM = 2700  # SparkFun setReadPower(): "Maximum power is 2700 = 27.00 dBm"

# North-American hop table of the M6e (902.75..927.25 MHz in 500 kHz steps); the one real frequency in the
# SparkFun logs, 923.2 MHz, is on it.
_HOP_TABLE_KHZ = tuple(902_750 + 500 * k for k in range(50))


def wire_tag_id(tag_id: str, protocol: str) -> str:
    """The hex id the reader puts on the wire for a simulated tag (what a driver reports)."""
    if protocol == "mercury":
        if _EPC_ID.fullmatch(tag_id):
            return tag_id.upper()
        return hashlib.sha256(tag_id.encode()).digest()[:12].hex().upper()  # a 96-bit EPC, the usual size
    if _ASCII_ID.fullmatch(tag_id):
        return tag_id.upper()
    return hashlib.sha256(tag_id.encode()).digest()[:5].hex().upper()


class FakeRfidReader:
    """A fake reader over a :class:`Simulation`; see the module docstring for what it sends."""

    def __init__(
        self,
        sim: Simulation,
        protocol: str | None = None,
        *,
        range_m: float | None = None,
        repeat_s: float | None = None,
        antennas: int | None = None,
        keepalive_s: float = 1.0,
        rssi_at_1m_dbm: float = -50.0,
        rssi_noise_db: float = 1.0,
        version: MercuryVersion = DEFAULT_VERSION,
        seed: int = 0,
    ) -> None:
        model = sim.world.rfid
        self.sim = sim
        self.protocol = protocol if protocol is not None else model.protocol
        if self.protocol not in ("id12la", "rdm6300", "mercury"):
            raise ValueError(f"unknown RFID protocol {self.protocol!r}")
        self.channel: RfidChannel | None = None
        if model.antenna_yaws_rad and self.protocol == "mercury":
            antennas = len(model.antenna_yaws_rad) if antennas is None else antennas
            if antennas != len(model.antenna_yaws_rad):
                raise ValueError(
                    f"the world's reader has {len(model.antenna_yaws_rad)} antennas, not {antennas}"
                )
            sites = tuple(
                AntennaSite(model.antenna_radius_m * math.cos(y), model.antenna_radius_m * math.sin(y), y)
                for y in model.antenna_yaws_rad
            )
            self.channel = RfidChannel(
                walls_array(sim.world.walls),
                sites,
                beamwidth_rad=model.beamwidth_rad,
                front_to_back_db=model.front_to_back_db,
                rssi_at_1m_dbm=model.rssi_at_1m_dbm,
                wall_reflection=model.wall_reflection,
                scatterers=model.scatterers,
                scatter_amplitude=model.scatter_amplitude,
                body_loss_db=model.body_loss_db,
                noise_db=model.noise_db,
                seed=seed,
                layout_seed=model.scatter_seed,
            )
        antennas = 1 if antennas is None else antennas
        if self.channel is None and antennas not in (1, 2):
            raise ValueError("antennas must be 1 or 2")
        self.range_m = model.range_m if range_m is None else range_m
        self.repeat_s = model.repeat_s if repeat_s is None else repeat_s
        self.antennas = antennas
        self.keepalive_s = keepalive_s
        self.rssi_at_1m_dbm = rssi_at_1m_dbm
        self.rssi_noise_db = rssi_noise_db
        self.version = version
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._requests = MercuryRequestDecoder()
        self._last_sent: dict[str, float] = {}
        self._injected = bytearray()
        self._corrupt = 0
        self._silent = False
        self._streaming = False
        self._last_keepalive = 0.0
        # Mercury: the ports of the host's antenna search list (command 91h, option 02); 1 at power-on.
        self.search_ports: tuple[int, ...] = (1,)
        self._cycle_due = -math.inf
        self._seen_at: dict[str, tuple[float, float]] = {}
        self._heading: dict[str, tuple[float, float]] = {}
        self.received: collections.deque[MercuryRequest] = collections.deque(maxlen=64)
        self.requests_received = 0
        self.frames_sent = 0

    # -- switches ------------------------------------------------------------------------------------
    @property
    def silent(self) -> bool:
        return self._silent

    @silent.setter
    def silent(self, value: bool) -> None:
        """A silent reader takes commands in but neither acts on them nor sends anything (hung firmware)."""
        with self._lock:
            self._silent = value

    @property
    def streaming(self) -> bool:
        """Mercury: whether a continuous read is running."""
        return self._streaming

    def inject(self, data: bytes) -> None:
        """Send ``data`` as is with the next output (line noise, a second device on the line)."""
        with self._lock:
            self._injected += data

    @property
    def injected_pending(self) -> int:
        """Injected bytes not sent yet."""
        with self._lock:
            return len(self._injected)

    def corrupt_next(self, frames: int = 1) -> None:
        """Send the next ``frames`` tag frames with a wrong checksum."""
        with self._lock:
            self._corrupt += frames

    def power_cycle(self) -> None:
        """Back to the power-on state: no continuous read, nothing half-received."""
        with self._lock:
            self._streaming = False
            self._requests.reset()
            self._last_sent.clear()
            self.search_ports = (1,)

    # -- ByteDevice ------------------------------------------------------------------------------------
    def receive(self, data: bytes, now: float) -> bytes:
        with self._lock:
            if self.protocol != "mercury":
                return b""  # 125 kHz readers have no command channel; anything written is ignored
            out = bytearray()
            for request in self._requests.feed(data):
                self.received.append(request)
                self.requests_received += 1
                if not self._silent:  # a hung module still takes the bytes in, it just does not act
                    out += self._answer(request, now)
            return bytes(out)

    def poll(self, now: float) -> bytes:
        with self._lock:
            out = bytearray(self._injected)
            self._injected.clear()
            if self._silent:
                return bytes(out)
            if self.protocol == "mercury":
                if self._streaming:
                    out += self._stream(now)
            else:
                out += self._ascii(now)
            return bytes(out)

    # -- 125 kHz -----------------------------------------------------------------------------------
    def _ascii(self, now: float) -> bytes:
        tags = self.sim.tags_in_range(self.range_m)
        if not tags:
            return b""
        tag = min(tags, key=lambda t: t.distance_m)
        if now - self._last_sent.get(tag.tag_id, -math.inf) < self.repeat_s:
            return b""
        self._last_sent[tag.tag_id] = now
        frame = bytearray(
            encode_ascii_frame(
                bytes.fromhex(wire_tag_id(tag.tag_id, self.protocol)), AsciiFormat(self.protocol)
            )
        )
        if self._corrupt:
            self._corrupt -= 1
            frame[12] = ord("0") if frame[12] != ord("0") else ord("1")  # low checksum digit
        self.frames_sent += 1
        return bytes(frame)

    # -- Mercury -----------------------------------------------------------------------------------------
    def _answer(self, request: MercuryRequest, now: float) -> bytes:
        op, data = request.opcode, request.data
        if op == MercuryOpcode.VERSION:
            if data:
                return encode_response(op, MercuryStatus.WRONG_NUMBER_OF_DATA)
            return encode_version_response(self.version)
        if op == MercuryOpcode.SET_READ_TX_POWER:
            if len(data) != 2:
                return encode_response(op, MercuryStatus.WRONG_NUMBER_OF_DATA)
            if int.from_bytes(data, "big", signed=True) > _MAX_POWER_CDBM:
                return encode_response(op, MercuryStatus.POWER_TOO_HIGH)
            return encode_response(op)
        if op == MercuryOpcode.SET_TAG_PROTOCOL:
            if len(data) != 2:
                return encode_response(op, MercuryStatus.WRONG_NUMBER_OF_DATA)
            if int.from_bytes(data, "big") != GEN2_PROTOCOL:
                return encode_response(op, MercuryStatus.INVALID_PARAMETER_VALUE)
            return encode_response(op)
        if op == MercuryOpcode.SET_ANTENNA_PORT and len(data) >= 3 and data[0] == 0x02 and len(data) % 2 == 1:
            ports = tuple(data[i] for i in range(1, len(data), 2))  # (TX, RX) pairs: the TX ports
            if not all(1 <= p <= self.antennas for p in ports):
                return encode_response(op, MercuryStatus.INVALID_PARAMETER_VALUE)
            self.search_ports = ports
            return encode_response(op)
        if op == MercuryOpcode.SET_ANTENNA_PORT and len(data) == 2:
            if not 1 <= data[0] <= self.antennas:
                return encode_response(op, MercuryStatus.INVALID_PARAMETER_VALUE)
            self.search_ports = (data[0],)
            return encode_response(op)
        if op in (
            MercuryOpcode.SET_REGION,
            MercuryOpcode.SET_ANTENNA_PORT,
            MercuryOpcode.SET_READER_OPTIONAL_PARAMS,
        ):
            return encode_response(op) if data else encode_response(op, MercuryStatus.WRONG_NUMBER_OF_DATA)
        if op == MercuryOpcode.MULTI_PROTOCOL_TAG_OP and len(data) >= 3:
            option = data[2]
            if option == 0x01:  # start continuous read; the log's answer: 01 22 00 00
                self._streaming = True
                self._last_keepalive = now
                self._last_sent.clear()
                return encode_response(op, 0, bytes([0x01, MercuryOpcode.READ_TAG_ID_MULTIPLE, 0x00, 0x00]))
            if option == 0x02:  # stop; the log's answer: 02
                self._streaming = False
                return encode_response(op, 0, b"\x02")
            return encode_response(op, MercuryStatus.INVALID_PARAMETER_VALUE)
        return encode_response(op, MercuryStatus.INVALID_OPCODE)

    def _stream(self, now: float) -> bytes:
        out = bytearray()
        if now - self._last_keepalive >= self.keepalive_s:
            self._last_keepalive = now
            out += encode_response(MercuryOpcode.READ_TAG_ID_MULTIPLE, MercuryStatus.NO_TAGS_FOUND)
        if self.channel is not None:
            return bytes(out + self._stream_channel(now))
        for tag in self.sim.tags_in_range(self.range_m):
            if now - self._last_sent.get(tag.tag_id, -math.inf) < self.repeat_s:
                continue
            self._last_sent[tag.tag_id] = now
            frame = bytearray(encode_tag_read(self._record(tag, now)))
            if self._corrupt:
                self._corrupt -= 1
                frame[-1] ^= 0x5A
            self.frames_sent += 1
            out += frame
        return bytes(out)

    def _stream_channel(self, now: float) -> bytes:
        """One read cycle every ``repeat_s``: each search-list port in turn, each tag in range."""
        channel = self.channel
        assert channel is not None
        if now < self._cycle_due:
            return b""
        self._cycle_due = now + self.repeat_s
        out = bytearray()
        base = self.sim.pose()
        people = {p.name: p for p in self.sim.world.people}
        sensitivity = self.sim.world.rfid.sensitivity_dbm
        for tag in self.sim.tags_in_range(self.range_m):
            person = people[tag.person]
            x, y = self.sim.person_position(person)
            away = self._walking_away(person.name, (x, y), (base.x_m, base.y_m))
            frequency_khz = _HOP_TABLE_KHZ[int(self._rng.integers(len(_HOP_TABLE_KHZ)))]
            rssi, phase = channel.read((base.x_m, base.y_m), base.yaw_rad, (x, y), away, frequency_khz * 1e3)
            for port in self.search_ports:
                if rssi[port - 1] < sensitivity:
                    continue
                frame = bytearray(
                    encode_tag_read(
                        self._tag_read(
                            tag, now, float(rssi[port - 1]), port, frequency_khz, float(phase[port - 1])
                        )
                    )
                )
                if self._corrupt:
                    self._corrupt -= 1
                    frame[-1] ^= 0x5A
                self.frames_sent += 1
                out += frame
        return bytes(out)

    def _walking_away(self, name: str, xy: tuple[float, float], robot_xy: tuple[float, float]) -> bool:
        """Whether the wearer's back is to the robot: they face where they last walked (kept while they
        stand), and the robot is more than 90 degrees off that."""
        last = self._seen_at.setdefault(name, xy)
        dx, dy = xy[0] - last[0], xy[1] - last[1]
        if math.hypot(dx, dy) > 0.05:
            self._heading[name] = (dx, dy)
            self._seen_at[name] = xy
        heading = self._heading.get(name)
        if heading is None:
            return False
        to_robot = (robot_xy[0] - xy[0], robot_xy[1] - xy[1])
        return heading[0] * to_robot[0] + heading[1] * to_robot[1] < 0.0

    def _tag_read(
        self, tag: TagInRange, now: float, rssi: float, port: int, frequency_khz: int, phase_deg: float
    ) -> MercuryTagRead:
        epc = bytes.fromhex(wire_tag_id(tag.tag_id, "mercury"))
        pc = (len(epc) // 2) << 11
        return MercuryTagRead(
            rssi_dbm=int(max(-110, min(-20, round(rssi)))),
            tx_antenna=port,
            rx_antenna=port,
            frequency_khz=frequency_khz,
            timestamp_ms=max(0, int((now - self._last_keepalive) * 1000)),
            phase_deg=round(phase_deg) % 181,
            protocol=GEN2_PROTOCOL,
            pc=pc,
            epc=epc,
            epc_crc=crc16_gen2(pc.to_bytes(2, "big") + epc),
        )

    def _record(self, tag: TagInRange, now: float) -> MercuryTagRead:
        # Antenna 1 looks forward (bearing 0), antenna 2 backward; each has a cosine-shaped pattern, 0 dB on
        # boresight and -12 dB behind.
        port = 1 if self.antennas == 1 or math.cos(tag.bearing_rad) >= 0 else 2
        boresight = 0.0 if port == 1 else math.pi
        gain_db = 6.0 * math.cos(tag.bearing_rad - boresight) - 6.0
        # Log-distance path loss with exponent 2 (free space), the same scale as SparkFun's -60 dBm reads.
        rssi = self.rssi_at_1m_dbm - 20.0 * math.log10(max(tag.distance_m, 0.05)) + gain_db
        rssi += float(self._rng.normal(0.0, self.rssi_noise_db))
        epc = bytes.fromhex(wire_tag_id(tag.tag_id, "mercury"))
        pc = (len(epc) // 2) << 11  # Gen2 PC word: EPC length in words in the top 5 bits
        return MercuryTagRead(
            rssi_dbm=int(max(-110, min(-20, round(rssi)))),
            tx_antenna=port,
            rx_antenna=port,
            frequency_khz=_HOP_TABLE_KHZ[int(self._rng.integers(len(_HOP_TABLE_KHZ)))],
            timestamp_ms=max(0, int((now - self._last_keepalive) * 1000)),
            phase_deg=int(self._rng.integers(0, 181)),
            protocol=GEN2_PROTOCOL,
            pc=pc,
            epc=epc,
            epc_crc=crc16_gen2(pc.to_bytes(2, "big") + epc),
        )
