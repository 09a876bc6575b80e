"""What a camera can tell apart: the LED map's signatures checked against the decoder's resolution.

Pure functions on the map and the camera's intrinsics (no I/O). An LED of frequency f draws stripes of
P = 1 / (f t_row_eff) output rows, its bright ones D P long, across a blob of H = f_px d / h rows (d its
diameter, h its height above the lens). The decoder (``agent.vlp.decode``) measures P in one frame to about

    sigma_P = sigma_edge sqrt(2) P / L,   L = 2 row_span (H / 2) rows of profile,

(sigma_edge = 0.3 row: an edge between two output rows is known to a row's width over sqrt(12); the
sub-row fit does better on short periods, so this is the conservative side; ``benchmarks/vlp_decode.py``).
Two signatures whose periods differ by less than ``RESOLUTION_SIGMAS`` sigma_P on the smaller blob, and whose
duties differ by less than a row's worth of stripe, cannot be told apart in one frame: the tracks vote over
frames and may never settle, or settle wrong. Single signatures are checked too: a stripe shorter than one
output row (the nearest-neighbour resize can drop it whole, and the decoder refuses it), periods under two
rows (aliasing), and blobs holding less than one period (too few stripes to read). Pairs the decoder
resolves but whose frequencies are closer than twice the row time's tolerance (3 %) are named as well: an
error of half their separation in the stated row time reads one as the other, on every frame alike.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from agent.vlp.model import CameraIntrinsics, LedMap

__all__ = [
    "RESOLUTION_SIGMAS",
    "ROW_TIME_TOLERANCE",
    "SignatureWarning",
    "check_signatures",
    "period_resolution_rows",
]

# Edge position noise (rows) in the resolution model: uniform over one output row.
SIGMA_EDGE_ROWS = 0.3
# Periods closer than this many sigma_P are not told apart in one frame.
RESOLUTION_SIGMAS = 3.0
# The decoder's profile spans this fraction of the blob's height (DecoderConfig.row_span, both sides).
ROW_SPAN = 0.92
# Least stripe (rows), least periods across the blob: as DecoderConfig's defaults.
MIN_STRIPE_ROWS = 1.0
MIN_PROFILE_PERIODS = 1.0
# How far off a row time not calibrated by `vlp-agent calibrate row-time` may be (issue 19: 2-3 %).
ROW_TIME_TOLERANCE = 0.03


@dataclass(frozen=True, slots=True)
class SignatureWarning:
    """One problem of the map for this camera: ``kind`` is ``"too-close"`` or ``"row-time"`` (a pair,
    ``ids`` both),
    ``"stripe-too-short"``, ``"aliased"`` or ``"too-few-stripes"`` (one signature); ``message`` says which
    and why, with the numbers."""

    kind: str
    ids: tuple[str, ...]
    message: str


def period_resolution_rows(period_rows: float, blob_rows: float) -> float:
    """The least period difference (rows) the decoder tells apart in one frame on a blob this tall."""
    profile = max(ROW_SPAN * blob_rows, 1.0)
    return RESOLUTION_SIGMAS * SIGMA_EDGE_ROWS * math.sqrt(2.0) * period_rows / profile


def check_signatures(
    led_map: LedMap,
    intrinsics: CameraIntrinsics,
    lens_height_m: float = 0.2,
    row_time_tolerance: float = ROW_TIME_TOLERANCE,
) -> list[SignatureWarning]:
    """Every pair of the map's signatures the camera cannot tell apart, and every signature it cannot read
    (see the module docstring). ``lens_height_m``: the lens above the floor (the mount's z), for the blobs'
    sizes. ``row_time_tolerance``: how far off the stated row time may be (a fraction); pairs whose
    frequencies are closer than twice that (and duties within a row of stripe) are named too (kind
    ``"row-time"``): a row-time error of half their separation reads one as the other."""
    t_eff = intrinsics.t_row_eff_s
    f_px = min(intrinsics.fx_px, intrinsics.fy_px)
    blob: dict[str, float] = {}
    for led in led_map.leds:
        rows = f_px * led.diameter_m / max(led.z_m - lens_height_m, 0.05)
        blob[led.id] = min(blob.get(led.id, math.inf), rows)
    out: list[SignatureWarning] = []
    sigs = led_map.signatures
    period = {s.id: 1.0 / (s.frequency_hz * t_eff) for s in sigs}
    for s in sigs:
        p, h = period[s.id], blob[s.id]
        stripe = min(s.duty, 1.0 - s.duty) * p
        name = f"LED {s.id} ({s.frequency_hz:.0f} Hz, duty {s.duty:.2f})"
        if p < 2.0:
            out.append(
                SignatureWarning(
                    "aliased",
                    (s.id,),
                    f"{name}: a stripe period of {p:.2f} rows is under 2 rows: the stripes alias",
                )
            )
        elif stripe < MIN_STRIPE_ROWS:
            kind = "bright" if s.duty <= 0.5 else "dark"
            out.append(
                SignatureWarning(
                    "stripe-too-short",
                    (s.id,),
                    f"{name}: its {kind} stripe lasts {stripe:.2f} rows, under {MIN_STRIPE_ROWS:g}: the "
                    "resize can drop it whole, so the decoder refuses it",
                )
            )
        if ROW_SPAN * h < MIN_PROFILE_PERIODS * p:
            out.append(
                SignatureWarning(
                    "too-few-stripes",
                    (s.id,),
                    f"{name}: its {h:.0f}-row blob holds {ROW_SPAN * h / p:.1f} periods of {p:.1f} rows, "
                    f"under {MIN_PROFILE_PERIODS:g}: too few stripes to read",
                )
            )
    for a, b in itertools.combinations(sigs, 2):
        pa, pb = period[a.id], period[b.id]
        h = min(blob[a.id], blob[b.id])
        resolution = period_resolution_rows(max(pa, pb), h)
        duty_rows = abs(a.duty - b.duty) * min(pa, pb)
        if duty_rows < 1.0 and abs(pa - pb) >= resolution:
            apart = abs(math.log(a.frequency_hz / b.frequency_hz))
            if apart < 2.0 * math.log1p(row_time_tolerance):
                out.append(
                    SignatureWarning(
                        "row-time",
                        (a.id, b.id),
                        f"LED {a.id} ({a.frequency_hz:.0f} Hz) and LED {b.id} ({b.frequency_hz:.0f} Hz) are "
                        f"{100.0 * math.expm1(apart):.1f} % apart: a row-time error of "
                        f"{50.0 * math.expm1(apart):.1f} % reads one as the other; check the row time "
                        "(vlp-agent calibrate row-time)",
                    )
                )
        if abs(pa - pb) < resolution and duty_rows < 1.0:
            out.append(
                SignatureWarning(
                    "too-close",
                    (a.id, b.id),
                    f"LED {a.id} ({a.frequency_hz:.0f} Hz) and LED {b.id} ({b.frequency_hz:.0f} Hz): periods "
                    f"{pa:.2f} and {pb:.2f} rows differ by less than the decoder's resolution "
                    f"{resolution:.2f} rows at a {h:.0f}-row blob"
                    + (
                        f", and their duties ({a.duty:.2f}, {b.duty:.2f}) by {duty_rows:.2f} rows of stripe"
                        if a.duty != b.duty
                        else ", at the same duty"
                    ),
                )
            )
    return out
