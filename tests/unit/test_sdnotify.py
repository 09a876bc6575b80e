"""agent.sdnotify against a real AF_UNIX datagram receiver (path and abstract), byte for byte.

The receiver plays systemd's side: it binds a socket, the notifier sends to it, the test reads what arrived.
One test checks our bytes against the real ``systemd-notify`` binary's when it is installed.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest

from agent.sdnotify import Notifier, socket_address, watchdog_interval_s, watchdog_usec

WATCHDOG_10_S = "10000000"


class Receiver:
    """systemd's end of the notification socket: a bound SOCK_DGRAM socket we read datagrams from."""

    def __init__(self, address: str, bind_to: str | bytes) -> None:
        self.address = address  # the $NOTIFY_SOCKET value
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(bind_to)
        self.sock.settimeout(5.0)  # a hang guard for a datagram that should arrive; it arrives at once

    def recv(self) -> bytes:
        data, fds, _flags, _addr = socket.recv_fds(self.sock, 4096, 4)
        for fd in fds:  # systemd-notify's BARRIER=1 passes an fd and waits for us to close it
            os.close(fd)
        return data

    def pending(self) -> list[bytes]:
        """Every datagram already queued, without waiting (the notifier's sends complete before returning)."""
        out = []
        self.sock.setblocking(False)
        try:
            while True:
                try:
                    out.append(self.sock.recv(4096))
                except BlockingIOError:
                    return out
        finally:
            self.sock.settimeout(5.0)

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def path_receiver(tmp_path: Path) -> Iterator[Receiver]:
    path = str(tmp_path / "notify.sock")
    receiver = Receiver(path, path)
    yield receiver
    receiver.close()


@pytest.fixture(params=["path", "abstract"])
def receiver(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Receiver]:
    if request.param == "path":
        path = str(tmp_path / "notify.sock")
        r = Receiver(path, path)
    else:
        name = f"vlp-agent-test-{uuid.uuid4().hex}"
        r = Receiver("@" + name, b"\0" + name.encode())
    yield r
    r.close()


def watched(receiver: Receiver, watchdog_pid: int | None = None) -> Notifier:
    """A notifier as systemd would start us with WatchdogSec=10s."""
    env = {"NOTIFY_SOCKET": receiver.address, "WATCHDOG_USEC": WATCHDOG_10_S}
    env["WATCHDOG_PID"] = str(os.getpid() if watchdog_pid is None else watchdog_pid)
    return Notifier.from_environ(env)


# -- messages, byte-exact ----------------------------------------------------------------------------


def test_ready_status_stopping_are_byte_exact(receiver: Receiver) -> None:
    with Notifier(receiver.address) as n:
        assert n.enabled
        assert n.ready()
        assert receiver.recv() == b"READY=1"
        assert n.ready("3 LEDs, scan 10 Hz")
        assert receiver.recv() == b"READY=1\nSTATUS=3 LEDs, scan 10 Hz"
        assert n.status("camera 30 fps; laser ok")
        assert receiver.recv() == b"STATUS=camera 30 fps; laser ok"
        assert n.extend_timeout(1.5)
        assert receiver.recv() == b"EXTEND_TIMEOUT_USEC=1500000"
        assert n.stopping()
        assert receiver.recv() == b"STOPPING=1"
        assert n.stats().sent == 5
        assert n.stats().send_failures == 0


def test_status_is_one_line_so_it_cannot_inject_fields(path_receiver: Receiver) -> None:
    with Notifier(path_receiver.address) as n:
        assert n.status("laser lost\nREADY=1\n")
        assert path_receiver.recv() == b"STATUS=laser lost READY=1"
        assert n.status("température ✓")
        assert path_receiver.recv() == "STATUS=température ✓".encode()


def test_watchdog_pings_only_while_all_loops_are_alive(receiver: Receiver) -> None:
    with watched(receiver) as n:
        assert n.watchdog_enabled
        assert n.watchdog_interval_s == 5.0
        assert n.watchdog_ping_if(True)
        assert receiver.recv() == b"WATCHDOG=1"

        assert not n.watchdog_ping_if(False)
        assert not n.watchdog_ping_if(False)
        assert receiver.pending() == []

        assert n.watchdog_ping_if(True)
        assert receiver.pending() == [b"WATCHDOG=1"]
        stats = n.stats()
        assert (stats.watchdog_pings, stats.watchdog_withheld, stats.sent) == (2, 2, 2)


