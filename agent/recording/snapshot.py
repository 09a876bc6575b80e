"""The flight recorder's snapshot: the last ``snapshot_s`` of encoded messages kept in memory, written to
an MCAP file of its own on request (SIGUSR2) or when a device goes bad.

:class:`SnapshotRing` is the memory: encoded messages in log-time order, bounded by a time span and a
byte count (the oldest go first, counted). :func:`write_snapshot` writes a ring's messages to a whole,
indexed MCAP file under a temporary name and renames it, so a snapshot file is either absent or complete.
Both run on the recorder's writer thread only (no lock).
"""

from __future__ import annotations

import collections
import json
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import CompressionType, Writer

from agent.recording.messages import CHANNELS
from agent.recording.reader import FORMAT_VERSION
from agent.recording.schemas import SCHEMAS

__all__ = ["SnapshotEntry", "SnapshotRing", "snapshot_files", "write_snapshot"]

# Written once, first, and needed to make sense of the rest (the replays start from them): the newest of
# each is kept whatever its age, outside the bounds.
PINNED_TOPICS = frozenset({"/fusion/setup", "/slam/setup"})

# What one kept message costs beyond its bytes (the tuple, the bytes object's header, the deque slot):
# the byte cap bounds the memory, not only the payloads.
_ENTRY_OVERHEAD_BYTES = 120


@dataclass(frozen=True)
class SnapshotEntry:
    topic: str
    t_ns: int
    data: bytes


class SnapshotRing:
    """The newest messages spanning at most ``span_s`` of log time and ``max_bytes`` of memory, plus the
    newest message of each of ``pinned`` topics whatever its age."""

    def __init__(self, span_s: float, max_bytes: int, pinned: frozenset[str] = PINNED_TOPICS) -> None:
        if span_s <= 0 or max_bytes <= 0:
            raise ValueError("a snapshot ring needs span_s > 0 and max_bytes > 0")
        self.span_ns = round(span_s * 1e9)
        self.max_bytes = max_bytes
        self._entries: collections.deque[SnapshotEntry] = collections.deque()
        self.pinned = pinned
        self._pinned: dict[str, SnapshotEntry] = {}
        self.newest_ns: int | None = None
        self.bytes = 0
        self.dropped = 0  # messages let go to keep within the bounds (the expected steady state)

    def __len__(self) -> int:
        return len(self._entries)

    def append(self, topic: str, t_ns: int, data: bytes) -> None:
        entry = SnapshotEntry(topic, t_ns, data)
        if topic in self.pinned:
            self._pinned[topic] = entry
            return
        self._entries.append(entry)
        self.bytes += len(data) + _ENTRY_OVERHEAD_BYTES
        # Time is the newest message's, not the wall clock's: a quiet recorder keeps its last span.
        self.newest_ns = t_ns if self.newest_ns is None else max(self.newest_ns, t_ns)
        oldest_kept_ns = self.newest_ns - self.span_ns
        while self._entries and (self.bytes > self.max_bytes or self._entries[0].t_ns < oldest_kept_ns):
            gone = self._entries.popleft()
            self.bytes -= len(gone.data) + _ENTRY_OVERHEAD_BYTES
            self.dropped += 1

    def entries(self) -> list[SnapshotEntry]:
        """A copy of what is kept: the pinned messages, then the rest in arrival order. The loops hand
        samples over in arrival order, not quite in log-time order (a scan is stamped before it is read):
        one that came late with an older time is left out here rather than stretch the span."""
        pinned = sorted(self._pinned.values(), key=lambda e: e.t_ns)
        if self.newest_ns is None:
            return pinned
        oldest_kept_ns = self.newest_ns - self.span_ns
        return pinned + [e for e in self._entries if e.t_ns >= oldest_kept_ns]


def snapshot_files(path: Path) -> list[Path]:
    """The snapshots written for the recording named by ``path`` (``<stem>-snapshot-<n>.mcap``), in order."""
    if not path.parent.is_dir():
        return []
    return sorted(path.parent.glob(f"{path.stem}-snapshot-[0-9]*.mcap"))


def next_snapshot_path(path: Path) -> Path:
    """``<stem>-snapshot-<n>.mcap`` beside ``path``, n one past the highest there (never overwrites)."""
    numbers = []
    for p in snapshot_files(path):
        tail = p.stem.rsplit("-", 1)[-1]
        if tail.isdigit():
            numbers.append(int(tail))
    return path.parent / f"{path.stem}-snapshot-{1 + max(numbers, default=0):04d}.mcap"


def write_snapshot(
    path: Path,
    entries: Iterable[SnapshotEntry],
    reason: str,
    profile: str,
    admit: Callable[[int], bool] | None = None,
) -> int | None:
    """Write ``entries`` as one MCAP file at ``path`` (a temporary name, fsync, then the rename: a reader
    never sees half a snapshot). ``admit``: asked with the file's size before the rename (the recorder's
    total cap and disk guard); False removes it, and None is returned. Returns the number of messages
    written. Raises OSError."""
    tmp = path.with_name(f".{path.name}.tmp")
    count = 0
    try:
        with open(tmp, "wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            writer.start(profile=profile, library=f"vlp-agent recorder {FORMAT_VERSION}")
            writer.add_metadata(
                "vlp_agent",
                {
                    "format_version": str(FORMAT_VERSION),
                    "clock": "monotonic",
                    "unix_minus_monotonic_ns": str(time.time_ns() - time.monotonic_ns()),
                    "snapshot_reason": reason,
                },
            )
            channels: dict[str, int] = {}
            for e in entries:
                channel = channels.get(e.topic)
                if channel is None:
                    name = CHANNELS[e.topic]
                    schema = writer.register_schema(
                        name=name, encoding="jsonschema", data=json.dumps(SCHEMAS[name]).encode()
                    )
                    channel = writer.register_channel(
                        topic=e.topic, message_encoding="json", schema_id=schema
                    )
                    channels[e.topic] = channel
                writer.add_message(channel, log_time=e.t_ns, publish_time=e.t_ns, data=e.data, sequence=0)
                count += 1
            writer.finish()  # type: ignore[no-untyped-call]
            stream.flush()
            os.fsync(stream.fileno())
        if admit is not None and not admit(tmp.stat().st_size):
            tmp.unlink(missing_ok=True)
            return None
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return count
