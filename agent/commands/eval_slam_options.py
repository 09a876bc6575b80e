"""``vlp-agent eval slam``'s research options: variants of the filter measured in ``docs/slam.md``, each
off (or at its source's default) unless asked for, none of them what the agent runs.

Every option is declared once in :data:`RESEARCH_OPTIONS` (its flag, the configuration field it sets, its
range and the option it needs); the parser's group, the checks of a command line and the filter
configuration it gives are all made from that table, so adding a variant is one entry."""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

# Which part of ``RbpfConfig`` an option sets: the loop closure (``LoopClosureConfig``), the proposal
# (``ProposalConfig``), its scan matcher (``MatcherConfig``) or the filter itself.
Target = Literal["loop_closure", "proposal", "matcher", "filter"]


@dataclass(frozen=True, slots=True)
class Bounds:
    """The values an option takes: ``low`` to ``high``, ``low`` itself excluded when ``open_low``;
    ``text`` is the error a value outside them gets (``must be in (0, 1]``)."""

    low: float
    high: float
    open_low: bool
    text: str

    def holds(self, value: float) -> bool:
        above = value > self.low if self.open_low else value >= self.low
        return above and value <= self.high


@dataclass(frozen=True, slots=True)
class Needs:
    """Another option's setting an option is meaningless without: ``text`` names it for the error
    (``needs --edge-information scan``), ``holds`` tells from the parsed command line."""

    text: str
    holds: Callable[[argparse.Namespace], bool]


@dataclass(frozen=True, slots=True)
class ResearchOption:
    """One command-line option: ``--flag`` sets ``field`` of ``target``. ``kind`` is its value's type
    (``None``: a switch, set when given); ``choices`` lists the words it takes."""

    flag: str
    target: Target
    field: str
    help: str
    kind: type[float] | type[int] | type[str] | None = float
    metavar: str | None = None
    choices: tuple[str, ...] | None = None
    bounds: Bounds | None = None
    needs: Needs | None = None

    @property
    def dest(self) -> str:
        return self.flag.removeprefix("--").replace("-", "_")

    def given(self, args: argparse.Namespace) -> bool:
        value = getattr(args, self.dest)
        return bool(value) if self.kind is None else value is not None


def _with_edge_sigma(args: argparse.Namespace) -> bool:
    return args.edge_match_sigma is not None


def _with_scan_edges(args: argparse.Namespace) -> bool:
    return bool(args.edge_information == "scan")


_EDGE_SIGMA = Needs("needs --edge-match-sigma", _with_edge_sigma)
_SCAN_EDGES = Needs("needs --edge-information scan", _with_scan_edges)
_LOOP_CLOSURE = Needs("needs --loop-closure on", lambda args: args.loop_closure == "on")
_UNIT = Bounds(0.0, 1.0, open_low=False, text="must be in [0, 1]")