def test_stall_and_recovery_are_logged_once_each(
    path_receiver: Receiver, caplog: pytest.LogCaptureFixture
) -> None:
    with watched(path_receiver) as n, caplog.at_level(logging.INFO, logger="agent.sdnotify"):
        for alive in (False, False, False, True, True):
            n.watchdog_ping_if(alive)
    messages = [r.getMessage() for r in caplog.records]
    assert sum("withholding watchdog pings" in m for m in messages) == 1
    assert sum("pings resumed" in m for m in messages) == 1


def test_watchdog_pid_of_another_process_means_no_pings(path_receiver: Receiver) -> None:
    with watched(path_receiver, watchdog_pid=os.getpid() + 1) as n:
        assert not n.watchdog_enabled
        assert n.watchdog_interval_s is None
        assert not n.watchdog_ping_if(True)
        assert not n.watchdog_ping()
        assert path_receiver.pending() == []
        # The rest of the protocol still works: only the watchdog belongs to the other process.
        assert n.ready()
        assert path_receiver.recv() == b"READY=1"


def test_forked_child_does_not_ping_for_its_parent(path_receiver: Receiver) -> None:
    # `pid` is the process the watchdog belongs to; a fork keeps the object but not the pid.
    with Notifier(path_receiver.address, watchdog_usec=10_000_000, pid=os.getpid() + 1) as n:
        assert not n.watchdog_enabled
        assert n.watchdog_interval_s is None
        assert not n.watchdog_ping_if(True)
        assert path_receiver.pending() == []


def test_a_real_fork_does_not_ping(path_receiver: Receiver) -> None:
    n = watched(path_receiver)
    child = os.fork()
    if child == 0:  # the child: same object, different pid
        os._exit(0 if not n.watchdog_ping_if(True) and not n.watchdog_enabled else 1)
    _, status = os.waitpid(child, 0)
    assert os.waitstatus_to_exitcode(status) == 0
    assert path_receiver.pending() == []
    assert n.watchdog_ping_if(True)  # the parent still pings
    assert path_receiver.recv() == b"WATCHDOG=1"
    n.close()


def test_no_watchdog_usec_means_no_pings(path_receiver: Receiver) -> None:
    with Notifier.from_environ({"NOTIFY_SOCKET": path_receiver.address}) as n:
        assert n.enabled
        assert not n.watchdog_enabled
        assert n.watchdog_interval_s is None
        assert not n.watchdog_ping_if(True)
        assert path_receiver.pending() == []


def test_unset_notify_socket_is_a_silent_no_op(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.DEBUG, logger="agent.sdnotify"):
        n = Notifier.from_environ({"WATCHDOG_USEC": WATCHDOG_10_S})
        assert not n.enabled
        assert not n.watchdog_enabled
        assert not n.ready("x")
        assert not n.status("x")
        assert not n.watchdog_ping_if(True)
        assert not n.watchdog_ping_if(False)
        assert not n.stopping()
        n.close()
        n.close()
    assert n.stats().sent == 0
    assert n.stats().send_failures == 0
    assert caplog.records == []


def test_receiver_gone_never_raises_and_is_counted_and_logged_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = str(tmp_path / "notify.sock")
    receiver = Receiver(path, path)
    n = watched(receiver)
    assert n.ready()
    receiver.close()
    os.unlink(path)  # systemd re-executing: the socket is briefly not there

    with caplog.at_level(logging.DEBUG, logger="agent.sdnotify"):
        assert not n.status("still here")
        assert not n.watchdog_ping_if(True)
        assert not n.stopping()
    stats = n.stats()
    assert (stats.sent, stats.send_failures, stats.watchdog_pings) == (1, 3, 0)
    assert stats.last_error is not None and "FileNotFoundError" in stats.last_error
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "failed" in warnings[0].getMessage()

    # It comes back: sends work again without a new Notifier, and the recovery is logged.
    receiver = Receiver(path, path)
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="agent.sdnotify"):
        assert n.watchdog_ping_if(True)
    assert receiver.recv() == b"WATCHDOG=1"
    assert any("works again" in r.getMessage() for r in caplog.records)
    n.close()
    receiver.close()


def test_full_receiver_queue_fails_fast_instead_of_blocking(path_receiver: Receiver) -> None:
    # Nobody reads the socket, so the kernel queue fills after a few datagrams. A blocking send would hang
    # the health monitor; the notifier must count failures and return. The join timeout only guards the
    # test against hanging forever if that regresses.
    n = Notifier(path_receiver.address)
    results: list[bool] = []
    worker = threading.Thread(target=lambda: results.extend(n.status(f"{i}") for i in range(2000)))
    worker.start()
    worker.join(timeout=60)
    assert not worker.is_alive(), "Notifier.send blocked on a full receiver queue"
    stats = n.stats()
    assert stats.sent + stats.send_failures == 2000
    assert stats.send_failures > 0
    assert results.count(True) == stats.sent
    n.close()


