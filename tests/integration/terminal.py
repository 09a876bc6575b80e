"""Ctrl-C for programs run under pexpect.

The terminal turns Ctrl-C into SIGINT for its foreground process group; :func:`press_ctrl_c` sends that
signal to the group directly rather than writing the interrupt character to the pty and relying on the line
discipline to turn it into one (on a loaded machine, twice in one run, that character never became a
signal). What the program does with the SIGINT is what these tests check. :func:`signal_state` is put in
the failure message: the child's blocked, ignored and caught signal masks.

At a prompt, :func:`press_ctrl_c_at_prompt` first waits until the program sits in its read of the terminal.
Python takes a SIGINT in its C handler and raises KeyboardInterrupt when the read it interrupts returns
EINTR; a SIGINT that lands after the prompt was written but before that read began (a loaded machine
can stop the program there) interrupts nothing, and the read then waits for input that never comes (a
wizard test once hung so, its only thread in ``wait_woken`` with nothing pending). A person pressing Ctrl-C
at a prompt is never that quick; a test reacting to the prompt's bytes can be.
"""

from __future__ import annotations

import os
import signal
import time
from typing import Any


def terminal_signals() -> None:
    """pexpect's ``preexec_fn``: SIGINT and SIGQUIT as a shell at a terminal hands them to a program it
    starts. A test runner started in the background without job control (``cmd &`` in a script) inherits
    them ignored, and Python keeps an ignored SIGINT ignored: Ctrl-C would then test nothing."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGQUIT, signal.SIG_DFL)


def press_ctrl_c(child: Any) -> None:
    os.killpg(os.getpgid(child.pid), signal.SIGINT)


def press_ctrl_c_at_prompt(child: Any, wait_s: float = 20.0) -> None:
    """Ctrl-C once the child's main thread waits in a read of its terminal (or after ``wait_s``)."""
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline and _main_thread_wait(child) not in _TTY_READ_WAITS:
        time.sleep(0.01)
    press_ctrl_c(child)


# Where the kernel has a task that waits in a read of a tty (n_tty_read sleeps in wait_woken).
_TTY_READ_WAITS = frozenset({"wait_woken", "n_tty_read"})


def _main_thread_wait(child: Any) -> str:
    try:
        with open(f"/proc/{child.pid}/wchan", encoding="ascii") as f:
            return f.read().strip()
    except OSError:
        return ""


def signal_state(child: Any) -> str:
    """The child's signal masks, and per thread its pending/blocked signals and where the kernel has it
    waiting (``wchan``): for the message of a test whose Ctrl-C went unanswered."""
    try:
        with open(f"/proc/{child.pid}/status", encoding="ascii") as f:
            text = " ".join(
                line.strip() for line in f if line.startswith(("SigPnd", "SigBlk", "SigIgn", "SigCgt"))
            )
        for task in sorted(os.listdir(f"/proc/{child.pid}/task")):
            with open(f"/proc/{child.pid}/task/{task}/status", encoding="ascii") as f:
                masks = [line.split()[1] for line in f if line.startswith(("SigPnd", "SigBlk"))]
            with open(f"/proc/{child.pid}/task/{task}/wchan", encoding="ascii") as f:
                wchan = f.read().strip()
            text += f"; thread {task} pending/blocked {'/'.join(masks)} waiting in {wchan or '-'}"
        return text
    except OSError as exc:
        return f"(no signal state: {exc})"
