"""SP2ATM against the frontier baseline on one world and several seeds (issue 22's acceptance): each seed
is run by both explorers with ``vlp-agent eval explore``'s simulation (``run_exploration``: map from the true
pose, localization by odometry and VLP fixes, or with ``--map slam`` the RBPF's map and pose; faster than
real time), one after the other.

Prints one JSON object per run as it ends (the ``eval explore --json`` keys, with ``seed`` and
``explorer``), then one summary object: per explorer and per seed group (``tuned``: the seeds the
explorer's parameters were tuned on, 0-3; ``held_out``: the rest) the medians of path length, simulated
time, explored fraction and decision time (wall and CPU), the smallest explored fraction, the number of
runs that ended complete, that stopped early (complete below 95 % explored), and SP2ATM's median path
over the frontier explorer's on the same seeds (``path_ratio``; <= 1 is the acceptance). The frontier
explorer's decision CPU time is the floor SP2ATM's is compared with (``decision_cpu_ratio``), both
measured in the same process on the same machine; the budget is 50 ms median on one core.

OpenCV and BLAS are held to one thread.

    python benchmarks/explore_compare.py [--world examples/worlds/office.toml] [--seeds 0-11]
        [--explorers sp2atm,frontier] [--budget-s 1200] [--map truth-pose|slam] [--png-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.commands.eval_explore import MapSource, run_exploration
from agent.exploration import ExplorerKind
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[1] / "examples" / "worlds" / "office.toml"
TUNED = frozenset(range(4))  # the seeds SP2ATM's defaults were tuned on
EXPLORED_MIN = 0.95


def seeds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        elif part:
            out.append(int(part))
    return out


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 3) if values else None


def group(runs: list[dict[str, Any]]) -> dict[str, Any]:
    def col(key: str) -> list[float]:
        return [float(r[key]) for r in runs if r.get(key) is not None]

    return {
        "runs": len(runs),
        "seeds": [r["seed"] for r in runs],
        "path_length_m_median": _median(col("path_length_m")),
        "time_s_median": _median(col("time_s")),
        "explored_fraction_median": _median(col("explored_fraction")),
        "explored_fraction_min": min(col("explored_fraction"), default=None),
        "decision_ms_median": _median(col("decision_ms_median")),
        "decision_cpu_ms_median": _median(col("decision_cpu_ms_median")),
        "complete": sum(1 for r in runs if r["complete"]),
        "premature_complete": sum(1 for r in runs if r["complete"] and r["explored_fraction"] < EXPLORED_MIN),
        "collisions_walls": sum(int(r["collisions_walls"]) for r in runs),
        "collisions": sum(int(r["collisions"]) for r in runs),
        "retries": sum(int(r.get("retries", 0)) for r in runs),
        "target_switches_median": _median(col("target_switches")),
        "blocked_branches": sum(len(r.get("blocked_branches", [])) for r in runs),
        "ate_m_max": max(col("ate_m"), default=None),
        "map_error_m_max": max(col("map_error_m"), default=None),
    }


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--world", default=str(OFFICE))
    parser.add_argument("--seeds", default="0-11", help="e.g. 0-11 or 4,5,6 (default 0-11)")
    parser.add_argument("--explorers", default="sp2atm,frontier")
    parser.add_argument("--budget-s", type=float, default=1200.0)
    parser.add_argument("--map", choices=[m.value for m in MapSource], default=MapSource.TRUTH_POSE.value)
    parser.add_argument("--png-dir", default=None, help="write each run's picture here")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    world = load_world(Path(args.world))
    kinds = [ExplorerKind(k) for k in args.explorers.split(",") if k]
    runs: dict[ExplorerKind, list[dict[str, Any]]] = {k: [] for k in kinds}
    for seed in seeds(args.seeds):
        for kind in kinds:
            e = run_exploration(world, kind, seed, MapSource(args.map), args.budget_s)
            summary, picture = e.summary, e.picture
            if args.png_dir:
                folder = Path(args.png_dir)
                folder.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(folder / f"{world.name}-{kind.value}-{seed}.png"), picture)
            runs[kind].append(summary)
            print(json.dumps(summary, sort_keys=True), flush=True)
    out: dict[str, Any] = {
        "world": world.name,
        "map": args.map,
        "budget_s": args.budget_s,
        "tuned_seeds": sorted(TUNED),
    }
    for name, keep in (
        ("all", lambda s: True),
        ("tuned", lambda s: s in TUNED),
        ("held_out", lambda s: s not in TUNED),
    ):
        part: dict[str, Any] = {}
        for kind in kinds:
            part[kind.value] = group([r for r in runs[kind] if keep(r["seed"])])
        if ExplorerKind.SP2ATM in runs and ExplorerKind.FRONTIER in runs:
            a, b = part["sp2atm"], part["frontier"]
            if a["path_length_m_median"] and b["path_length_m_median"]:
                part["path_ratio"] = round(a["path_length_m_median"] / b["path_length_m_median"], 3)
            if a["decision_cpu_ms_median"] and b["decision_cpu_ms_median"]:
                part["decision_cpu_ratio"] = round(
                    a["decision_cpu_ms_median"] / b["decision_cpu_ms_median"], 3
                )
        out[name] = part
    print(json.dumps(out, sort_keys=True))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
