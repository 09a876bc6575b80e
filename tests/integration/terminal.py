"""Ctrl-C for programs run under pexpect.

The terminal turns Ctrl-C into SIGINT for its foreground process group; :func:`press_ctrl_c` sends that
signal to the group directly rather than writing the interrupt character to the pty and relying on the line
discipline to turn it into one (on a loaded machine, twice in one run, that character never became a
signal). What the program does with the SIGINT is what these tests check. :func:`signal_state` is put in
the failure message: the child's blocked, ignored and caught signal masks.
"""

from __future__ import annotations

import os
import signal
from typing import Any


def press_ctrl_c(child: Any) -> None:
    os.killpg(os.getpgid(child.pid), signal.SIGINT)


def signal_state(child: Any) -> str:
    try:
        with open(f"/proc/{child.pid}/status", encoding="ascii") as f:
            return " ".join(
                line.strip() for line in f if line.startswith(("SigPnd", "SigBlk", "SigIgn", "SigCgt"))
            )
    except OSError as exc:
        return f"(no signal state: {exc})"
