"""The agent process opens no network socket: no camera image (nor anything else) can leave the robot over IP.

Two independent checks on the real process (``vlp-agent run`` on the simulated robot with both cameras,
the ceiling camera and the forward camera of person following, with systemd's
notification socket set so that the one socket it *should* open, AF_UNIX for sd_notify, is there):

* a ``sitecustomize`` installs a ``sys.addaudithook`` before any of the agent's code runs and logs every
  ``socket.__new__``: only AF_UNIX may appear (and it must, or the hook saw nothing);
* while it runs, every socket among ``/proc/<pid>/fd`` of the agent and its child processes (the SLAM
  process, the simulated camera's renderer) is looked up in ``/proc/<pid>/net/{tcp,udp,raw}{,6}``: none may
  be an IP socket.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import socket
import subprocess
import time
from pathlib import Path

from tests.integration.test_agent_accuracy import REPO, vlp_agent

HOOK = """
import os, sys

_LOG = os.environ["VLP_TEST_SOCKET_LOG"]

def _audit(event, args):
    if event == "socket.__new__":
        with open(_LOG, "a") as fp:
            fp.write(f"{int(args[1])} {int(args[2])}\\n")

with open(_LOG, "a") as fp:
    fp.write("hook\\n")
sys.addaudithook(_audit)
"""

IP_TABLES = ("tcp", "tcp6", "udp", "udp6", "raw", "raw6", "udplite", "udplite6")


def socket_inodes(pid: int) -> set[int]:
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        match = re.fullmatch(r"socket:\[(\d+)\]", target)
        if match:
            inodes.add(int(match.group(1)))
    return inodes


def ip_socket_inodes(pid: int) -> set[int]:
    inodes = set()
    for table in IP_TABLES:
        path = Path(f"/proc/{pid}/net/{table}")
        if not path.exists():
            continue
        for line in path.read_text().splitlines()[1:]:
            fields = line.split()
            if len(fields) > 9:
                inodes.add(int(fields[9]))
    return inodes


def family(pid: int) -> list[int]:
    """``pid`` and its descendants (from ``/proc/<pid>/task/<tid>/children``)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
    return out


def test_the_agent_process_opens_no_network_socket(tmp_path: Path) -> None:
    (tmp_path / "hook").mkdir()
    (tmp_path / "hook" / "sitecustomize.py").write_text(HOOK)
    log = tmp_path / "sockets.log"
    notify_path = tmp_path / "notify.sock"
    notify = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    notify.bind(str(notify_path))
    examples = REPO / "examples"
    config = tmp_path / "robot.toml"
    # Both cameras: the ceiling camera of the pose and the forward camera of person following; and the
    # fleet loop serving its bridge (a Unix socket: the bridge, another process, holds the network).
    config.write_text(
        (examples / "sim.toml").read_text().replace('"worlds/', f'"{examples}/worlds/')
        + "\n[camera.forward]\nframe_rate_hz = 10.0\nrender_process = true\n"
        + f'\n[fleet]\nsocket = "{tmp_path / "fleet.sock"}"\n'
    )
    env = {
        **os.environ,
        "PYTHONPATH": f"{tmp_path / 'hook'}{os.pathsep}{REPO}",
        "VLP_TEST_SOCKET_LOG": str(log),
        "NOTIFY_SOCKET": str(notify_path),
        "WATCHDOG_USEC": "2000000",
    }
    proc = subprocess.Popen(
        vlp_agent("run", "--config", str(config), "--seconds", "5", "--json"),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )
    seen_sockets: set[int] = set()
    ip_in_use: set[int] = set()
    pids_seen: set[int] = set()
    try:
        deadline = time.monotonic() + 30
        while proc.poll() is None and time.monotonic() < deadline:
            for pid in family(proc.pid):
                try:
                    ours = socket_inodes(pid)
                    seen_sockets |= ours
                    ip_in_use |= ours & ip_socket_inodes(pid)
                except FileNotFoundError:  # the process ended between two reads
                    continue
                pids_seen.add(pid)
            time.sleep(0.2)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        notify.close()
    assert proc.returncode == 0, stderr[-2000:]
    lines = log.read_text().splitlines()
    # One "hook" line per process that started: the agent, its SLAM process and the simulated cameras'
    # render processes (render_process = true), which both checks watch too.
    assert lines[0] == "hook" and lines.count("hook") >= 4
    assert len(pids_seen) >= 4
    families = {int(line.split()[0]) for line in lines if line != "hook"}
    # The positive control: sd_notify's AF_UNIX datagram socket was seen, by both checks.
    assert int(socket.AF_UNIX) in families and seen_sockets
    assert families == {int(socket.AF_UNIX)}, f"socket families created: {families}"
    assert ip_in_use == set()
    # The forward camera did run (its frames stayed in the process).
    assert json.loads(stdout.strip().splitlines()[-1])["counts"].get("forward_frames", 0) > 0
