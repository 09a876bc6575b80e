"""The codec robustness benchmark runs, and every codec holds its contract on a short run.

The full run (10^5 inputs per codec) is `python benchmarks/fuzz_codecs.py`; CI runs a few hundred.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

HARNESS = Path(__file__).resolve().parents[2] / "benchmarks" / "fuzz_codecs.py"


def test_every_codec_survives_random_and_mutated_input(capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("fuzz_codecs", HARNESS)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["fuzz_codecs"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    assert module.main(["--examples", "300"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True
    for name, codec in report["codecs"].items():
        assert codec["inputs"] == 300, name
        assert codec["failures"] == [], name
        # The mutated corpus must reach the decoders' good paths too, not only their error paths.
        assert codec["messages_decoded"] > 0, name