RESEARCH_OPTIONS: tuple[ResearchOption, ...] = (
    ResearchOption(
        "--along-surface-weight",
        "proposal",
        "along_surface_weight",
        "weight of a scan point's offset along its surface in the match: 1 point to point, 0 point to "
        "line (default: 0 for radish, 1 otherwise)",
        metavar="W",
        bounds=_UNIT,
    ),
    ResearchOption(
        "--proposal-temperature",
        "proposal",
        "proposal_temperature",
        "the proposal's likelihood temperature T' (default: 1)",
        metavar="T",
        bounds=Bounds(0.0, math.inf, open_low=True, text="must be positive"),
    ),
    ResearchOption(
        "--degenerate-noise-scale",
        "proposal",
        "degenerate_noise_scale",
        "a particle's draw is K times narrower in the directions its scan match does not hold (a "
        "corridor's length), ~1 where it does ([slam] degenerate_noise_scale, in (0, 1]; default: 0.3 for "
        "--world, 1 otherwise: the paper's draw)",
        metavar="K",
        bounds=Bounds(0.0, 1.0, open_low=True, text="must be in (0, 1]"),
    ),
    ResearchOption(
        "--medial-window-cells",
        "matcher",
        "medial_window_cells",
        "judge a wall's straightness, for the match's distance to its medial line, over the square of W "
        "cells either way around it ([slam] match_medial_window_cells, 0-8; default 0: a wall cell's four "
        "neighbours): finds walls on cell boundaries mapped in patches, hurts walls elsewhere",
        kind=int,
        metavar="W",
        bounds=Bounds(0, 8, open_low=False, text="must be in [0, 8]"),
    ),
    ResearchOption(
        "--search-heading-doubt",
        "filter",
        "search_heading_doubt",
        "also run the correlative search at an update whose odometry heading is as doubtful (motion "
        "model) as after a straight search_increment_m, not only past the metres or radians thresholds "
        "(RbpfConfig.search_heading_doubt)",
        kind=None,
    ),
    ResearchOption(
        "--loop-correction-odometry-sigmas",
        "loop_closure",
        "correction_odometry_sigmas",
        "the pose graph widens a front-end edge only by the match's departure from odometry beyond K of "
        "the motion model's sigmas ([slam] loop_correction_odometry_sigmas; default: the whole departure)",
        metavar="K",
        bounds=Bounds(0.0, 10.0, open_low=False, text="must be in [0, 10]"),
        needs=_LOOP_CLOSURE,
    ),
    ResearchOption(
        "--edge-match-sigma",
        "loop_closure",
        "edge_match_sigma_m",
        "the pose graph's front-end edges get their covariance from each update's scan match, its "
        "information over S² (an endpoint's residual, metres, in (0, 1]; "
        "LoopClosureConfig.edge_match_sigma_m; default: off, the edges' sigmas from the match's departure "
        "from odometry)",
        metavar="S",
        bounds=Bounds(0.0, 1.0, open_low=True, text="must be in (0, 1] metres"),
        needs=_LOOP_CLOSURE,
    ),
    ResearchOption(
        "--edge-information",
        "loop_closure",
        "edge_information",
        "which information: the match's own sum J Jᵀ (match), or the point-to-line information of the "
        "endpoints with a surface normal only (normals: loose along a corridor), or that of a relative "
        "measurement, the update's scan matched point to line against the last update's (scan: only what "
        "the two scans share; LoopClosureConfig.edge_information; default: match)",
        kind=str,
        choices=("match", "normals", "scan"),
        needs=_EDGE_SIGMA,
    ),
    ResearchOption(
        "--edge-departure-floor",
        "loop_closure",
        "edge_departure_floor",
        "each edge's covariance sits on its sigmas widened by the match's departure from odometry (the "
        "edges without --edge-match-sigma) instead of the plain motion sigmas "
        "(LoopClosureConfig.edge_departure_floor)",
        kind=None,
        needs=_EDGE_SIGMA,
    ),
    ResearchOption(
        "--edge-judge-plain",
        "loop_closure",
        "edge_judge_plain",
        "a loop candidate's consistency tests run on the chain without the edges' covariances (the "
        "departure-widened sigmas), the accepted graph with them (LoopClosureConfig.edge_judge_plain)",
        kind=None,
        needs=_EDGE_SIGMA,
    ),
    ResearchOption(
        "--edge-normal-radius-per-m",
        "loop_closure",
        "edge_normal_radius_per_m",
        "the normals the information is taken from are estimated for it alone, from a neighbourhood of "
        "max(0.25 m, R x range), up to 3 cm thick (LoopClosureConfig.edge_normal_radius_per_m; default: "
        "the match's own normals; with scan 0.1)",
        metavar="R",
        bounds=_UNIT,
        needs=Needs(
            "needs --edge-information normals or scan",
            lambda args: args.edge_information in ("normals", "scan"),
        ),
    ),
    ResearchOption(
        "--edge-scan-mean",
        "loop_closure",
        "edge_scan_mean",
        "the edges' means from the scan-to-scan match too, not the filter's steps "
        "(LoopClosureConfig.edge_scan_mean)",
        kind=None,
        needs=_SCAN_EDGES,
    ),
    ResearchOption(
        "--edge-scan-gate-chi2",
        "loop_closure",
        "edge_scan_gate_chi2",
        "only at the edges where the scan-to-scan step and the filter's differ by more than C (squared "
        "Mahalanobis distance under the edge's covariance; LoopClosureConfig.edge_scan_gate_chi2; "
        "default: 0, every edge)",
        metavar="C",
        bounds=Bounds(0.0, 1e6, open_low=False, text="must be in [0, 1e6]"),
        needs=Needs("needs --edge-scan-mean", lambda args: bool(args.edge_scan_mean)),
    ),
    ResearchOption(
        "--edge-scan-coarse-iterations",
        "loop_closure",
        "edge_scan_coarse_iterations",
        "the scan-to-scan match's first N iterations pair endpoints within 0.5 m, so a step the filter "
        "put tens of centimetres off is pulled back (LoopClosureConfig.edge_scan_coarse_iterations; "
        "default: 0)",
        kind=int,
        metavar="N",
        bounds=Bounds(0, 100, open_low=False, text="must be in [0, 100]"),
        needs=_SCAN_EDGES,
    ),
    ResearchOption(
        "--edge-scan-anchor",
        "loop_closure",
        "edge_scan_anchor",
        "the scan-to-scan match's pull towards the filter's step (per m² and rad², against one per paired "
        "endpoint; LoopClosureConfig.edge_scan_anchor; default: 5)",
        metavar="A",
        bounds=Bounds(0.0, 1e6, open_low=True, text="must be in (0, 1e6]"),
        needs=_SCAN_EDGES,
    ),
    ResearchOption(
        "--edge-scan-fallback",
        "loop_closure",
        "edge_scan_fallback",
        "an edge whose scan-to-scan match failed takes the update's own match's information instead of "
        "none (LoopClosureConfig.edge_scan_fallback)",
        kind=None,
        needs=_SCAN_EDGES,
    ),
)


