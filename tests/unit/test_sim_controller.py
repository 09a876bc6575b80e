"""The simulated controller process: it makes the pose stream's pty, decodes what is written to it, and
keeps its counts after it stops."""

from __future__ import annotations

import os
import time

from drivers.sim.controller import ControllerCounts, SimulatedController
from firmware_protocol.pose_frame import PoseFlags, PoseFrame, encode_pose


def _frame(k: int) -> bytes:
    return encode_pose(PoseFrame(k, 1_000_000 + k, 1.0, 2.0, 0.5, 0.01, 0.02, PoseFlags.VLP, 0))


def test_it_decodes_the_stream_written_to_its_pty() -> None:
    controller = SimulatedController()
    try:
        assert controller.url.startswith("/dev/pts/")
        fd = os.open(controller.url, os.O_WRONLY | os.O_NOCTTY)
        try:
            stream = _frame(1) + _frame(2)
            bad = bytearray(_frame(3))
            bad[5] ^= 0x40  # a flipped bit: the CRC rejects it
            os.write(fd, stream + bytes(bad) + _frame(4))
            deadline = time.monotonic() + 5.0
            while controller.frames < 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            assert controller.counts() == ControllerCounts(3, 1, len(stream) + len(bad) + len(_frame(4)))
            os.write(fd, _frame(5))  # still in the pty when it stops: taken in
        finally:
            os.close(fd)
    finally:
        controller.stop()
    assert controller.frames == 4 and controller.bad == 1
    controller.stop()  # twice is fine; the counts stay
    assert controller.counts().frames == 4
