"""The flight recorder's writer: samples from the agent's loops into rotating, chunked MCAP files.

The loops call :meth:`McapRecorder.record` with a kind and the sample they hold: one bounded-deque append
(no lock, no encoding, no I/O); a full queue drops the sample and counts it. A writer thread drains the
queue every ``chunk_s / 4`` (giving way to the hot path before each sample), turns each sample into
channel messages (``agent.recording.messages``), encodes them as JSON and adds them to the open MCAP
file. A chunk on disk is whole and indexed by its own records, so a file cut by a kill or a power cut
reads up to its last whole chunk (``agent.recording.reader``). The writer closes the open chunk before the
newest message on disk is ``chunk_s`` old by the messages' own stamps (the agent's monotonic clock): it
wakes ``lead`` ahead of that instant, ``lead`` being 1.5 times the longest a recent close took from its
wake-up target to the data in the kernel (at least 10 ms, at most ``chunk_s / 2``). So a kill loses at
most the last ``chunk_s`` of messages, by construction and not by luck, as long as no close takes 1.5
times longer than the longest of the last 32 (``record_chunks_late`` counts the ones that did). A chunk
is also closed ``chunk_s`` after the last one on the writer's clock (stamps from another clock, a test's).

Files are ``<stem>-<n>.mcap`` beside the configured path (n counts up, also across restarts). A file is
closed and the next one begun at ``file_mb`` or after ``file_s``; before a file is begun the oldest files
of the same stem are deleted until the closed ones plus a full new one fit in ``total_mb``. When the
free space of the folder falls below ``min_free_mb`` the recorder closes its file and pauses (samples are
dropped and counted) until the space is back; the agent keeps running either way, and every such step is
logged once.

With ``snapshot_s`` > 0 the writer also keeps the last ``snapshot_s`` of encoded messages in memory
(``agent.recording.snapshot``, at most ``snapshot_mb``) and writes them to ``<stem>-snapshot-<n>.mcap``
when asked (:meth:`McapRecorder.request_snapshot`, SIGUSR2 under ``run`` and ``sim``) or when a device
health event goes bad; ``continuous = false`` keeps only that memory (nothing is written until asked).
Snapshots count in ``total_mb``: once one is written (under its temporary name), files are deleted until
the kept ones, the open file at its full ``file_mb`` and the snapshot fit, the oldest recording files
first and the oldest snapshots only after them; a snapshot that would not fit even then, or leaves less
than ``min_free_mb`` free, is removed instead of renamed (logged, ``snapshot_skipped_cap`` /
``snapshot_skipped_disk``), and none is begun below ``min_free_mb``.
"""

from __future__ import annotations

import collections
import contextlib
import json
import logging
import os
import shutil
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

from mcap.writer import CompressionType, Writer

from agent.config import RecorderConfig
from agent.recording.messages import CHANNELS, messages_for
from agent.recording.reader import FORMAT_VERSION, recording_files
from agent.recording.schemas import SCHEMAS
from agent.recording.snapshot import SnapshotRing, next_snapshot_path, snapshot_files, write_snapshot

__all__ = [
    "PROFILE",
    "McapRecorder",
    "close_lead_s",
    "close_target_s",
    "free_bytes",
    "next_wait_s",
    "recording_files",
]

log = logging.getLogger(__name__)

PROFILE = "vlp_agent"
# How often a paused recorder (disk nearly full) looks at the free space again.
_DISK_RECHECK_S = 5.0
_MAX_CHUNK_BYTES = 8 << 20


def _no_wait() -> None:
    pass


# The close's lead over its deadline: a multiple of the longest recent close, within bounds.
_LEAD_FACTOR = 1.5
_MIN_LEAD_S = 0.01
_LEAD_HISTORY = 32


def next_wait_s(now_s: float, due_s: float | None, period_s: float) -> float:
    """How long the writer thread sleeps: its pass period, but no later than when the open chunk is due
    (``due_s``, None: no chunk open), so it is closed then rather than up to a period later."""
    if due_s is None:
        return period_s
    return min(period_s, max(0.0, due_s - now_s))


def close_lead_s(costs: Iterable[float], chunk_s: float) -> float:
    """How far ahead of its deadline a chunk close starts, from what recent closes took (seconds from the
    instant the writer meant to start to the data in the kernel): 1.5 times the longest, at least 10 ms,
    at most half a chunk (beyond that the bound cannot be kept without writing chunks of almost nothing)."""
    longest = max(costs, default=0.0)
    return min(max(_LEAD_FACTOR * longest, _MIN_LEAD_S), 0.5 * chunk_s)


