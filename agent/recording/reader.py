"""Read a recording back: every message of every whole record, up to where a cut file stops being whole.

A file the recorder closed ends with a summary and a footer; a file cut by a kill or a power cut ends in
the middle of a chunk (or of the record after it). The records are read in order and checked (the chunks'
CRCs); the first one that is cut or corrupt ends the reading, and :class:`Recording` says where
(``stopped_at``, a byte offset: everything before it was read) and why. A recording written by a newer
format version of the recorder raises :class:`RecordingFormatError` rather than being misread.
"""

from __future__ import annotations

import json
import logging
import re
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from firmware_protocol.errors import VlpAgentError

__all__ = [
    "RecordedMessage",
    "Recording",
    "RecordingFormatError",
    "fusion_records",
    "is_mcap",
    "read_recording",
    "read_recordings",
    "recording_files",
    "recording_paths",
]

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"

FORMAT_VERSION = 1


class RecordingFormatError(VlpAgentError):
    """A file that is not a recording this agent can read (another profile, a newer format version)."""


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    topic: str
    schema_name: str
    log_time_ns: int
    data: dict[str, Any]


@dataclass
class Recording:
    """What was read from one file. ``complete``: the file ended with its footer (closed cleanly)."""

    path: Path
    messages: list[RecordedMessage] = field(default_factory=list)
    schemas: dict[str, dict[str, Any]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False
    stopped_at: int | None = None  # bytes read whole, when the file is cut or corrupt
    error: str = ""

    def by_topic(self) -> dict[str, list[RecordedMessage]]:
        out: dict[str, list[RecordedMessage]] = {}
        for m in self.messages:
            out.setdefault(m.topic, []).append(m)
        return out


def read_recording(path: Path) -> Recording:
    result = Recording(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open(path, "rb") as fp:
        reader = StreamReader(fp, emit_chunks=True, validate_crcs=True)
        good = 0
        try:
            for record in reader.records:
                records = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
                for r in records:
                    if isinstance(r, Schema):
                        schemas[r.id] = r
                        result.schemas[r.name] = json.loads(r.data)
                    elif isinstance(r, Channel):
                        channels[r.id] = r
                    elif isinstance(r, Message):
                        channel = channels[r.channel_id]
                        name = schemas[channel.schema_id].name if channel.schema_id in schemas else ""
                        result.messages.append(
                            RecordedMessage(channel.topic, name, r.log_time, json.loads(r.data))
                        )
                    elif isinstance(r, Metadata):
                        result.metadata[r.name] = dict(r.metadata)
                        _check_version(path, r)
                    elif isinstance(r, Footer):
                        result.complete = True
                good = fp.tell()
        except RecordingFormatError:
            raise
        except (McapError, ValueError, KeyError, EOFError, struct.error, OSError) as exc:
            result.stopped_at, result.error = good, f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # a decompressor's own error on a cut chunk
            if type(exc).__module__.split(".")[0] not in ("zstandard", "lz4"):
                raise
            result.stopped_at, result.error = good, f"{type(exc).__name__}: {exc}"
    return result


def recording_files(path: Path) -> list[tuple[int, Path]]:
    """The files of the recording named by ``path`` (``<stem>-<n>.mcap`` beside it), oldest first."""
    pattern = re.compile(re.escape(path.stem) + r"-(\d+)\.mcap$")
    found = []
    if path.parent.is_dir():
        for entry in path.parent.iterdir():
            m = pattern.match(entry.name)
            if m is not None:
                found.append((int(m.group(1)), entry))
    return sorted(found)


def recording_paths(path: Path) -> list[Path]:
    """The files to read for ``path``: the file itself when it exists, else the recorder's files it names
    (``run.mcap`` -> ``run-0001.mcap``, ``run-0002.mcap``, ...), oldest first."""
    if path.exists():
        return [path]
    files = [p for _, p in recording_files(path)]
    if not files:
        raise FileNotFoundError(f"{path}: no such recording (nor {path.stem}-NNNN.mcap beside it)")
    return files


def is_mcap(path: Path) -> bool:
    """Whether ``path`` is (or names) an MCAP recording, by its magic bytes."""
    paths = [path] if path.exists() else [p for _, p in recording_files(path)]
    if not paths:
        return False
    with open(paths[0], "rb") as fp:
        return fp.read(len(MAGIC)) == MAGIC


def read_recordings(path: Path) -> list[Recording]:
    """Every file of the recording ``path`` names (``recording_paths``), read in order, up to the first
    one that is cut or corrupt (a replay cannot go on past a gap; the files after it are left out, logged)."""
    out = []
    paths = recording_paths(path)
    for i, path_i in enumerate(paths):
        recording = read_recording(path_i)
        out.append(recording)
        if recording.stopped_at is not None:
            log.warning(
                "%s: read up to byte %d of %d (%s); the replay stops there%s",
                path_i,
                recording.stopped_at,
                path_i.stat().st_size,
                recording.error,
                f" ({len(paths) - i - 1} later files left out)" if i + 1 < len(paths) else "",
            )
            break
    return out


def fusion_records(path: Path | list[Recording]) -> Iterator[dict[str, Any]]:
    """The fusion's part of a flight recording (a path, or the files :func:`read_recordings` read), in the
    records of ``agent.runtime.recorder``'s JSON lines: the header (the filter's setup), every input in the
    order the filter took them, and every pose written (``out``), over the files in order."""
    recordings = read_recordings(path) if isinstance(path, Path) else path
    for recording in recordings:
        for m in recording.messages:
            if m.topic == "/fusion/setup":
                yield {"k": "header", "format": FORMAT_VERSION, "fusion": m.data["parameters"]}
            elif m.topic == "/fusion/input":
                yield m.data
            elif m.topic == "/pose/fused":
                d = m.data
                yield {
                    "k": "out",
                    "v": d["version"],
                    "t": d["t_ns"],
                    "x": d["x_m"],
                    "y": d["y_m"],
                    "yaw": d["yaw_rad"],
                    "flags": d["flags"],
                }


def _check_version(path: Path, record: Metadata) -> None:
    if record.name != "vlp_agent":
        return
    try:
        version = int(record.metadata.get("format_version", "0"))
    except ValueError as exc:
        raise RecordingFormatError(f"{path}: format_version is not a number") from exc
    if version > FORMAT_VERSION:
        raise RecordingFormatError(
            f"{path}: recorded in format version {version}; this agent reads up to {FORMAT_VERSION} "
            "(update vlp-agent to read it)"
        )
