"""Read a recording back: every message of every whole record, up to where a cut file stops being whole.

A file the recorder closed ends with a summary and a footer; a file cut by a kill or a power cut ends in
the middle of a chunk (or of the record after it). The records are read in order and checked (the chunks'
CRCs); the first one that is cut or corrupt ends the reading, and :class:`Recording` says where
(``stopped_at``, a byte offset: everything before it was read) and why. A recording written by a newer
format version of the recorder raises :class:`RecordingFormatError` rather than being misread.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from firmware_protocol.errors import VlpAgentError

__all__ = ["RecordedMessage", "Recording", "RecordingFormatError", "read_recording"]

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