def add_research_options(parser: argparse.ArgumentParser) -> None:
    """The table's options, in their own group of ``parser``'s help."""
    group = parser.add_argument_group(
        "research options",
        'Variants of the filter measured in docs/slam.md ("Open problems", "Measurements"): off, or '
        "at the source's default, unless given; not what the agent runs. The --edge-* options shape the "
        "pose graph's front-end edges and need --edge-match-sigma.",
    )
    for option in RESEARCH_OPTIONS:
        if option.kind is None:
            group.add_argument(option.flag, action="store_true", help=option.help)
        else:
            group.add_argument(
                option.flag,
                type=option.kind,
                choices=option.choices,
                metavar=option.metavar,
                help=option.help,
            )


def check_research_options(args: argparse.Namespace) -> None:
    """Raise ``ConfigError`` for the first option given without what it needs or out of its range."""
    from drivers.errors import ConfigError

    for option in RESEARCH_OPTIONS:
        if not option.given(args):
            continue
        if option.needs is not None and not option.needs.holds(args):
            raise ConfigError(option.flag, option.needs.text)
        value = getattr(args, option.dest)
        if option.bounds is not None and not option.bounds.holds(value):
            raise ConfigError(option.flag, option.bounds.text)


def apply_research_options(args: argparse.Namespace, filter_keys: dict[str, Any]) -> dict[str, Any]:
    """``filter_keys`` (``RbpfConfig`` fields: ``loop_closure`` and ``proposal`` among them) with the
    options ``args`` gives, checked first (:func:`check_research_options`); returns the ``RbpfConfig``
    fields of the ``filter`` target, which the caller passes beside them."""
    check_research_options(args)
    changes: dict[Target, dict[str, Any]] = {"loop_closure": {}, "proposal": {}, "matcher": {}, "filter": {}}
    for option in RESEARCH_OPTIONS:
        if option.given(args):
            changes[option.target][option.field] = getattr(args, option.dest)
    if changes["loop_closure"]:
        loop_closure = filter_keys["loop_closure"]
        filter_keys["loop_closure"] = dataclasses.replace(loop_closure, **changes["loop_closure"])
    proposal = filter_keys["proposal"]
    if changes["matcher"]:
        changes["proposal"]["matcher"] = dataclasses.replace(proposal.matcher, **changes["matcher"])
    if changes["proposal"]:
        filter_keys["proposal"] = dataclasses.replace(proposal, **changes["proposal"])
    return changes["filter"]
