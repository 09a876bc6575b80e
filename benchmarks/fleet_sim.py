"""Two simulated robots meeting head-on in the office corridor, over several seeds: every goal reached, no
collision, how close they came. Prints one JSON object.

    python benchmarks/fleet_sim.py [--seeds 1 2 3] [--seconds 300]

Each run is ``vlp-agent sim --robots 2 --spacing 5 --goal 6.0,6.0 --goal 3.0,6.0 --seed S --json``: r1 from
(2, 6) drives east to (6, 6), r2 from (7, 6) west to (3, 6); they see each other only through the fleet
(the costmap's fleet layer). Issue 24 asks for no collision in 10 seeded runs, and one merged map whose
overlap agrees within 5 cm: per run, from the maps the robots published on ``fleet/<robot>/map`` (the
summary's ``maps``, docs/fleet.md "Maps"), the fraction of cells both saw that they classify alike and the
shift between their walls; and the privacy audit of everything heard on ``**`` during the run
(``privacy``: every key a documented fleet key, every payload decoding strictly).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--seconds", type=float, default=300.0)
    args = parser.parse_args()
    runs = []
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as out:
            argv = [sys.executable, "-m", "agent.cli", "sim", "--robots", "2", "--spacing", "5"]
            argv += ["--goal", "6.0,6.0", "--goal", "3.0,6.0", "--seed", str(seed), "--json", "--out", out]
            argv += ["--seconds", str(args.seconds)]
            done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, check=False)
        try:
            summary = json.loads(done.stdout)
        except json.JSONDecodeError:
            runs.append({"seed": seed, "error": done.stderr[-500:]})
            continue
        pairs = (summary.get("maps") or {}).get("pairs") or [{}]
        privacy = summary.get("privacy") or {}
        runs.append(
            {
                "seed": seed,
                "map_agreement": pairs[0].get("agreement"),
                "map_shift_m": pairs[0].get("shift_norm_m"),
                "map_overlap_m2": pairs[0].get("overlap_m2"),
                "privacy_messages": privacy.get("messages"),
                "privacy_by_kind": privacy.get("by_kind"),
                "privacy_failed": privacy.get("failed"),
                "reached": [r["goal"].get("state") == "reached" for r in summary["robots"]],
                "goals": [f"{r['goal'].get('state')} ({r['goal'].get('reason')})" for r in summary["robots"]],
                "goal_attempts": [r["goal"].get("history") for r in summary["robots"]],
                "collisions": summary["collisions"],
                "min_separation_m": summary["min_separation_m"],
                "fleet_pose_latency_ms_p95": summary["fleet_pose_latency_ms_p95"],
                "seconds": summary["seconds"],
            }
        )
    ok = [r for r in runs if "error" not in r]
    out = {
        "benchmark": "fleet_sim",
        "runs": runs,
        "all_reached": bool(ok) and all(all(r["reached"]) for r in ok) and len(ok) == len(runs),
        "collisions": sum(r["collisions"] for r in ok),
        "min_separation_m": min(
            (r["min_separation_m"] for r in ok if r["min_separation_m"] is not None), default=None
        ),
        "map_shift_m_max": max((r["map_shift_m"] for r in ok if r["map_shift_m"] is not None), default=None),
        "map_agreement_min": min(
            (r["map_agreement"] for r in ok if r["map_agreement"] is not None), default=None
        ),
        "maps_missing": sum(r["map_shift_m"] is None for r in ok),
        "privacy_failed": sum(r["privacy_failed"] or 0 for r in ok),
    }
    print(json.dumps(out, sort_keys=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
