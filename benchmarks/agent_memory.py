"""The service's memory over time: ``vlp-agent run`` on the simulated robot. Prints one JSON object.

    python benchmarks/agent_memory.py [--minutes 10] [--interval 10] [--warmup 120] [--config FILE]

Starts ``vlp-agent run`` (the systemd service's entry point) with a config that has ``[sim]`` (default
``examples/sim.toml``: camera, VLP, SLAM, fusion, the pose stream on a pty read by the simulated controller),
samples the agent process's memory every ``--interval`` seconds for ``--minutes``, then stops it with
SIGTERM. A service runs for weeks, so what matters is the slope: a least-squares line through the samples
after ``--warmup`` seconds (start-up, the first map, the heap settling), in MB per hour. The measure is the
agent's anonymous resident memory (``RssAnon`` in ``/proc/PID/status``: its heap, where a leak shows);
``VmRSS`` is reported beside it, but it also counts file-backed pages (the interpreter, numpy's libraries)
that the kernel drops and reloads under memory pressure from other processes, which moves it by tens of MB
either way. The agent's child processes (the camera's renderer, the simulated controller) are sampled too,
apart. Progress goes to stderr, one line per sample.

Reported: ``samples`` ([seconds since start, agent RssAnon MB, children RssAnon MB, agent VmRSS MB]),
``slope_mb_per_h`` (the agent's RssAnon after the warm-up), ``children_slope_mb_per_h``,
``vm_rss_slope_mb_per_h``, ``rss_anon_mb_first`` / ``_last`` / ``_peak`` after the warm-up, and the
agent's own final status (``frames_received``: the pose stream kept flowing).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]


def rss_mb(pid: int, field: str = "RssAnon") -> float | None:
    """A resident-set field of /proc/PID/status in MB (``RssAnon``: the heap and other anonymous memory;
    ``VmRSS``: everything resident), None once the process is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    for line in text.splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024.0
    return None


def children(pid: int) -> list[int]:
    """Every descendant of ``pid`` (through /proc/PID/task/*/children)."""
    out: list[int] = []
    todo = [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = [int(k) for k in (task / "children").read_text().split()]
            except (FileNotFoundError, ProcessLookupError):
                continue
            out.extend(kids)
            todo.extend(kids)
    return out


def slope_per_h(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (seconds, MB) in MB per hour; NaN with fewer than two points."""
    n = len(points)
    if n < 2:
        return float("nan")
    mt = sum(t for t, _ in points) / n
    mv = sum(v for _, v in points) / n
    stt = sum((t - mt) ** 2 for t, _ in points)
    if stt == 0:
        return float("nan")
    return 3600.0 * sum((t - mt) * (v - mv) for t, v in points) / stt


def sim_config(path: Path | None, tmp: Path) -> Path:
    """The given config, or a copy of examples/sim.toml with its world path made absolute."""
    if path is not None:
        return path
    text = (REPO / "examples" / "sim.toml").read_text()
    text = text.replace('"worlds/', f'"{REPO / "examples" / "worlds"}/')
    out = tmp / "sim.toml"
    out.write_text(text)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--interval", type=float, default=10.0, help="seconds between samples")
    parser.add_argument("--warmup", type=float, default=120.0, help="seconds left out of the slope")
    parser.add_argument(
        "--config", type=Path, default=None, help="a config with [sim] (default: examples/sim.toml)"
    )
    args = parser.parse_args()
    total_s = args.minutes * 60.0
    with tempfile.TemporaryDirectory() as tmp:
        config = sim_config(args.config, Path(tmp))
        cmd = [sys.executable, "-m", "agent.cli", "run", "--config", str(config), "--json"]
        env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC")}
        proc = subprocess.Popen(
            cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        samples: list[tuple[float, float, float, float]] = []
        t0 = time.monotonic()
        try:
            while True:
                elapsed = time.monotonic() - t0
                main_mb, main_rss = rss_mb(proc.pid), rss_mb(proc.pid, "VmRSS")
                if main_mb is None or main_rss is None or proc.poll() is not None:
                    raise SystemExit(f"vlp-agent run ended early:\n{proc.communicate()[1][-3000:]}")
                kids_mb = sum(v for v in (rss_mb(c) for c in children(proc.pid)) if v is not None)
                samples.append((round(elapsed, 1), round(main_mb, 2), round(kids_mb, 2), round(main_rss, 2)))
                print(
                    f"[{elapsed / 60:5.1f}/{args.minutes:g} min] agent {main_mb:7.2f} MB anonymous "
                    f"({main_rss:.2f} MB resident), children {kids_mb:7.2f} MB",
                    file=sys.stderr,
                    flush=True,
                )
                if elapsed >= total_s:
                    break
                time.sleep(min(args.interval, max(0.0, total_s - elapsed)))
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            try:
                stdout, stderr = proc.communicate(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                stdout, stderr = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"vlp-agent run exited {proc.returncode}:\n{stderr[-3000:]}")
    status: dict[str, Any] = json.loads(stdout)
    steady = [s for s in samples if s[0] >= args.warmup]
    main_steady = [s[1] for s in steady]
    result = {
        "command": " ".join(cmd[2:]),
        "minutes": args.minutes,
        "interval_s": args.interval,
        "warmup_s": args.warmup,
        "cpus": os.cpu_count(),
        "slope_mb_per_h": round(slope_per_h([(s[0], s[1]) for s in steady]), 2),
        "children_slope_mb_per_h": round(slope_per_h([(s[0], s[2]) for s in steady]), 2),
        "rss_anon_mb_first": main_steady[0] if main_steady else None,
        "rss_anon_mb_last": main_steady[-1] if main_steady else None,
        "rss_anon_mb_peak": max(main_steady) if main_steady else None,
        "vm_rss_slope_mb_per_h": round(slope_per_h([(s[0], s[3]) for s in steady]), 2),
        "vm_rss_mb_peak": max((s[3] for s in samples), default=None),
        "frames_received": status.get("frames_received"),
        "flags": status.get("flags"),
        "samples": samples,
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
