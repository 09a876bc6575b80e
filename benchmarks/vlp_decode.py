"""Stripe decoding below the output row: frequency error and id accuracy of close signatures, edges vs fit.

Single LEDs rendered by the simulator (``drivers.sim.render``: the MV-UB300 at 800x600, nearest-neighbour
resize, 32 us rows, 20 us exposure) straight above the camera at random offsets and headings, over a range
of stripe periods (LED frequencies) and blob heights (LED diameters). Each frame is decoded twice:

- ``edges``: the decoder without the sub-row fit (``DecoderConfig(period_fit="never")``, no row timing):
  the period from the interpolated edges, the id from the edge template, as before issue 19 (the refusals
  for what a frame cannot show apply to it too: on these frames they change its ids by under 1 %);
- ``fit``: the decoder with the camera's row timing (``RowTiming.of``) and the sub-row fit
  (``period_fit="always"`` for the frequency, the default ``"ambiguous"`` for the ids).

Per (period, blob height): the frequency error (bias, rms, max, relative), and, for a pair of signatures
``--separation-hz`` apart (the LED blinking at the lower one; the map holding both), the share of frames
identified right, wrong, and refused (no id, with the reason counted). Prints one JSON object.

    .venv/bin/python benchmarks/vlp_decode.py [--frames N] [--seed S] [--separation-hz 100]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.sim_view import nominal_intrinsics
from agent.vlp.decode import DecoderConfig, RowTiming, StripeDecoder
from agent.vlp.detect import DetectorConfig, find_blobs
from agent.vlp.model import CameraIntrinsics, Signature
from drivers.sim.render import RollingShutterRenderer
from drivers.sim.world import CameraModel, Led, Mount, Pose2D, World

FREQUENCIES_HZ = (1500.0, 2000.0, 3000.0, 4500.0)
DIAMETERS_M = (0.05, 0.086, 0.14)


def intrinsics_of(cam: CameraModel) -> CameraIntrinsics:
    """The camera as the agent knows it (here: exactly)."""
    return nominal_intrinsics(World("benchmark", camera=cam))


def _stats(errors: list[float], period: float, frequency_hz: float) -> dict[str, float]:
    """Period errors (rows): bias, rms, max, and the rms as a frequency error (dP / P of f, in Hz)."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        return {"n": 0}
    rms = float(np.sqrt(np.mean(e * e)))
    return {
        "n": int(e.size),
        "bias_rows": round(float(e.mean()), 4),
        "rms_rows": round(rms, 4),
        "max_rows": round(float(np.abs(e).max()), 4),
        "rms_hz": round(rms / period * frequency_hz, 2),
    }


def run_case(frequency_hz: float, diameter_m: float, frames: int, separation_hz: float, seed: int) -> dict:
    cam = CameraModel()
    intrinsics = intrinsics_of(cam)
    t_eff = intrinsics.t_row_eff_s
    period = 1.0 / (frequency_hz * t_eff)
    led = Led("A", 0.0, 0.0, 1.5, frequency_hz=frequency_hz, duty=0.5, diameter_m=diameter_m)
    renderer = RollingShutterRenderer(cam, [led], Mount(0.0, 0.0, 0.2), seed=seed)
    signatures = (Signature("A", frequency_hz, 0.5), Signature("B", frequency_hz + separation_hz, 0.5))
    decoders = {
        "edges": (
            StripeDecoder(DecoderConfig(period_fit="never")),
            StripeDecoder(DecoderConfig(period_fit="never")),
        ),
        "fit": (
            StripeDecoder(DecoderConfig(period_fit="always"), RowTiming.of(intrinsics)),
            StripeDecoder(DecoderConfig(), RowTiming.of(intrinsics)),
        ),
    }
    errors: dict[str, list[float]] = {k: [] for k in decoders}
    ids: dict[str, Counter[str]] = {k: Counter() for k in decoders}
    reasons: dict[str, Counter[str]] = {k: Counter() for k in decoders}
    rng = np.random.default_rng(seed)
    detector = DetectorConfig(min_diameter_px=6.0, bridge_px=period + 2.0)
    blob_rows = 0.0
    for k in range(frames):
        pose = Pose2D(float(rng.uniform(-0.2, 0.2)), float(rng.uniform(-0.2, 0.2)), float(rng.uniform(-3, 3)))
        frame = renderer.render(lambda t, p=pose: p, 1.0 + 0.05 * k + float(rng.uniform(0.0, 0.01)))
        blob_rows = 2.0 * frame.truth.leds[0].radius_px
        blobs = [b for b in find_blobs(frame.image, detector) if not b.at_border]
        if len(blobs) != 1:
            continue
        b = blobs[0]
        request = [(b.centre_px, b.radius_px, b.background_dn, False)]
        for name, (measure, identify) in decoders.items():
            (feat,) = measure.features_many(frame.image, request, t_eff)
            if math.isfinite(feat.period_px):
                errors[name].append(feat.period_px - period)
            ((_, cls),) = identify.decode_many(frame.image, request, signatures, t_eff)
            verdict = "right" if cls.id == "A" else "wrong" if cls.id is not None else "refused"
            ids[name][verdict] += 1
            if cls.reason:
                reasons[name][cls.reason.split(":")[0]] += 1
    out: dict[str, object] = {
        "frequency_hz": frequency_hz,
        "period_rows": round(period, 3),
        "blob_rows": round(blob_rows, 1),
    }
    for name in decoders:
        n = sum(ids[name].values())
        stats = _stats(errors[name], period, frequency_hz)
        out[name] = {
            "period_error": stats,
            "ids": {v: round(ids[name][v] / n, 3) if n else None for v in ("right", "wrong", "refused")},
            "refusals": dict(reasons[name]),
        }
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=30, help="frames per case (default 30)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--separation-hz", type=float, default=100.0, help="the pair's separation (100)")
    args = parser.parse_args()
    cases = [
        run_case(f, d, args.frames, args.separation_hz, args.seed + 17 * i)
        for i, (d, f) in enumerate((d, f) for d in DIAMETERS_M for f in FREQUENCIES_HZ)
    ]
    summary = {}
    for name in ("edges", "fit"):
        right = [c[name]["ids"]["right"] for c in cases if c[name]["ids"]["right"] is not None]
        wrong = [c[name]["ids"]["wrong"] for c in cases if c[name]["ids"]["wrong"] is not None]
        rel = [
            c[name]["period_error"]["rms_rows"] / c["period_rows"]
            for c in cases
            if c[name]["period_error"]["n"]
        ]
        summary[name] = {
            "ids_right_mean": round(float(np.mean(right)), 3),
            "ids_wrong_mean": round(float(np.mean(wrong)), 3),
            "ids_wrong_max": round(float(np.max(wrong)), 3),
            "period_rms_relative_median": round(float(np.median(rel)), 4),
        }
    print(
        json.dumps(
            {"frames": args.frames, "separation_hz": args.separation_hz, "summary": summary, "cases": cases},
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
