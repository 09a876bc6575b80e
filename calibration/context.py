"""What every step gets: how to talk to the user, where files go, where the robot is (or its simulation)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from agent.shipped import WORLDS
from calibration.report import CalibrationError, Console
from drivers.sim.world import World

__all__ = ["DEFAULT_DIR", "ROBOT_DIR", "SimOptions", "StepContext", "default_output_dir"]

# Where an installed robot keeps its calibration (systemd/install.sh creates it); elsewhere a local folder.
ROBOT_DIR = Path("/var/lib/vlp-agent/calibration")
DEFAULT_DIR = Path("vlp-calibration")
EXAMPLES = WORLDS
DEFAULT_SIM_WORLD = EXAMPLES / "env1.toml"


def default_output_dir() -> Path:
    """The robot's calibration folder when it exists and is writable, else ``./vlp-calibration``."""
    if ROBOT_DIR.is_dir() and os.access(ROBOT_DIR, os.W_OK):
        return ROBOT_DIR
    return DEFAULT_DIR


@dataclass(frozen=True)
class SimOptions:
    """The simulated robot: its world file and the seed of everything random in it."""

    world_file: Path = DEFAULT_SIM_WORLD
    seed: int = 0

    def load(self) -> World:
        from drivers.sim.worldfile import load_world

        if not self.world_file.is_file():
            raise CalibrationError(f"no such world file: {self.world_file}")
        return load_world(self.world_file)


@dataclass
class StepContext:
    """``config``: the robot's config file (devices and nominal values); None with ``sim``.
    ``interactive``: a person answers questions (the wizard); otherwise answers come from options or stdin."""

    console: Console
    out_dir: Path
    sim: SimOptions | None = None
    config: Path | None = None
    interactive: bool = False

    def output(self, override: str | None, default_name: str) -> Path:
        """The file a step writes: ``--output`` if given, else ``default_name`` in the output folder."""
        return Path(override) if override else self.out_dir / default_name

    def require_robot(self, what: str) -> None:
        """Fail early, with the fix, when a step needs a robot and there is neither config nor sim."""
        if self.sim is None and self.config is None:
            raise CalibrationError(
                f"{what} needs the robot: pass --config FILE (the robot's config, docs/config.md) or --sim"
            )
