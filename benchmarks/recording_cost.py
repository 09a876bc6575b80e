"""What the flight recorder costs: the same simulated run with and without ``--record``. Prints one JSON
object.

    python benchmarks/recording_cost.py [--seconds 60] [--pairs 2]

Each pair is two fresh ``vlp-agent sim --json`` processes one after the other, without and with
``--record`` (the order alternates between pairs, so a machine that gets busier does not always count
against the same side). Reported per run: the process's CPU time (user + system, its children's too: the
camera renderer), the capture -> pose latency p99, and with recording the bytes written, the messages per
channel, drops and the writer thread's own CPU time (``record_writer_cpu_ms``). Over all pairs:

* ``extra_cpu_share_of_one_core``: (CPU with - CPU without) / seconds, the median over the pairs: the
  budget's measure (ARCHITECTURE.md: recording <= 3 % of one core), everything the recording costs (the
  loops' queue appends, the map snapshots, the writer) but also the run-to-run noise of a simulation whose
  threads compete for the cores;
* ``writer_cpu_share_of_one_core``: the writer thread alone (encoding, compression, writing), which has no
  such noise;
* ``bytes_per_minute``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
BUDGET_SHARE = 0.03


def one_run(seconds: float, record: bool) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "agent.cli", "sim", "--seconds", str(seconds), "--json", "--out", tmp]
        if record:
            cmd += ["--record", str(Path(tmp) / "rec" / "run.mcap")]
        t0, before = time.monotonic(), os.times()
        proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=False)
        wall_s, after = time.monotonic() - t0, os.times()
        if proc.returncode != 0:
            raise SystemExit(f"vlp-agent sim failed:\n{proc.stderr[-3000:]}")
        summary = json.loads(proc.stdout)
        out: dict[str, Any] = {
            "record": record,
            "wall_s": round(wall_s, 2),
            # The finished child's CPU time, and that of the processes it waited for (the renderer).
            "cpu_s": round(_children_cpu_s(after) - _children_cpu_s(before), 3),
            "latency_ms_p99": summary["latency_ms_p99"],
        }
        if record:
            rec = summary["recording"]
            out["bytes"] = sum(Path(p).stat().st_size for p in rec["files"])
            out["recording"] = {k: v for k, v in rec.items() if k != "files"}
    return out


def _children_cpu_s(t: os.times_result) -> float:
    return t.children_user + t.children_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--pairs", type=int, default=2)
    args = parser.parse_args()
    runs = []
    extra, writer, rates = [], [], []
    for i in range(args.pairs):
        order = (False, True) if i % 2 == 0 else (True, False)
        pair = {flag: one_run(args.seconds, flag) for flag in order}
        runs += [pair[False], pair[True]]
        extra.append((pair[True]["cpu_s"] - pair[False]["cpu_s"]) / args.seconds)
        writer.append(pair[True]["recording"]["record_writer_cpu_ms"] * 1e-3 / args.seconds)
        rates.append(pair[True]["bytes"] / args.seconds * 60)
    result = {
        "seconds": args.seconds,
        "runs": runs,
        "extra_cpu_share_of_one_core": round(statistics.median(extra), 4),
        "writer_cpu_share_of_one_core": round(statistics.median(writer), 4),
        "bytes_per_minute": round(statistics.median(rates)),
        "budget_share_of_one_core": BUDGET_SHARE,
    }
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
