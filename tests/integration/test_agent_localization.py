"""Mapping, then localization on the saved map: ``vlp-agent sim`` writes the SLAM map as map_server files,
and an agent configured with ``[slam] mode = "localization"`` localizes on it (MCL), its pose fused."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from agent.slam.mapio import load_map
from tests.integration.test_agent_accuracy import REPO, vlp_agent


def run(*args: str) -> dict[str, object]:
    proc = subprocess.run(
        vlp_agent("sim", "--json", *args), capture_output=True, text=True, timeout=120, cwd=REPO, check=False
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary: dict[str, object] = json.loads(proc.stdout)
    return summary


def test_the_agent_localizes_on_the_map_it_saved(tmp_path: Path) -> None:
    mapping = run("--seconds", "12", "--out", str(tmp_path / "mapping"))
    files = mapping["files"]
    assert isinstance(files, dict)
    image = load_map(files["map_yaml"])
    assert image.occupied_mask().sum() > 100  # the corridor's walls

    examples = REPO / "examples"
    config = tmp_path / "localize.toml"
    config.write_text(
        (examples / "sim.toml")
        .read_text()
        .replace('"worlds/office.toml"', f'"{examples}/worlds/office.toml"')
        .replace('map_mode = "per_particle"', f'mode = "localization"\nmap = "{files["map_yaml"]}"')
    )
    localizing = run("--config", str(config), "--seconds", "10", "--out", str(tmp_path / "localizing"))
    assert localizing["unavailable"] == {}
    slam = localizing["slam"]
    assert isinstance(slam, dict)
    assert slam["filter_updates"] >= 3 and slam.get("unmatched_updates", 0) == 0
    assert localizing["fusion"]["slam_fused"] >= 3  # type: ignore[index]
    assert localizing["within_2cm"] >= 0.9  # type: ignore[operator]
    # Localization writes no map of its own.
    assert "map_yaml" not in localizing["files"]  # type: ignore[operator]
