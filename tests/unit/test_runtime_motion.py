"""The motor dead-man, the odometry track and the IMU tilt."""

from __future__ import annotations

import math

import pytest

from agent.runtime.motion import DriveCommand, OdometryTrack, StillDetector, TiltEstimator, wheel_speeds
from agent.runtime.types import Tilt

MS = 1_000_000


def test_a_stale_command_becomes_zero() -> None:
    drive = DriveCommand(deadman_timeout_s=0.5, recovery_hold_s=0.5, max_speed_mps=0.2, max_turn_radps=2.0)
    assert drive.current(0).reason == "none"
    drive.set(0.1, 0.3, 0)
    assert (drive.current(400 * MS).v_mps, drive.current(400 * MS).reason) == (0.1, "command")
    stale = drive.current(600 * MS)
    assert (stale.v_mps, stale.omega_radps, stale.reason) == (0.0, 0.0, "stale")
    assert drive.stale_events == 1
    drive.set(0.1, 0.0, 700 * MS)
    assert drive.current(710 * MS).reason == "command"


def test_after_a_fault_zero_is_held_whatever_is_commanded() -> None:
    drive = DriveCommand(0.5, 0.5, 0.2, 2.0)
    drive.set(0.15, 0.0, 0)
    drive.hold(100 * MS)
    assert drive.current(110 * MS).reason == "hold"
    drive.set(0.15, 0.0, 300 * MS)  # the command source kept going
    assert drive.current(400 * MS).v_mps == 0.0
    assert drive.current(700 * MS).v_mps == 0.15  # a command given after the hold counts


def test_commands_are_clamped_and_must_be_finite() -> None:
    drive = DriveCommand(0.5, 0.0, 0.2, 2.0)
    drive.set(1.0, -5.0, 0)
    c = drive.current(0)
    assert (c.v_mps, c.omega_radps) == (0.2, -2.0) and drive.clamped == 1
    with pytest.raises(ValueError):
        drive.set(math.nan, 0.0, 0)


def test_wheel_speeds_of_a_differential_drive() -> None:
    left, right = wheel_speeds(0.1, 1.0, 0.033, 0.16)
    assert left == pytest.approx((0.1 - 0.08) / 0.033) and right == pytest.approx((0.1 + 0.08) / 0.033)


def test_the_odometry_track_interpolates_and_holds() -> None:
    track = OdometryTrack(keep_s=1.0, hold_s=0.1)
    assert track.at(0) is None
    track.add(0, (0.0, 0.0, math.pi - 0.1))
    track.add(20 * MS, (0.02, 0.0, -math.pi + 0.1))
    x, _, yaw = track.at(10 * MS) or (0, 0, 0)
    assert x == pytest.approx(0.01) and abs(math.remainder(yaw - math.pi, math.tau)) < 1e-9  # across +-pi
    assert track.at(60 * MS) == pytest.approx((0.06, 0.0, -math.pi + 0.5))  # speed and turn rate held
    assert track.at(200 * MS) is None and track.at(-5 * MS) is None


def test_tilt_is_learnt_from_gravity_starting_level() -> None:
    tilt = TiltEstimator(tau_s=0.1)
    assert tilt.tilt() == Tilt(0.0, 0.0)  # before any still sample: level
    g = 9.81
    roll, pitch = math.radians(2.0), math.radians(-1.0)
    # At rest, rolled and pitched: f = g (-sin pitch, sin roll cos pitch, cos roll cos pitch).
    f = (-g * math.sin(pitch), g * math.sin(roll) * math.cos(pitch), g * math.cos(roll) * math.cos(pitch))
    tilt.update(0, f)
    first = tilt.tilt()
    assert 0 < first.roll_rad < 0.2 * roll  # one sample is one low-pass step, not the answer
    for k in range(1, 300):
        tilt.update(k * 10 * MS, f)
    t = tilt.tilt()
    assert t.roll_rad == pytest.approx(roll, abs=1e-6)
    assert t.pitch_rad == pytest.approx(pitch, abs=1e-6)
    tilt.update(10_000 * MS, (0.0, 0.0, -g))  # upside down: not a tilt
    assert tilt.tilt() == t


def test_still_means_not_moved_for_the_hold_time_with_fresh_odometry() -> None:
    still = StillDetector(hold_s=0.5)
    assert not still.still_at(0, 60 * MS)
    for k in range(30):  # 0.6 s standing, encoder noise below the tolerance
        still.update(k * 20 * MS, (1.0 + 1e-4 * (k % 2), 2.0, 0.3))
    assert still.still_at(29 * 20 * MS + 10 * MS, 60 * MS)
    assert not still.still_at(29 * 20 * MS + 100 * MS, 60 * MS)  # odometry stale: unknown
    still.update(30 * 20 * MS, (1.01, 2.0, 0.3))  # it moved
    assert not still.still_at(30 * 20 * MS, 60 * MS)
    still.reset()
    assert not still.still_at(30 * 20 * MS, 60 * MS)
