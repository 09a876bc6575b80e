"""The research options' table of ``vlp-agent eval slam`` (agent.commands.eval_slam_options)."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from agent.commands.eval_slam_options import (
    RESEARCH_OPTIONS,
    add_research_options,
    apply_research_options,
    check_research_options,
)
from agent.slam.loops import LoopClosureConfig
from agent.slam.matcher import MatcherConfig
from agent.slam.proposal import ProposalConfig
from agent.slam.rbpf import RbpfConfig
from drivers.errors import ConfigError

_TARGETS = {
    "loop_closure": LoopClosureConfig,
    "proposal": ProposalConfig,
    "matcher": MatcherConfig,
    "filter": RbpfConfig,
}


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    parser.add_argument("--loop-closure", choices=("on", "off"), default="on")
    add_research_options(parser)
    return parser.parse_args(list(argv))


def _keys() -> dict[str, object]:
    return {"loop_closure": LoopClosureConfig(), "proposal": ProposalConfig()}


def _value(option_kind: object, choices: tuple[str, ...] | None) -> list[str]:
    if option_kind is None:
        return []
    if choices is not None:
        return [choices[-1]]
    return ["3"] if option_kind is int else ["0.5"]  # inside every range, off every default


def test_every_option_names_a_field_of_its_target() -> None:
    for option in RESEARCH_OPTIONS:
        fields = {f.name for f in dataclasses.fields(_TARGETS[option.target])}
        assert option.field in fields, option.flag
    flags = [option.flag for option in RESEARCH_OPTIONS]
    assert len(set(flags)) == len(flags)


def test_nothing_given_changes_nothing() -> None:
    keys = _keys()
    assert apply_research_options(_parse(), keys) == {}
    assert keys == _keys()


def test_every_option_reaches_its_field() -> None:
    # Everything each option needs: edge options need the matched sigma and the scan information.
    base = ["--edge-match-sigma", "0.5", "--edge-information", "scan", "--edge-scan-mean"]
    for option in RESEARCH_OPTIONS:
        argv = [*base, option.flag, *_value(option.kind, option.choices)] if option.flag not in base else base
        args = _parse(*argv)
        keys = _keys()
        extra = apply_research_options(args, keys)
        expected = getattr(args, option.dest)
        if option.target == "filter":
            got = extra[option.field]
        elif option.target == "matcher":
            got = getattr(keys["proposal"].matcher, option.field)  # type: ignore[attr-defined]
        else:
            got = getattr(keys[option.target], option.field)
        assert got == expected, option.flag
        assert got != getattr(_TARGETS[option.target](), option.field), f"{option.flag} left the default"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--edge-scan-anchor", "2"], "--edge-scan-anchor: needs --edge-information scan"),
        (["--edge-judge-plain"], "--edge-judge-plain: needs --edge-match-sigma"),
        (["--loop-closure", "off", "--loop-correction-odometry-sigmas", "1"], "needs --loop-closure on"),
        (["--loop-correction-odometry-sigmas", "11"], "must be in [0, 10]"),
        (["--proposal-temperature", "0"], "--proposal-temperature: must be positive"),
        (["--along-surface-weight", "-0.1"], "--along-surface-weight: must be in [0, 1]"),
        (
            ["--edge-match-sigma", "0.3", "--edge-information", "scan", "--edge-scan-anchor", "0"],
            "--edge-scan-anchor: must be in (0, 1e6]",
        ),
        (
            [
                "--edge-match-sigma",
                "0.3",
                "--edge-information",
                "scan",
                "--edge-scan-coarse-iterations",
                "101",
            ],
            "--edge-scan-coarse-iterations: must be in [0, 100]",
        ),
    ],
)
def test_a_bad_option_is_named(argv: list[str], message: str) -> None:
    with pytest.raises(ConfigError) as raised:
        check_research_options(_parse(*argv))
    assert message in str(raised.value)


def test_the_range_edges() -> None:
    check_research_options(_parse("--degenerate-noise-scale", "1", "--along-surface-weight", "0"))
    with pytest.raises(ConfigError, match="must be in"):
        check_research_options(_parse("--degenerate-noise-scale", "0"))
