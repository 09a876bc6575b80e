"""A fake Hokuyo URG-04LX(-UG01) that speaks SCIP 2.0 byte for byte, as a ``ByteDevice`` for ``PtyServer``.

It answers QT, SCIP2.0, VV, PP, II, BM, RS, TM0/1/2, SS, GD/GS and MD/MS with the statuses of the Hokuyo
spec (C-42-03320B), refuses bad parameters with the documented codes, and answers anything else with 0E.
Its device facts are the real URG-04LX-UG01's PP values (taken from the world's ``LaserModel``).

Timing follows the sensor, because clients depend on it: the motor turns at SCAN rpm (600: 100 ms per
scan) from the moment the fake first sees time; the 24-bit millisecond timestamp is the clock value at
step 0 of a scan (spec p.12); a scan's data leaves the sensor once its last requested step has been
measured, so MD scans are paced one per revolution and never arrive together (hokuyolx breaks on two
replies in one read). Time is the simulation's clock when there is a simulation, else the ``now`` that
``PtyServer`` passes.

Ranges are ray-cast from the world with ``Simulation.laser_ranges_m`` at the middle of the scan, with the
``LaserModel``'s Gaussian noise and dropout. Beams that return nothing are reported as the URG-04LX does:

* no hit within DMAX -> 0. The real captures B and C report 0 in runs where the sensor looks into open
  space (the spec's table 3: "detected object is possibly at 22 m", i.e. nothing measurable in range);
* a noisy reading outside DMIN..DMAX -> 6 ("others"); capture C has runs of 6 next to its last ~5.5 m
  returns, which is where such readings show up;
* a dropout (weak return, ``LaserModel.dropout``) -> 1 ("reflected light has low intensity", table 3);
* steps outside AMIN..AMAX (the dead zone behind the sensor) -> 19 ("non-measurable step").

With cluster count > 1 each group reports its smallest non-error value, or its smallest error code when
all of its steps are errors (spec p.10 only covers the first case). Values that do not fit in the 2
characters of GS/MS (> 4095 mm) are reported as 0, the sensor's own "nothing in range" code (an
assumption: the spec does not say).

Without a simulation the fake replays fixed ranges: the 682 values given as ``fixed_ranges_mm`` (e.g. a
real capture decoded, which then comes back byte for byte), or a built-in fixed room.

The USB model (the default) hands its output to the host as fast as the host reads. With ``link_bitrate``
the fake is the RS-232 model on a serial line of that rate: each byte takes 10 bit times (8N1), replies
leave one after the other, and a streamed scan that is finished while the line is still busy with the
previous one is skipped (counted in ``scans_skipped``): the sensor sends the latest scan it has once the
line is free rather than queueing without bound (an assumption: the spec does not say what a URG does when
its line is slower than its scans). ``SS`` changes only the rate II reports; the line keeps its rate.

Fault injection for tests: ``silent`` (the sensor hangs), ``hardware_fault`` (laser trouble statuses),
``inject(junk)`` (bytes between replies), ``corrupt_next(n)`` (break a data checksum in the next n scans)
and ``power_cycle()`` (what a USB pull does to a bus-powered URG: laser off, streaming stopped, clock
restarted).
"""

from __future__ import annotations

import collections
import logging
import math
import re
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import numpy.typing as npt

from drivers.sim.raycast import cast_rays, walls_array
from drivers.sim.simulation import Simulation
from drivers.sim.world import LaserModel, Wall
from firmware_protocol import scip

log = logging.getLogger(__name__)

__all__ = ["ERR_LOW_INTENSITY", "ERR_NOT_MEASURABLE", "ERR_NO_ECHO", "ERR_OTHER", "EmittedScan", "FakeUrg"]

# URG-04LX error codes used by the fake (spec p.12, table 3).
ERR_NO_ECHO = 0
ERR_LOW_INTENSITY = 1
ERR_OTHER = 6
ERR_NOT_MEASURABLE = 19

MAX_STEP = 768  # highest step number a command may name on the URG-04LX (spec p.4: steps 0..768)
VALID_BITRATES = frozenset({19200, 38400, 57600, 115200, 250000, 500000, 750000})  # spec p.16
_TAG_RE = re.compile(r"[A-Za-z0-9 ._+@]*")
_MAX_COMMAND_BYTES = 64  # a longer unterminated line is noise, not a command

