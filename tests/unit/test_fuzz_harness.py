"""The codec robustness benchmark runs, and every codec holds its contract on a short run.

The full run (10^5 inputs per codec) is `python benchmarks/fuzz_codecs.py`; CI runs a few hundred.
"""

from __future__ import annotations

import gc
import importlib.util
import json
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from firmware_protocol.errors import ProtocolError

HARNESS = Path(__file__).resolve().parents[2] / "benchmarks" / "fuzz_codecs.py"


def load_harness() -> Any:
    spec = importlib.util.spec_from_file_location("fuzz_codecs", HARNESS)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["fuzz_codecs"] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_every_codec_survives_random_and_mutated_input(capsys: pytest.CaptureFixture[str]) -> None:
    module = load_harness()
    assert module.main(["--examples", "300"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["ok"] is True
    for name, codec in report["codecs"].items():
        assert codec["inputs"] == 300, name
        assert codec["failures"] == [], name
        # The mutated corpus must reach the decoders' good paths too, not only their error paths.
        assert codec["messages_decoded"] > 0, name


class SlowInGcDecoder:
    """A decoder whose first input hangs inside a gc callback, where Python swallows the alarm's exception."""

    def __init__(self) -> None:
        self.fed = False

    def feed(self, data: bytes) -> list[bytes]:
        if not self.fed:
            self.fed = True
            gc.callbacks.append(_sleep_in_gc)
            try:
                gc.collect()
            finally:
                gc.callbacks.remove(_sleep_in_gc)
        return []


def _sleep_in_gc(phase: str, info: dict[str, int]) -> None:
    if phase == "start":
        until = time.process_time() + 0.3  # CPU, which the harness's guard counts
        while time.process_time() < until:
            pass


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed alarm
def test_a_hang_inside_a_gc_callback_is_still_reported() -> None:
    module = load_harness()
    codec = module.Codec("slow", ProtocolError, SlowInGcDecoder, None, lambda: [b"\x01\x00"])
    result, _ = module.fuzz_codec(codec, examples=1, hang_s=0.05, seed_value=0)
    assert any("more than 0.05 s of CPU" in failure for failure in result.failures), result.failures
