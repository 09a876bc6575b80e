"""The RFID loop: read tags and keep the last ones for the status (person following and landmarks come
later). The reader's driver reconnects by itself."""

from __future__ import annotations

from agent.runtime.health import Heartbeat
from agent.runtime.loop_state import LoopState
from drivers.errors import DeviceError
from drivers.rfid.base import RfidReader

__all__ = ["rfid_loop"]


def rfid_loop(state: LoopState, beat: Heartbeat, *, rfid: RfidReader) -> None:
    watch = state.watch["rfid"]
    while not state.stop.is_set():
        beat.beat()
        if not state.open("rfid", rfid):
            state.retry_wait(beat, 1.0)
            continue
        try:
            tag = rfid.read(timeout_s=0.25)
        except DeviceError as exc:
            watch.bad(f"failed: {exc}")
            state.retry_wait(beat, 0.5)
            continue
        if rfid.health().connected:
            watch.good()
        if tag is not None:
            state.tags.append(tag)
            state.count("tag_reads")
            state.record("tag", tag.host_time_ns, tag)