def test_closed_notifier_sends_nothing(path_receiver: Receiver) -> None:
    n = Notifier(path_receiver.address)
    n.close()
    assert not n.enabled
    assert not n.ready()
    assert path_receiver.pending() == []


def test_threads_share_one_notifier(path_receiver: Receiver) -> None:
    # Four threads send at once while a reader drains the socket. The kernel queue is short (a few
    # datagrams), so some sends may fail with EAGAIN; what matters is that every count adds up and
    # every datagram that arrived is whole.
    n = Notifier(path_receiver.address)
    got: list[bytes] = []
    done = threading.Event()

    def drain() -> None:
        path_receiver.sock.settimeout(0.2)
        while True:
            try:
                got.append(path_receiver.sock.recv(4096))
            except TimeoutError:
                if done.is_set():
                    return

    def send(k: int) -> None:
        for _ in range(25):
            n.status(f"t{k}")

    reader = threading.Thread(target=drain)
    reader.start()
    senders = [threading.Thread(target=send, args=(k,)) for k in range(4)]
    for t in senders:
        t.start()
    for t in senders:
        t.join()
    done.set()
    reader.join(timeout=60)
    stats = n.stats()
    assert stats.sent + stats.send_failures == 100
    assert len(got) == stats.sent > 0
    assert set(got) <= {b"STATUS=t0", b"STATUS=t1", b"STATUS=t2", b"STATUS=t3"}
    n.close()


# -- environment parsing -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("/run/systemd/notify", b"/run/systemd/notify"),
        ("@/org/freedesktop/systemd1/notify/123", b"\0/org/freedesktop/systemd1/notify/123"),
        (None, None),
        ("", None),
        ("@", None),
        ("vsock:2:1234", None),
        ("relative.sock", None),
    ],
)
def test_socket_address(value: str | None, expected: bytes | None) -> None:
    assert socket_address(value) == expected


@pytest.mark.parametrize(
    ("env", "expected_s"),
    [
        ({"WATCHDOG_USEC": WATCHDOG_10_S}, 5.0),
        ({"WATCHDOG_USEC": "3000000", "WATCHDOG_PID": "4242"}, 1.5),
        ({"WATCHDOG_USEC": WATCHDOG_10_S, "WATCHDOG_PID": "4243"}, None),
        ({"WATCHDOG_USEC": WATCHDOG_10_S, "WATCHDOG_PID": "not-a-pid"}, None),
        ({"WATCHDOG_USEC": "0"}, None),
        ({"WATCHDOG_USEC": "-5"}, None),
        ({"WATCHDOG_USEC": "ten"}, None),
        ({"WATCHDOG_USEC": ""}, None),
        ({}, None),
    ],
)
def test_watchdog_interval_is_half_of_watchdog_usec_for_our_pid(
    env: dict[str, str], expected_s: float | None
) -> None:
    assert watchdog_interval_s(env, pid=4242) == expected_s
    assert watchdog_usec(env, pid=4242) == (None if expected_s is None else int(expected_s * 2_000_000))


def test_unset_environment_keeps_children_from_notifying(path_receiver: Receiver) -> None:
    env = {
        "NOTIFY_SOCKET": path_receiver.address,
        "WATCHDOG_USEC": WATCHDOG_10_S,
        "WATCHDOG_PID": str(os.getpid()),
        "PATH": "/usr/bin",
    }
    n = Notifier.from_environ(env, unset_environment=True)
    assert env == {"PATH": "/usr/bin"}
    assert n.watchdog_enabled  # the notifier itself keeps what it read
    n.close()


# -- against the real client -------------------------------------------------------------------------


@pytest.mark.skipif(shutil.which("systemd-notify") is None, reason="systemd-notify is not installed")
def test_same_bytes_as_systemd_notify(path_receiver: Receiver) -> None:
    env = {**os.environ, "NOTIFY_SOCKET": path_receiver.address}
    proc = subprocess.Popen(["systemd-notify", "--ready", "--status=3 LEDs, scan 10 Hz"], env=env)
    theirs = path_receiver.recv()
    # systemd-notify then waits on a BARRIER=1 handshake (an fd we must close); Receiver.recv closes it.
    barrier = path_receiver.recv()
    assert proc.wait(timeout=30) == 0
    assert barrier == b"BARRIER=1"

    with Notifier(path_receiver.address) as n:
        n.ready("3 LEDs, scan 10 Hz")
    assert path_receiver.recv() == theirs == b"READY=1\nSTATUS=3 LEDs, scan 10 Hz"
