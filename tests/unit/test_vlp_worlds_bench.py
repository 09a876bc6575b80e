"""benchmarks/vlp_worlds.py's verdict: a world passes issue 19's acceptance only with no uncaught exception,
no unflagged fix over 5 cm and protection coverage >= 0.999; every case names a world that exists."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from typing import Any

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "vlp_worlds.py"


def load_bench() -> Any:
    spec = importlib.util.spec_from_file_location("vlp_worlds", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["vlp_worlds"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_every_case_is_a_shipped_world() -> None:
    bench = load_bench()
    for _, stem, speed, prior in bench.CASES:
        assert (bench.WORLDS / f"{stem}.toml").is_file(), stem
        assert speed >= 0.0
        assert prior is None or (prior[0] > 0.0 and prior[1] > 0.0)


def test_the_table_has_exactly_the_acceptance_columns() -> None:
    bench = load_bench()
    assert bench.TABLE_COLUMNS == (
        "fix_fraction",
        "mean_error_cm",
        "p90_error_cm",
        "max_error_cm",
        "unflagged_over_5cm",
        "protection_coverage",
        "frame_ms_max",
    )
    good = [bench.Seeded(0, frames=10, fixed=10, errors_m=(0.001,) * 10, protected=10, frame_ms_max=3.0)]
    verdict = bench.row("x", 0.0, good)
    assert all(c in verdict for c in bench.TABLE_COLUMNS)
    assert verdict["mean_error_cm"] == 0.1 and verdict["frame_ms_max"] == 3.0


def test_the_verdict_follows_the_acceptance() -> None:
    bench = load_bench()
    good = [bench.Seeded(s, frames=10, fixed=10, errors_m=(0.001,) * 10, protected=10) for s in range(3)]
    assert bench.row("x", 0.0, good)["pass"]
    lying = [*good[:2], bench.Seeded(2, frames=10, fixed=10, errors_m=(0.3,), protected=1, unflagged=1)]
    verdict = bench.row("x", 0.0, lying)
    assert not verdict["pass"] and "1 unflagged fixes over 5 cm" in verdict["fails"]
    uncovered = [bench.Seeded(0, frames=1000, fixed=1000, errors_m=(0.001,) * 1000, protected=998)]
    assert not bench.row("x", 0.0, uncovered)["pass"]
    raised = [*good[:2], bench.Seeded(2, exception="ValueError: boom")]
    assert bench.row("x", 0.0, raised)["fails"] == ["uncaught exception"]
    # Every fix degraded: the criteria hold vacuously, and the row says so.
    degraded = [bench.Seeded(0, frames=10, fixed=10, degraded_errors_m=(1.0,) * 10, degraded=10)]
    verdict = bench.row("x", 0.0, degraded)
    assert verdict["pass"] and verdict["notes"] and verdict["protection_coverage"] is None
    # Environment 1 must also keep its figures.
    coarse = [
        bench.Seeded(0, frames=10, fixed=10, errors_m=(0.002,) * 10, protected=10, id_accuracy_track=1.0)
    ]
    assert not bench.row("env1", 0.0, coarse)["pass"]
