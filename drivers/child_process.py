"""A worker in a child process, talked to over a socketpair: how the simulated camera's renderer and the
agent's SLAM filter run off the agent's interpreter lock.

The child is a fresh interpreter (``python -m MODULE FD``: never a ``fork`` of the threaded agent, and not
``multiprocessing``'s spawn, which re-imports the parent's main script) serving the connection on file
descriptor FD with ``multiprocessing.connection`` framing; AF_UNIX only, no network. By convention a
``None`` message asks it to stop.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing.connection
import os
import signal
import socket
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

__all__ = ["child_connection", "kill_child", "start_child", "stop_child"]

log = logging.getLogger(__name__)


def start_child(
    module: str, env: Mapping[str, str] | None = None
) -> tuple[subprocess.Popen[bytes], multiprocessing.connection.Connection]:
    """Start ``python -m module FD`` with the other end of a socketpair on FD (``env``: variables set for it
    on top of this process's); returns the process and this end of the connection."""
    ours, theirs = socket.socketpair()
    # The child finds this package where the parent found it, installed or not.
    root = str(Path(__file__).resolve().parents[1])
    child_env = {**os.environ, **(env or {})}
    child_env["PYTHONPATH"] = os.pathsep.join(p for p in (root, child_env.get("PYTHONPATH", "")) if p)
    try:
        process = subprocess.Popen(
            [sys.executable, "-m", module, str(theirs.fileno())],
            pass_fds=(theirs.fileno(),),
            stdin=subprocess.DEVNULL,
            env=child_env,
        )
    finally:
        theirs.close()
    return process, multiprocessing.connection.Connection(ours.detach())


def stop_child(
    process: subprocess.Popen[bytes], conn: multiprocessing.connection.Connection, what: str
) -> None:
    """Ask the child to stop (``None``), wait 2 s, kill it if it did not, and close the connection."""
    if process.poll() is None:
        with contextlib.suppress(OSError):
            conn.send(None)
        try:
            process.wait(2.0)
        except subprocess.TimeoutExpired:
            log.warning("the %s process did not stop; killing it", what)
            kill_child(process, wait_s=1.0)
    conn.close()


def kill_child(
    process: subprocess.Popen[bytes],
    conn: multiprocessing.connection.Connection | None = None,
    wait_s: float = 2.0,
) -> None:
    """Kill the child, wait for it (``wait_s`` at most; a child still there after that is left to the
    kernel) and close ``conn``, where given."""
    with contextlib.suppress(OSError):
        process.kill()
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(wait_s)
    if conn is not None:
        conn.close()


def child_connection(
    module: str, started_by: str, argv: Sequence[str] | None = None
) -> multiprocessing.connection.Connection | None:
    """In the child (``python -m module FD``): the connection on the descriptor its command line names, or
    None, with a usage line on stderr, when the command line is not one descriptor number.

    The child ignores SIGUSR1 and SIGUSR2 from here on: they are the agent's "save the map now" and
    "write a recorder snapshot", and ``systemctl kill`` sends a signal to every process of the unit unless
    told ``--kill-whom=main``; their default action would end the child (the SLAM process, with the map)."""
    signal.signal(signal.SIGUSR1, signal.SIG_IGN)
    signal.signal(signal.SIGUSR2, signal.SIG_IGN)
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not args[0].isdigit():
        print(f"usage: python -m {module} FD (started by {started_by})", file=sys.stderr)
        return None
    return multiprocessing.connection.Connection(int(args[0]))
