"""A ``vlp-agent sim`` on a pty, as the whole-agent tests start it (the ``sim_on_pty`` fixture in
``conftest.py``)."""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass

from firmware_protocol.pose_frame import PoseFrameDecoder
from tests.integration.test_agent_accuracy import PtyReader


@dataclass
class SimOnPty:
    """A ``vlp-agent sim`` in a session of its own, its pose stream on a pty the test reads."""

    proc: subprocess.Popen[str]
    reader: PtyReader

    def frames(self) -> int:
        """Pose frames the stream has carried so far."""
        return len(PoseFrameDecoder().feed(self.reader.snapshot()))

    def signal_group(self, signum: int) -> None:
        """``signum`` to the sim and its children, as ``systemctl kill`` sends it."""
        os.killpg(self.proc.pid, signum)
