"""Set-ups the tests share: running ``vlp-agent sim`` on a world, the example configs with their world
paths made absolute, and the minimal real-robot config the config tests build on."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

from tests.strict_json import strict_loads

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = REPO / "examples"

# A minimal real robot: servos only (odometry is a pose source), output on a port.
REAL_ROBOT = """
[servos]
backend = "dynamixel"
port = "/dev/dynamixel"

[output]
url = "/dev/ttyS0"
"""


def run_sim(*args: str, timeout_s: float) -> dict[str, Any]:
    """``vlp-agent sim ARGS --json`` in a fresh interpreter (stdin closed): its summary, once it has exited
    0 (the failure shows the end of its stderr). ``--seconds`` in ``args`` bounds the simulation;
    ``timeout_s`` only the process, as a last resort beside a CPU hog."""
    out = subprocess.run(
        [sys.executable, "-m", "agent.cli", "sim", *args, "--json"],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=REPO,
        check=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    summary: dict[str, Any] = strict_loads(out.stdout)
    return summary


def example_config(
    dest: Path,
    *,
    name: str = "sim.toml",
    world: str | None = None,
    replace: tuple[tuple[str, str], ...] = (),
    append: str = "",
) -> Path:
    """A copy of ``examples/NAME`` at ``dest`` with its ``"worlds/..."`` paths absolute (or its world
    ``worlds/office.toml`` swapped for ``examples/worlds/WORLD``), ``replace`` pairs applied in turn and
    ``append`` added at the end."""
    text = (EXAMPLES / name).read_text()
    if world is not None:
        text = text.replace('"worlds/office.toml"', f'"worlds/{world}"')
    text = text.replace('"worlds/', f'"{EXAMPLES / "worlds"}/')
    for old, new in replace:
        if old not in text:
            raise ValueError(f"examples/{name} has no {old!r} to replace")
        text = text.replace(old, new)
    dest.write_text(text + append)
    return dest
