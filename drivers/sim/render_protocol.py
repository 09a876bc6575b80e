"""The protocol both simulated cameras' render processes speak (:mod:`drivers.sim.render_worker` for the
ceiling camera, :mod:`drivers.sim.forward_render_worker` for the forward one).

A real camera exposes and transfers its frames in hardware; the simulated ones draw theirs in Python and
numpy, so under ``vlp-agent sim`` they draw in a child process of their own (a fresh interpreter started by
:func:`~drivers.child_process.start_child`, never a fork of the threaded agent) and the parent waits on the
socketpair, the interpreter lock released, as it would in a camera driver.

The exchange, in ``multiprocessing.connection`` framing:

* parent -> child, once: the renderer's set-up (whatever the worker's ``build`` takes);
* parent -> child, per frame: ``(number, request)``, the number counting up from 1;
* child -> parent, per frame: ``(number, truth)`` then the frame's pixels as one bytes message, received
  straight into the caller's buffer;
* parent -> child: ``None`` asks the child to stop (as does the parent hanging up).

Each answer names its request: a frame whose wait ran out (:meth:`RenderClient.request` raised
:class:`~drivers.errors.DeviceDisconnected`, a loaded machine, a child slow to start) and that comes later
is dropped, not handed out as the next frame's (it was, for the ceiling camera: the image of an earlier
pose under a later frame's time, until the camera reopened). A child that dies is a
:class:`~drivers.errors.DeviceDisconnected` too (the camera then reopens, starting a new child).
"""

from __future__ import annotations

import logging
import multiprocessing.connection
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import numpy as np
import numpy.typing as npt

from drivers.child_process import start_child, stop_child
from drivers.errors import DeviceDisconnected

__all__ = ["Draw", "RenderClient", "serve"]

log = logging.getLogger(__name__)

# How long a frame may take to draw before the child counts as hung (a frame takes milliseconds; the
# first one also waits for the child's start). Read at each request, so a test can shorten it.
_REPLY_TIMEOUT_S = 5.0

TruthT = TypeVar("TruthT")

# The child's drawing function: a request's payload -> (the frame's ground truth, its pixels).
Draw = Callable[[Any], tuple[Any, memoryview]]


def serve(conn: multiprocessing.connection.Connection, build: Callable[[Any], Draw]) -> None:
    """The child's side: ``build`` the drawing function from the first message, then answer every numbered
    request until the parent sends ``None`` or hangs up."""
    draw = build(conn.recv())
    while True:
        try:
            message = conn.recv()
        except (EOFError, OSError):
            return
        if message is None:
            return
        number, request = message
        truth, pixels = draw(request)
        conn.send((number, truth))
        conn.send_bytes(pixels)


class RenderClient(Generic[TruthT]):
    """The parent's side: starts ``python -m module FD``, sends it ``setup``, then asks for frames.

    Args:
        module: the worker module (its ``main`` calls :func:`serve`).
        setup: the first message, from which the child builds its renderer.
        device: the device name that errors carry (``sim-camera``, ``sim-forward-camera``).
        what: the process's name in log lines (``render``, ``forward render``).
    """

    def __init__(self, module: str, setup: Any, *, device: str, what: str) -> None:
        self._device = device
        self._what = what
        self._requests = 0  # frames asked for; each answer names its request
        self._process, self._conn = start_child(module)
        self._conn.send(setup)

    def request(self, request: Any, out: npt.NDArray[np.uint8]) -> TruthT:
        """Ask the child for one frame: its pixels land in ``out`` (C-contiguous, the frame's size), its
        ground truth is returned. Raises DeviceDisconnected when the child is gone or gives no frame in
        time; an answer that comes after its wait ran out is dropped when the next request reads it."""
        if not out.flags.c_contiguous:
            raise ValueError("out must be C-contiguous")
        self._requests += 1
        number = self._requests
        timeout_s = _REPLY_TIMEOUT_S
        try:
            self._conn.send((number, request))
            deadline = time.monotonic() + timeout_s
            while True:
                if not self._conn.poll(max(0.0, deadline - time.monotonic())):
                    raise DeviceDisconnected(
                        f"the {self._what} process gave no frame in {timeout_s:g} s", self._device
                    )
                answered, truth = self._conn.recv()
                self._conn.recv_bytes_into(out.data.cast("B"))
                # A frame asked for earlier whose wait ran out arrives late: dropped, never taken for this.
                if answered == number:
                    return truth  # type: ignore[no-any-return]
                log.warning(
                    "dropped a late frame from the %s process (%d, waiting for %d)",
                    self._what,
                    answered,
                    number,
                )
        except (EOFError, OSError) as exc:
            raise DeviceDisconnected(f"the {self._what} process is gone: {exc}", self._device) from exc

    def close(self) -> None:
        """Stop the child (idempotent)."""
        stop_child(self._process, self._conn, self._what)