VENDOR = "Hokuyo Automatic Co.,Ltd."
PRODUCT = "SOKUIKI Sensor URG-04LX-UG01(Simple-URG)"
FIRMWARE = "3.4.03(17/Dec./2012)"  # real capture A


@dataclass(frozen=True, slots=True)
class EmittedScan:
    """Ground truth about one scan the fake sent: when step 0 was measured (fake's clock, seconds), the
    raw 24-bit timestamp it carried, and whether ``corrupt_next`` broke its checksum."""

    step0_time_s: float
    device_time_ms: int
    echo: str
    corrupted: bool = False


@dataclass(slots=True)
class _Stream:
    body: str  # echo body without the scan count, e.g. "MD0044072501"... up to the interval digit
    tag: str
    first: int
    last: int
    cluster: int
    nchars: int
    skip: int  # scans between sends (the interval digit)
    remaining: int | None  # None: until QT
    next_k: int


class FakeUrg:
    """A URG-04LX-UG01 on the other end of the wire. Thread-safe: ``PtyServer`` and a test both call it."""

    def __init__(
        self,
        simulation: Simulation | None = None,
        *,
        laser: LaserModel | None = None,
        serial: str = "H0000001",
        clock_start_ms: int = 0,
        fixed_ranges_mm: Sequence[int] | None = None,
        boot_in_scip1: bool = False,
        seed: int = 0,
        max_backlog_scans: int = 10,
        history: int = 1000,
        link_bitrate: int | None = None,
    ) -> None:
        self._sim = simulation
        self.laser = laser or (simulation.world.laser if simulation is not None else LaserModel())
        lm = self.laser
        if not 0 <= lm.first_step <= lm.front_step <= lm.last_step <= MAX_STEP:
            raise ValueError(f"laser steps out of order: {lm.first_step}, {lm.front_step}, {lm.last_step}")
        self.serial = serial
        self.boot_in_scip1 = boot_in_scip1
        self.max_backlog_scans = max_backlog_scans
        if link_bitrate is not None and link_bitrate <= 0:
            raise ValueError(f"link_bitrate must be positive, got {link_bitrate}")
        # 8N1: a start bit, 8 data bits and a stop bit per byte.
        self.link_bytes_per_s = None if link_bitrate is None else link_bitrate / 10.0
        self._link_bitrate = link_bitrate
        self.period_s = 60.0 / lm.scan_rpm
        self._rng = np.random.default_rng(seed)
        self._lock = threading.RLock()
        self._fixed: npt.NDArray[np.int64] | None = None
        if fixed_ranges_mm is not None:
            fixed = np.asarray(fixed_ranges_mm, dtype=np.int64)
            n = lm.last_step - lm.first_step + 1
            if fixed.shape != (n,):
                raise ValueError(f"fixed_ranges_mm needs {n} values (steps {lm.first_step}..{lm.last_step})")
            self._fixed = self._full_scan(fixed)
        elif simulation is None:
            self._fixed = self._full_scan(self._builtin_room())
        self._epoch: float | None = None  # motor phase 0 (step 0 of scan 0)
        self._timer_epoch = 0.0  # when the 24-bit clock read _timer_start_ms
        self._timer_start_ms = clock_start_ms
        self._t_last = 0.0
        self._inbuf = bytearray()
        self._outq: collections.deque[tuple[float, bytes | Callable[[], bytes]]] = collections.deque()
        self._last_due = -math.inf
        self._wire = bytearray()  # RS-232 model: bytes on their way out, the first one leaving at _wire_t
        self._wire_t = -math.inf
        self._wire_end = -math.inf  # when the line has sent everything queued so far
        self._cache: dict[int, npt.NDArray[np.int64]] = {}
        self._corrupt = 0
        self._silent = False
        # When set the laser "fails": BM answers 01, GD/GS and MD/MS answer 50 (spec p.11-14).
        self.hardware_fault = False
        self.emitted: collections.deque[EmittedScan] = collections.deque(maxlen=history)
        self.commands: collections.deque[bytes] = collections.deque(maxlen=history)
        self.scans_skipped = 0
        self._reset_state()

    # -- state ---------------------------------------------------------------------------------------------
    def _reset_state(self) -> None:
        self._scip1 = self.boot_in_scip1
        self._laser_on = False
        self._laser_on_time = math.inf
        self._tm_mode = False
        self._stream: _Stream | None = None
        self._bitrate = self._link_bitrate or 115200
        self._inbuf.clear()
        self._clear_output()
        self._cache.clear()

    def power_cycle(self, now: float | None = None) -> None:
        """What unplugging a bus-powered URG does: everything back to boot state, clock restarted at 0."""
        with self._lock:
            t = self._time(now if now is not None else self._t_last)
            self._reset_state()
            self._timer_epoch, self._timer_start_ms = t, 0

    @property
    def silent(self) -> bool:
        return self._silent

    @silent.setter
    def silent(self, value: bool) -> None:
        """A hung sensor: input is swallowed, nothing is sent; the motor keeps turning."""
        with self._lock:
            self._silent = value
            if value:
                self._clear_output()

    def inject(self, data: bytes) -> None:
        """Send ``data`` as is, after the replies already due (junk between frames)."""
        with self._lock:
            self._enqueue(self._last_due, bytes(data))

    def corrupt_next(self, n: int = 1) -> None:
        """Break one data character (and so the block checksum) in each of the next ``n`` scans."""
        with self._lock:
            self._corrupt += n

    @property
    def laser_on(self) -> bool:
        return self._laser_on

    @property
    def streaming(self) -> bool:
        return self._stream is not None

    # -- time ----------------------------------------------------------------------------------------------
    def _time(self, now: float) -> float:
        t = self._sim.clock() if self._sim is not None else now
        if self._epoch is None:
            self._epoch = t
            self._timer_epoch = t
        self._t_last = t
        return t

    def device_ms(self, t: float) -> int:
        """The 24-bit millisecond clock at time ``t`` (fake's clock)."""
        # The epsilon keeps k * 0.1 s from flooring to one millisecond less in binary floating point.
        elapsed_ms = math.floor((t - self._timer_epoch) * 1000.0 + 1e-6)
        return (self._timer_start_ms + elapsed_ms) % scip.TIMESTAMP_MODULUS

    def _step0(self, k: int) -> float:
        assert self._epoch is not None
        return self._epoch + k * self.period_s

    def _done_after_s(self, last_step: int) -> float:
        """Time from step 0 until step ``last_step`` has been measured."""
        return (last_step + 1) / self.laser.steps_per_rev * self.period_s

    # -- ByteDevice ----------------------------------------------------------------------------------------
    def receive(self, data: bytes, now: float) -> bytes:
        with self._lock:
            t = self._time(now)
            if self._silent:
                return b""
            self._inbuf += data
            # Commands end with LF, CR or CR LF (spec p.9); the empty line between CR and LF is ignored.
            while (m := re.search(rb"[\r\n]", self._inbuf)) is not None:
                line = bytes(self._inbuf[: m.start()])
                del self._inbuf[: m.end()]
                if line:
                    self.commands.append(line)
                    self._handle(line, t)
            if len(self._inbuf) > _MAX_COMMAND_BYTES:
                self._inbuf.clear()
            self._advance(t)
            return self._drain(t)

    def poll(self, now: float) -> bytes:
        with self._lock:
            t = self._time(now)
            self._advance(t)
            return b"" if self._silent else self._drain(t)

    def next_output_in(self, now: float) -> float | None:
        """Seconds until the next reply or streamed scan is due (``ScheduledByteDevice``), None when
        nothing is queued and no scan stream runs. In the fake's clock, which is monotonic time in
        ``vlp-agent sim``."""
        with self._lock:
            t = self._time(now)
            if self._silent:
                return None
            dues = []
            if self._outq:
                dues.append(self._outq[0][0])
            if self._wire and self.link_bytes_per_s is not None:
                # Wake when a line's worth (a data block) has left, not for every byte.
                chunk = min(len(self._wire), scip.BLOCK_CHARS + 2)
                dues.append(self._wire_t + chunk / self.link_bytes_per_s)
            s = self._stream
            if s is not None:
                dues.append(self._step0(s.next_k) + self._done_after_s(s.last))
            return max(min(dues) - t, 0.0) if dues else None

    def _clear_output(self) -> None:
        self._outq.clear()
        self._last_due = -math.inf
        self._wire.clear()
        self._wire_t = self._wire_end = -math.inf

    def _enqueue(self, due: float, item: bytes | Callable[[], bytes], size: int | None = None) -> None:
        """Queue ``item`` to leave at ``due``; ``size``: its length when it is built later (a GD scan)."""
        # Replies leave in command order even when one of them waits for a scan.
        due = max(due, self._last_due)
        self._last_due = due
        self._outq.append((due, item))
        if self.link_bytes_per_s is not None:
            n = len(item) if isinstance(item, bytes) else (size or 0)
            self._wire_end = max(due, self._wire_end) + n / self.link_bytes_per_s

    def _reply(
        self,
        t: float,
        echo: bytes,
        status: str,
        *,
        timestamp_ms: int | None = None,
        params: Sequence[tuple[str, str]] = (),
    ) -> None:
        self._enqueue(t, scip.encode_reply(echo, status, timestamp_ms=timestamp_ms, params=params))

    def _drain(self, t: float) -> bytes:
        rate = self.link_bytes_per_s
        out = bytearray()
        while True:
            if rate is not None and self._wire:
                n = min(len(self._wire), math.floor((t - self._wire_t) * rate + 1e-9))
                if n > 0:
                    out += self._wire[:n]
                    del self._wire[:n]
                    self._wire_t += n / rate
                if self._wire:
                    break
            if not self._outq or self._outq[0][0] > t:
                break
            due, item = self._outq.popleft()
            data = item() if callable(item) else item
            if rate is None:
                out += data
            else:
                self._wire_t = max(self._wire_t, due)
                self._wire += data
        return bytes(out)

    # -- commands ------------------------------------------------------------------------------------------
    def _handle(self, line: bytes, t: float) -> None:
        echo = line
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            text = ""
        body, sep, tag = text.partition(";")
        if self._scip1:
            # A SCIP 1.1 sensor only understands SCIP2.0 here; urg_c reads "E" as its answer to QT.
            if body == "SCIP2.0":
                self._scip1 = False
                self._enqueue(t, scip.encode_scip1_reply(echo, "0"))
            else:
                self._enqueue(t, scip.encode_scip1_reply(echo, "E"))
            return
        if sep and len(tag) > scip.TAG_MAX_CHARS:
            return self._reply(t, echo, "0G")
        if sep and _TAG_RE.fullmatch(tag) is None:
            return self._reply(t, echo, "0H")
        if self._tm_mode and not body.startswith("TM"):
            # In time-adjust mode the sensor takes no other command; urg_c reads QT's 0E as "in TM mode".
            return self._reply(t, echo, "0E")
        code = "SCIP2.0" if body == "SCIP2.0" else body[:2]
        handler = self._HANDLERS.get(code)
        if handler is None or not body.isprintable():
            return self._reply(t, echo, "0E")
        handler(self, body, tag, echo, t)

    def _cmd_scip2(self, body: str, tag: str, echo: bytes, t: float) -> None:
        # Already in SCIP 2.0: the URG-04LX-UG01 calls it an undefined command (capture B's log).
        self._reply(t, echo, "0E")

    def _cmd_simple(self, body: str, echo: bytes, t: float, name: str) -> bool:
        if body != name:
            self._reply(t, echo, "0C" if len(body) < len(name) else "0F")
            return False
        return True

    def _cmd_qt(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "QT"):
            self._stream = None
            self._laser_on = False
            self._reply(t, echo, "00")

    def _cmd_rs(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "RS"):
            # RS: laser off, settings back to default, internal timer reset (spec p.14).
            self._stream = None
            self._laser_on = False
            self._bitrate = 115200
            self._timer_epoch, self._timer_start_ms = t, 0
            self._reply(t, echo, "00")

    def _cmd_bm(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "BM"):
            if self.hardware_fault:
                self._reply(t, echo, "01")
            elif self._laser_on:
                self._reply(t, echo, "02")
            else:
                self._laser_on, self._laser_on_time = True, t
                self._reply(t, echo, "00")

    def _cmd_vv(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "VV"):
            params = [
                ("VEND", VENDOR),
                ("PROD", PRODUCT),
                ("FIRM", FIRMWARE),
                ("PROT", "SCIP 2.0"),
                ("SERI", self.serial),
            ]
            self._reply(t, echo, "00", params=params)

    def _cmd_pp(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "PP"):
            lm = self.laser
            params = [
                ("MODL", lm.model),
                ("DMIN", str(lm.min_range_mm)),
                ("DMAX", str(lm.max_range_mm)),
                ("ARES", str(lm.steps_per_rev)),
                ("AMIN", str(lm.first_step)),
                ("AMAX", str(lm.last_step)),
                ("AFRT", str(lm.front_step)),
                ("SCAN", str(lm.scan_rpm)),
            ]
            self._reply(t, echo, "00", params=params)

    def _cmd_ii(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if self._cmd_simple(body, echo, t, "II"):
            # Field list from the spec / urgnetwork wiki; the values are illustrative.
            params = [
                ("MODL", self.laser.model),
                ("LASR", "ON" if self._laser_on else "OFF"),
                ("SCSP", f"Initial({self.laser.scan_rpm}[rpm])<-Default setting by user"),
                ("MESM", "Measuring by Normal Mode" if self._stream else "IDLE"),
                ("SBPS", f"{self._bitrate}[bps]<-Default setting by user"),
                ("TIME", f"{self.device_ms(t):06X}"),
                ("STAT", "Sensor works well."),
            ]
            self._reply(t, echo, "00", params=params)

    def _cmd_tm(self, body: str, tag: str, echo: bytes, t: float) -> None:
        if len(body) != 3 or body[2] not in "012":
            return self._reply(t, echo, "01")
        mode = body[2]
        if mode == "0":
            if self._tm_mode:
                return self._reply(t, echo, "02")
            # Adjust mode switches the laser off and takes no other command (spec p.15).
            self._tm_mode, self._laser_on, self._stream = True, False, None
            return self._reply(t, echo, "00")
        if mode == "1":
            if not self._tm_mode:
                return self._reply(t, echo, "04")
            return self._reply(t, echo, "00", timestamp_ms=self.device_ms(t))
        if not self._tm_mode:
            return self._reply(t, echo, "03")
        self._tm_mode = False
        return self._reply(t, echo, "00")

    def _cmd_ss(self, body: str, tag: str, echo: bytes, t: float) -> None:
        arg = body[2:]
        if len(arg) != 6:
            return self._reply(t, echo, "0C" if len(arg) < 6 else "0F")
        if not arg.isdigit():
            return self._reply(t, echo, "01")
        rate = int(arg)
        if rate not in VALID_BITRATES:
            return self._reply(t, echo, "02")
        if rate == self._bitrate:
            return self._reply(t, echo, "03")
        # Over USB the new rate has no effect on the link (spec p.16 note 3); remember it for II.
        self._bitrate = rate
        return self._reply(t, echo, "00")

    def _parse_steps(self, body: str, streaming: bool) -> tuple[str, tuple[int, ...]]:
        """Status and numbers of a GD/GS/MD/MS command; the status checks follow spec p.10-13."""
        args = body[2:]
        want = 13 if streaming else 10
        if len(args) != want:
            return ("0C" if len(args) < want else "0F"), ()
        fields = [(args[0:4], "01"), (args[4:8], "02"), (args[8:10], "03")]
        if streaming:
            fields += [(args[10:11], "06"), (args[11:13], "07")]
        for text, status in fields:
            if not text.isdigit():
                return status, ()
        numbers = tuple(int(text) for text, _ in fields)
        first, last = numbers[0], numbers[1]
        if last > MAX_STEP:
            return "04", ()
        if first > last:
            return "05", ()
        return "00", numbers

    def _cmd_get(self, body: str, tag: str, echo: bytes, t: float) -> None:
        status, numbers = self._parse_steps(body, streaming=False)
        if status == "00" and self.hardware_fault:
            status = "50"
        if status != "00":
            return self._reply(t, echo, status)
        if not self._laser_on:
            return self._reply(t, echo, "10")
        first, last, cluster = numbers
        nchars = 2 if body[1] == "S" else 3
        # The latest scan that is complete up to ``last`` and was measured with the laser on; if there is
        # none yet, the reply waits for the first one.
        assert self._epoch is not None
        done = self._done_after_s(last)
        k_done = math.floor((t - self._epoch - done) / self.period_s + 1e-9)
        k_on = math.ceil((self._laser_on_time - self._epoch) / self.period_s - 1e-9)
        k = max(k_done, k_on)
        size = scip.scan_reply_size(len(echo), scip.expected_value_count(first, last, cluster), nchars)
        self._enqueue(
            self._step0(k) + done, lambda: self._data_frame(k, echo, "00", first, last, cluster, nchars), size
        )

    def _cmd_stream(self, body: str, tag: str, echo: bytes, t: float) -> None:
        status, numbers = self._parse_steps(body, streaming=True)
        if status == "00" and self.hardware_fault:
            status = "50"
        if status != "00":
            return self._reply(t, echo, status)
        first, last, cluster, skip, count = numbers
        assert self._epoch is not None
        # The first scan sent is the first one measured after the command arrived (spec p.10).
        k0 = math.ceil((t - self._epoch) / self.period_s - 1e-9)
        self._stream = _Stream(
            body[:13],
            tag,
            first,
            last,
            cluster,
            2 if body[1] == "S" else 3,
            skip,
            count if count else None,
            k0,
        )
        if not self._laser_on:
            self._laser_on, self._laser_on_time = True, t
        self._reply(t, echo, "00")

    _HANDLERS: ClassVar[dict[str, Callable[[FakeUrg, str, str, bytes, float], None]]] = {
        "SCIP2.0": _cmd_scip2,
        "QT": _cmd_qt,
        "RS": _cmd_rs,
        "BM": _cmd_bm,
        "VV": _cmd_vv,
        "PP": _cmd_pp,
        "II": _cmd_ii,
        "TM": _cmd_tm,
        "SS": _cmd_ss,
        "GD": _cmd_get,
        "GS": _cmd_get,
        "MD": _cmd_stream,
        "MS": _cmd_stream,
    }

    # -- streaming -----------------------------------------------------------------------------------------
    def _advance(self, t: float) -> None:
        """Queue every MD/MS scan whose data is complete by ``t``."""
        s = self._stream
        if s is None:
            return
        done = self._done_after_s(s.last)
        stride = s.skip + 1
        behind = (t - (self._step0(s.next_k) + done)) / self.period_s
        complete = math.floor(behind / stride) + 1 if behind >= 0 else 0
        # A hung sensor sends nothing; a sensor whose host stopped reading loses what it could not buffer
        # and sends only its latest scan.
        lost = complete if self._silent else (complete - 1 if complete > self.max_backlog_scans else 0)
        if lost:
            self.scans_skipped += lost
            s.next_k += lost * stride
            if s.remaining is not None:
                s.remaining = max(0, s.remaining - lost)
                if s.remaining == 0:
                    self._stream, self._laser_on = None, False
                    return
        while self._stream is s and self._step0(s.next_k) + done <= t:
            k = s.next_k
            s.next_k += s.skip + 1
            if s.remaining is not None:
                s.remaining -= 1
            if self._step0(k) + done < self._wire_end:
                # RS-232 model: the line is still sending; this scan is overwritten by the next one.
                self.scans_skipped += 1
                if s.remaining == 0:
                    self._stream, self._laser_on = None, False
                continue
            left = s.remaining if s.remaining is not None else 0
            echo = f"{s.body}{left:02d}" + (f";{s.tag}" if s.tag else "")
            self._enqueue(
                self._step0(k) + done,
                self._data_frame(k, echo.encode("ascii"), "99", s.first, s.last, s.cluster, s.nchars),
            )
            if s.remaining == 0:
                # After the last requested scan the laser goes off by itself (spec p.10).
                self._stream = None
                self._laser_on = False

    def _data_frame(
        self, k: int, echo: bytes, status: str, first: int, last: int, cluster: int, nchars: int
    ) -> bytes:
        step0 = self._step0(k)
        ts = self.device_ms(step0)
        values = self._cluster(self._ranges(k)[first : last + 1], cluster)
        if nchars == 2:
            values = np.where(values > 4095, ERR_NO_ECHO, values)
        frame = scip.encode_reply(echo, status, timestamp_ms=ts, payload=_encode_values(values, nchars))
        corrupted = self._corrupt > 0
        if corrupted:
            self._corrupt -= 1
            frame = _break_first_block(frame)
        self.emitted.append(EmittedScan(step0, ts, echo.decode("ascii", "replace"), corrupted))
        return frame

    @staticmethod
    def _cluster(values: npt.NDArray[np.int64], cluster: int) -> npt.NDArray[np.int64]:
        cluster = max(cluster, 1)
        if cluster == 1:
            return values
        out = []
        for i in range(0, values.size, cluster):
            group = values[i : i + cluster]
            valid = group[group >= 20]
            out.append(int(valid.min()) if valid.size else int(group.min()))
        return np.asarray(out, dtype=np.int64)

    # -- ranges --------------------------------------------------------------------------------------------
    def _full_scan(self, measured: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """Values for steps 0..MAX_STEP from the measured ones (AMIN..AMAX); the dead zone is code 19."""
        full = np.full(MAX_STEP + 1, ERR_NOT_MEASURABLE, dtype=np.int64)
        full[self.laser.first_step : self.laser.last_step + 1] = measured
        return full

    def _builtin_room(self) -> npt.NDArray[np.int64]:
        """A fixed 4 m x 3 m room with a doorway, seen from off-centre: walls, corners and open space."""
        walls = (
            Wall(-1.5, -1.2, 2.5, -1.2),
            Wall(2.5, -1.2, 2.5, 1.8),
            Wall(2.5, 1.8, 0.6, 1.8),
            Wall(-0.3, 1.8, -1.5, 1.8),
            Wall(-1.5, 1.8, -1.5, -1.2),
        )
        ranges_m = cast_rays(
            (0.0, 0.0), self._angles_rad(), walls_array(walls), None, self.laser.max_range_mm / 1000.0
        )
        return self._to_codes(ranges_m * 1000.0)

    def _angles_rad(self) -> npt.NDArray[np.float64]:
        """Beam angles of steps AMIN..AMAX, counter-clockwise from the front step."""
        lm = self.laser
        steps = np.arange(lm.first_step, lm.last_step + 1, dtype=np.float64)
        return (steps - lm.front_step) * (2.0 * math.pi / lm.steps_per_rev)

    def _to_codes(self, ranges_mm: npt.NDArray[np.float64]) -> npt.NDArray[np.int64]:
        lm = self.laser
        finite = np.isfinite(ranges_mm)
        mm = np.rint(np.where(finite, ranges_mm, 0.0)).astype(np.int64)
        out = np.where((mm < lm.min_range_mm) | (mm > lm.max_range_mm), ERR_OTHER, mm)
        return np.where(finite, out, ERR_NO_ECHO)

    def _ranges(self, k: int) -> npt.NDArray[np.int64]:
        """Values for steps 0..MAX_STEP of scan ``k`` (cached: asking twice for one scan gives one answer)."""
        if self._fixed is not None:
            return self._fixed
        cached = self._cache.get(k)
        if cached is not None:
            return cached
        assert self._sim is not None
        lm = self.laser
        angles = self._angles_rad()
        # The whole scan is cast from the pose at its middle step; the robot moves < 1 cm in 70 ms.
        t_mid = self._step0(k) + (lm.first_step + lm.last_step) / 2.0 / lm.steps_per_rev * self.period_s
        true_mm = self._sim.laser_ranges_m(angles, t_mid) * 1000.0
        noisy = true_mm + self._rng.normal(0.0, lm.range_noise_mm, true_mm.shape)
        values = self._to_codes(noisy)
        if lm.dropout > 0.0:
            values = np.where(self._rng.random(values.shape) < lm.dropout, ERR_LOW_INTENSITY, values)
        full = self._full_scan(values)
        self._cache = {k: full}
        return full


def _encode_values(values: npt.NDArray[np.int64], nchars: int) -> bytes:
    """``scip.encode_values`` for a whole scan at once, vectorised (the fake serves 10 scans a second from
    a thread of the agent's own process under ``vlp-agent sim``; the per-value Python loop cost ~1 ms)."""
    v = np.asarray(values, dtype=np.int64)
    if v.size and (int(v.min()) < 0 or int(v.max()) >= 1 << (6 * nchars)):
        raise ValueError(f"a value does not fit in {nchars} SCIP characters")
    shifts = np.arange(6 * (nchars - 1), -1, -6, dtype=np.int64)
    chars = 0x30 + ((v[:, None] >> shifts[None, :]) & 0x3F)
    return chars.astype(np.uint8).tobytes()


def _break_first_block(frame: bytes) -> bytes:
    """Change the first data character of a data reply so that its block checksum no longer matches."""
    lines = frame.split(b"\n")
    block = bytearray(lines[3])
    block[0] = 0x31 if block[0] == 0x30 else 0x30
    lines[3] = bytes(block)
    return b"\n".join(lines)
