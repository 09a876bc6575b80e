"""Localization on a saved map of the simulated office, started from a VLP fix.

A first drive maps the office with VLP fixes (so the map is in the LED frame) and saves it as map_server
files; a second drive (other noise, other odometry errors) loads them and localizes with Monte Carlo
localization, started from that drive's first VLP fix and then on the laser alone. The fixes of both come
from rendered camera frames through the VLP pipeline (``agent.commands.sim_fixes``). It stays within 5 cm of
the truth at every scan.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from agent.commands.sim_fixes import PipelineFixes
from agent.slam.fix import PoseFix
from agent.slam.mapio import load_map, save_map
from agent.slam.mcl import MclConfig, MclLocalizer
from agent.slam.rbpf import RbpfConfig, StepKind
from agent.slam.render import occupancy_image
from agent.slam.replay import replay
from agent.slam.simlog import MOTION_NOISE, SimulatedRun, WheelErrorModel, simulate_log
from drivers.sim.worldfile import load_world

OFFICE = Path(__file__).resolve().parents[2] / "examples" / "worlds" / "office.toml"
SECONDS = 60.0


@pytest.fixture(scope="module")
def office_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    world = load_world(OFFICE)
    mapping = simulate_log(world, SECONDS, fixes=PipelineFixes(world, seed=0), seed=0)
    config = RbpfConfig(particles=30, noise=MOTION_NOISE, initial_pose=mapping.start_pose(from_fix=True))
    slam = replay(mapping.log, config, fixes=mapping.fixes).slam
    window = slam.map_window()
    assert window is not None
    image = occupancy_image(window[0], window[1], config.grid.resolution_m)
    return save_map(image, tmp_path_factory.mktemp("office") / "office.yaml").yaml


@pytest.fixture(scope="module")
def second_drive() -> SimulatedRun:
    # Other wheels as well as other noise: this robot's odometry errs the other way round.
    wheels = WheelErrorModel(left_scale=0.996, right_scale=0.999, track_scale=0.99)
    world = load_world(OFFICE)
    return simulate_log(world, SECONDS, wheel_errors=wheels, fixes=PipelineFixes(world, seed=5), seed=5)


def localize(office_map: Path, drive: SimulatedRun, fix: PoseFix, odom_at_fix: np.ndarray) -> np.ndarray:
    """Position errors (m) at every scan after the localizer started from ``fix``, laser only after it."""
    occupancy = load_map(office_map)
    mcl = MclLocalizer(drive.log.geometry, occupancy, MclConfig(noise=MOTION_NOISE, seed=2))
    errors = []
    started = False
    for record, truth in zip(drive.log.records, drive.truth, strict=True):
        if not started and record.t_s >= drive.fixes[0].t_s:
            mcl.initialize(fix, odom_at_fix)
            started = True
        result = mcl.process(record.t_s, record.ranges_m, record.odom_pose)
        if started:
            assert result.kind is not StepKind.UNINITIALIZED
            errors.append(float(np.hypot(*(mcl.pose(record.odom_pose)[:2] - truth[:2]))))
    assert mcl.stats.updates > 50 and mcl.stats.fixes_applied == 0
    return np.array(errors)


def test_localization_from_a_vlp_fix_stays_within_5_cm(office_map: Path, second_drive: SimulatedRun) -> None:
    first = second_drive.fixes[0]
    errors = localize(office_map, second_drive, first.fix, first.odom_pose)
    assert errors.size > 550
    assert errors.max() < 0.05
    assert errors.mean() < 0.025


def test_localization_from_a_position_only_fix(office_map: Path, second_drive: SimulatedRun) -> None:
    # A fix with no heading (one LED's worth of information, say), 10 cm of uncertainty: the headings
    # start spread round the circle, and the laser picks the right one within the first metre.
    first = second_drive.fixes[0]
    coarse = PoseFix(first.fix.x_m, first.fix.y_m, None, np.diag([0.1**2, 0.1**2]))
    errors = localize(office_map, second_drive, coarse, first.odom_pose)
    settled = errors[50:]  # 5 s, under a metre of driving
    assert settled.max() < 0.05