def close_target_s(
    flushed_newest_ns: int | None,
    chunk_oldest_ns: int | None,
    chunk_newest_ns: int | None,
    chunk_s: float,
    lead_s: float,
) -> float | None:
    """When (monotonic seconds) the writer starts closing the open chunk so that the newest message on
    disk is never more than ``chunk_s`` old by the messages' stamps: ``chunk_s - lead_s`` after the newest
    stamp already on disk (the open chunk's oldest, before anything is). None when the open chunk holds
    nothing newer than what is on disk (closing it would not make the disk any fresher)."""
    if chunk_newest_ns is None or chunk_oldest_ns is None:
        return None
    if flushed_newest_ns is not None and chunk_newest_ns <= flushed_newest_ns:
        return None
    base_ns = chunk_oldest_ns if flushed_newest_ns is None else flushed_newest_ns
    return base_ns * 1e-9 + chunk_s - lead_s


def free_bytes(folder: Path) -> int:
    return shutil.disk_usage(folder).free


class McapRecorder:
    """One recording (possibly many files). ``free_space``: bytes free in a folder (tests pass a fake);
    ``clock_s``: monotonic seconds (chunk and file durations)."""

    def __init__(
        self,
        config: RecorderConfig,
        *,
        free_space: Callable[[Path], int] = free_bytes,
        clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        if config.path is None:
            raise ValueError("McapRecorder needs recorder.path")
        self.config = config
        self.path = config.path
        self.free_space = free_space
        self.clock_s = clock_s
        self.channels = frozenset(config.channels)
        # Called before each sample is encoded and before a chunk is compressed: the agent passes
        # HotPath.give_way, so the writer waits (the interpreter lock released) while a camera frame is on
        # the hot path instead of taking turns with it.
        self.give_way: Callable[[], None] = _no_wait
        self._queue: collections.deque[tuple[str, int, Any]] = collections.deque()
        self._limit = config.queue_size
        self._drop_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._writer: Writer | None = None
        self._stream: IO[bytes] | None = None
        self._file: Path | None = None
        self._file_opened_s = 0.0
        self._last_chunk_s = 0.0
        # Message stamps (ns) of the open chunk and of the newest message on disk (over all files).
        self._chunk_oldest_ns: int | None = None
        self._chunk_newest_ns: int | None = None
        self.flushed_newest_ns: int | None = None
        self._close_costs: collections.deque[float] = collections.deque(maxlen=_LEAD_HISTORY)
        self.lead_s = close_lead_s((), config.chunk_s)
        self._channel_ids: dict[str, int] = {}
        self._next_index = 1 + max((n for n, _ in recording_files(self.path)), default=0)
        self._paused_until_s = 0.0
        self.paused = False
        self.closed = False
        # Counters (read by the status and the summary; written by the writer thread, drops by any).
        self.counts: collections.Counter[str] = collections.Counter()
        self.dropped = 0
        self.writer_cpu_s = 0.0  # CPU time of the writer thread: the recording's cost but for the appends
        self.files: list[Path] = []
        self.deleted: list[Path] = []
        self.ring: SnapshotRing | None = None
        if config.snapshot_s > 0:
            self.ring = SnapshotRing(config.snapshot_s, round(config.snapshot_mb * 1e6))
        # Appended to by a signal handler or a loop, popped by the writer thread: deque ops are atomic.
        self._snapshot_requests: collections.deque[str] = collections.deque()
        self._last_fault_snapshot_ns: int | None = None
        self.snapshots: list[Path] = []

    # -- the loops' side ------------------------------------------------------------------------------
    def record(self, kind: str, t_ns: int, sample: Any) -> None:
        """Queue one sample; never blocks (a full queue drops it, counted)."""
        if len(self._queue) >= self._limit or self.closed:
            with self._drop_lock:
                self.dropped += 1
            return
        self._queue.append((kind, t_ns, sample))

    def request_snapshot(self, reason: str = "requested") -> None:
        """Ask the writer thread to write the snapshot ring to a file at its next pass. Safe from a signal
        handler (one deque append, no lock); nothing when snapshots are off."""
        if self.ring is not None:
            self._snapshot_requests.append(reason)

    # -- lifecycle ------------------------------------------------------------------------------------
    def start(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._thread = threading.Thread(target=self._run, name="agent-recorder", daemon=True)
        self._thread.start()
        if self.config.continuous:
            log.info("recording to %s (%s)", self.path.parent, ", ".join(sorted(self.channels)))
        if self.ring is not None:
            log.info(
                "recorder: keeping the last %g s (at most %g MB) for snapshots in %s",
                self.config.snapshot_s,
                self.config.snapshot_mb,
                self.path.parent,
            )

    def close(self) -> None:
        """Write what is queued, close the file (its summary and footer written) and stop. Twice is fine."""
        if self.closed:
            return
        self.closed = True
        self._stop.set()
        if self._thread is not None:
            self._thread.join(10.0)
            if self._thread.is_alive():
                log.warning("recorder: the writer did not finish within 10 s")
                return
        else:
            self._drain()
            self._write_snapshots()
        self._finish_file()

    def counters(self) -> dict[str, int]:
        counts = dict(self.counts)  # one copy (the writer thread adds keys while the agent runs)
        out = {f"recorded_{topic}": n for topic, n in sorted(counts.items()) if topic.startswith("/")}
        out.update({k: v for k, v in counts.items() if not k.startswith("/")})
        out["record_dropped"] = self.dropped
        out["record_files"] = len(self.files)
        out["record_files_deleted"] = len(self.deleted)
        out["record_paused"] = int(self.paused)
        out["record_writer_cpu_ms"] = round(1e3 * self.writer_cpu_s)
        out["record_close_lead_ms"] = round(1e3 * self.lead_s)
        if self.ring is not None:
            out["snapshot_files"] = len(self.snapshots)
            out["snapshot_ring_messages"] = len(self.ring)
            out["snapshot_ring_bytes"] = self.ring.bytes
            out["snapshot_ring_dropped"] = self.ring.dropped
        return out

    # -- the writer thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        period_s = max(self.config.chunk_s / 4.0, 0.01)
        c0 = time.thread_time()
        while not self._stop.wait(next_wait_s(self.clock_s(), self.close_due_s(), period_s)):
            self.pump()
            self.writer_cpu_s = time.thread_time() - c0
        self._drain()
        self._write_snapshots()
        self.writer_cpu_s = time.thread_time() - c0

    def pump(self) -> None:
        """One pass of the writer: write what is queued, close the chunk when ``chunk_s`` is up, rotate or
        pause when due. The writer thread's body; tests call it directly (no thread, a fake clock)."""
        self._drain()
        self._write_snapshots()
        self._maybe_close_chunk()

    def _drain(self) -> None:
        queue, give_way = self._queue, self.give_way
        while queue:
            give_way()
            kind, t_ns, sample = queue.popleft()
            self._write_sample(kind, t_ns, sample)

    def _write_sample(self, kind: str, t_ns: int, sample: Any) -> None:
        try:
            messages = messages_for(kind, sample)
            encoded = [
                (topic, json.dumps(m, separators=(",", ":"), allow_nan=False).encode())
                for topic, m in messages
                if topic in self.channels
            ]
        except (ValueError, TypeError, AttributeError, KeyError, IndexError) as exc:
            if not self.counts["record_bad_samples"]:
                log.warning("recorder: a %s sample could not be encoded (%s): skipped", kind, exc)
            self.counts["record_bad_samples"] += 1
            return
        if not encoded:
            return
        if self.ring is not None:
            for topic, data in encoded:
                self.ring.append(topic, t_ns, data)
            if kind == "health" and not sample.ok:
                self._fault(t_ns, f"{sample.device}: {sample.reason}")
            if not self.config.continuous:
                for topic, _ in encoded:
                    self.counts[topic] += 1
                return
        writer = self._writer_for_now()
        if writer is None:
            self.counts["record_dropped_disk"] += len(encoded)
            return
        for topic, data in encoded:
            channel = self._channel_ids.get(topic)
            if channel is None:
                channel = self._register(writer, topic)
            writer.add_message(channel, log_time=t_ns, publish_time=t_ns, data=data, sequence=0)
            self.counts[topic] += 1
        if self._chunk_oldest_ns is None or t_ns < self._chunk_oldest_ns:
            self._chunk_oldest_ns = t_ns
        if self._chunk_newest_ns is None or t_ns > self._chunk_newest_ns:
            self._chunk_newest_ns = t_ns

    def _fault(self, t_ns: int, what: str) -> None:
        """A device went bad: snapshot what led up to it, at most once per ``snapshot_s`` (a flapping
        device would otherwise write the same minutes over and over; the skipped ones are counted)."""
        last = self._last_fault_snapshot_ns
        if last is not None and t_ns - last < self.config.snapshot_s * 1e9:
            self.counts["snapshot_faults_skipped"] += 1
            return
        self._last_fault_snapshot_ns = t_ns
        self._snapshot_requests.append(f"fault {what}")

    def _write_snapshots(self) -> None:
        """Every pending request gets a file (two requests in one pass: two files, the same messages)."""
        ring = self.ring
        while ring is not None and self._snapshot_requests:
            reason = self._snapshot_requests.popleft()
            path = next_snapshot_path(self.path)
            self.give_way()
            if self._disk_low():
                self._snapshot_refused(reason, "disk", f"less than {self.config.min_free_mb:g} MB free")
                continue

            def admit(size: int, reason: str = reason) -> bool:
                # Written under a temporary name: the disk's free space now counts it.
                if self._disk_low():
                    self._snapshot_refused(
                        reason, "disk", f"it would leave less than {self.config.min_free_mb:g} MB free"
                    )
                    return False
                # The open file may still grow to file_mb: room for it stays reserved.
                reserve = size + (self.config.file_mb * 1e6 if self._writer is not None else 0.0)
                if not self._enforce_total_cap(reserve):
                    self._snapshot_refused(
                        reason,
                        "cap",
                        f"{size} bytes do not fit in total_mb = {self.config.total_mb:g} with the open file",
                    )
                    return False
                return True

            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                n = write_snapshot(path, ring.entries(), reason, PROFILE, admit)
            except OSError as exc:
                self.counts["snapshot_errors"] += 1
                log.warning("recorder: snapshot (%s) to %s failed: %s", reason, path, exc)
                continue
            if n is None:
                continue
            self.snapshots.append(path)
            log.warning("recorder: snapshot (%s): %d messages to %s", reason, n, path)

    def _stamp_target_s(self) -> float | None:
        return close_target_s(
            self.flushed_newest_ns,
            self._chunk_oldest_ns,
            self._chunk_newest_ns,
            self.config.chunk_s,
            self.lead_s,
        )

    def close_due_s(self) -> float | None:
        """When the open chunk is to be closed (monotonic seconds; None: no file open): by the stamps, or
        ``chunk_s`` after the last close on the writer's clock, whichever comes first."""
        if self._writer is None:
            return None
        by_clock = self._last_chunk_s + self.config.chunk_s
        by_stamps = self._stamp_target_s()
        return by_clock if by_stamps is None else min(by_clock, by_stamps)

    def _chunk_flushed(self) -> None:
        """The open chunk is on disk: its newest stamp is the disk's newest."""
        newest = self._chunk_newest_ns
        if newest is not None and (self.flushed_newest_ns is None or newest > self.flushed_newest_ns):
            self.flushed_newest_ns = newest
        self._chunk_oldest_ns = self._chunk_newest_ns = None

    def _snapshot_refused(self, reason: str, why: str, detail: str) -> None:
        self.counts[f"snapshot_skipped_{why}"] += 1
        log.warning("recorder: snapshot (%s) not written: %s (%s)", reason, detail, self.path.parent)

    def _maybe_close_chunk(self) -> None:
        if self._writer is None:
            return
        now = self.clock_s()
        target = self._stamp_target_s()
        by_stamps = target is not None and now >= target
        if not by_stamps and now - self._last_chunk_s < self.config.chunk_s:
            return
        self._last_chunk_s = now
        self.give_way()
        try:
            self._writer.flush()  # type: ignore[no-untyped-call]  # closes the chunk: whole on disk from here on
        except OSError as exc:
            self._fail(exc)
            return
        if by_stamps and target is not None:
            # From the instant the close was meant to start to the data in the kernel: the wake-up's lateness,
            # the drain before it, giving way, compressing and writing. The next lead covers the longest.
            cost = self.clock_s() - target
            self._close_costs.append(cost)
            if cost > self.lead_s:
                self.counts["record_chunks_late"] += 1
            self.lead_s = close_lead_s(self._close_costs, self.config.chunk_s)
        self.counts["record_chunks"] += 1
        self._chunk_flushed()
        assert self._stream is not None
        if (
            self._stream.tell() >= self.config.file_mb * 1e6
            or now - self._file_opened_s >= self.config.file_s
        ):
            self._finish_file()
        elif self._disk_low():
            self._pause()

    # -- files ----------------------------------------------------------------------------------------
    def _writer_for_now(self) -> Writer | None:
        if self._writer is not None:
            return self._writer
        now = self.clock_s()
        if self.paused and now < self._paused_until_s:
            return None
        if self._disk_low():
            self._pause()
            return None
        if self.paused:
            self.paused = False
            log.warning("recorder: free space is back above %g MB: recording again", self.config.min_free_mb)
        self._enforce_total_cap(self.config.file_mb * 1e6)
        return self._open_next(now)

    def _open_next(self, now_s: float) -> Writer | None:
        path = self.path.parent / f"{self.path.stem}-{self._next_index:04d}.mcap"
        self._next_index += 1
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            stream = open(path, "wb")  # noqa: SIM115  closed by _finish_file
        except OSError as exc:
            self._fail(exc)
            return None
        # Chunks are closed by time (every chunk_s); the size bound only caps memory on a burst.
        writer = Writer(stream, chunk_size=_MAX_CHUNK_BYTES, compression=CompressionType.ZSTD)
        writer.start(profile=PROFILE, library=f"vlp-agent recorder {FORMAT_VERSION}")
        writer.add_metadata(
            "vlp_agent",
            {
                "format_version": str(FORMAT_VERSION),
                "clock": "monotonic",
                # Add to a log time to get Unix time (the agent's clock is CLOCK_MONOTONIC).
                "unix_minus_monotonic_ns": str(time.time_ns() - time.monotonic_ns()),
                "file_index": str(self._next_index - 1),
            },
        )
        self._writer, self._stream, self._file = writer, stream, path
        self._channel_ids = {}
        self._file_opened_s = self._last_chunk_s = now_s
        self.files.append(path)
        log.info("recording to %s", path)
        return writer

    def _register(self, writer: Writer, topic: str) -> int:
        name = CHANNELS[topic]
        schema_id = writer.register_schema(
            name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode()
        )
        channel = writer.register_channel(topic=topic, message_encoding="json", schema_id=schema_id)
        self._channel_ids[topic] = channel
        return channel

    def _finish_file(self) -> None:
        writer, stream, path = self._writer, self._stream, self._file
        self._writer = self._stream = self._file = None
        if writer is None or stream is None:
            return
        try:
            writer.finish()  # type: ignore[no-untyped-call]
            stream.flush()
            os.fsync(stream.fileno())
        except OSError as exc:
            log.warning("recorder: closing %s: %s", path, exc)
        else:
            self._chunk_flushed()
        finally:
            stream.close()
            self._chunk_oldest_ns = self._chunk_newest_ns = None

    def _enforce_total_cap(self, reserve_bytes: float) -> bool:
        """Delete files until the ones kept plus ``reserve_bytes`` (a new file's ``file_mb``, a snapshot
        about to be written) fit in ``total_mb``: the oldest recording files first, then the oldest
        snapshots; never the open file. False when even that does not make room."""
        files = [p for _, p in recording_files(self.path) if p != self._file]
        candidates = files + snapshot_files(self.path)
        sizes = {}
        for p in candidates:
            with contextlib.suppress(OSError):
                sizes[p] = p.stat().st_size
        total = sum(sizes.values())
        budget = self.config.total_mb * 1e6 - reserve_bytes
        for oldest in candidates:
            if total <= budget:
                break
            if oldest not in sizes:
                continue
            try:
                oldest.unlink()
            except OSError as exc:
                log.warning("recorder: cannot delete %s: %s", oldest, exc)
                continue
            total -= sizes[oldest]
            self.deleted.append(oldest)
            log.warning(
                "recorder: deleted %s (%d bytes) to keep the recording under %g MB",
                oldest,
                sizes[oldest],
                self.config.total_mb,
            )
        return total <= budget

    def _disk_low(self) -> bool:
        """Whether the folder has less than ``min_free_mb`` free."""
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            free = self.free_space(self.path.parent)
        except OSError as exc:
            log.warning("recorder: cannot read the free space of %s: %s", self.path.parent, exc)
            return False
        return free < self.config.min_free_mb * 1e6

    def _pause(self) -> None:
        self._finish_file()
        self.flushed_newest_ns = None  # nothing recorded while paused: the bound starts again after it
        self._paused_until_s = self.clock_s() + _DISK_RECHECK_S
        if not self.paused:
            self.paused = True
            self.counts["record_disk_pauses"] += 1
            log.warning(
                "recorder: less than %g MB free in %s: recording paused (the agent keeps running)",
                self.config.min_free_mb,
                self.path.parent,
            )

    def _fail(self, exc: OSError) -> None:
        log.warning("recorder: %s: recording paused", exc)
        self._writer = None
        self._chunk_oldest_ns = self._chunk_newest_ns = self.flushed_newest_ns = None
        stream, self._stream, self._file = self._stream, None, None
        if stream is not None:
            with contextlib.suppress(OSError):
                stream.close()
        self._paused_until_s = self.clock_s() + _DISK_RECHECK_S
        self.paused = True
        self.counts["record_write_errors"] += 1
