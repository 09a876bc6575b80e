"""``vlp-agent eval vlp`` on Environment 1 with its four LEDs 50 Hz apart (3000-3150 Hz, duty 0.5): stripe
periods 4.07 to 3.88 rows, less than a row apart. The edges alone left 45 % of the sightings unsettled and a
fix on half the frames (issue 19); with the sub-row fit deciding between close signatures the ids settle,
right, and the map is checked at load (the pairs named)."""

from __future__ import annotations

import argparse
import json
import logging
import re
from pathlib import Path

import pytest

from agent.commands import eval_vlp
from tests.conftest import REPO

ENV1 = REPO / "examples" / "worlds" / "env1.toml"


def test_leds_50_hz_apart_are_identified(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    frequencies = iter([3000.0, 3050.0, 3100.0, 3150.0])
    text = ENV1.read_text()
    text = re.sub(r"frequency_hz = [0-9.]+", lambda m: f"frequency_hz = {next(frequencies)}", text)
    text = re.sub(r"duty = 0\.[0-9]+", "duty = 0.5", text)
    world = tmp_path / "close50.toml"
    world.write_text(text)
    parser = argparse.ArgumentParser()
    eval_vlp.add_parser(parser.add_subparsers(dest="what"))
    args = parser.parse_args(["vlp", "--world", str(world), "--points", "8", "--repeats", "12", "--json"])
    with caplog.at_level(logging.WARNING, logger="agent.vlp.pipeline"):
        assert eval_vlp.run(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["fix_fraction"] >= 0.9
    assert out["id_accuracy_track"] == 1.0
    # Ids settle on two decided frames in a row: each point's first frame (1 in 12) is unsettled by design,
    # and a frame the fit cannot decide delays it (0.17 here; under 0.15 when one frame settled an id).
    assert out["id_unsettled_fraction"] <= 0.22
    assert out["unflagged_over_5cm"] == 0
    # Neighbouring signatures are 0.06-0.07 row apart: the load-time check names them.
    warned = " ".join(r.getMessage() for r in caplog.records)
    assert "LED L1 (3000 Hz) and LED L2 (3050 Hz)" in warned
