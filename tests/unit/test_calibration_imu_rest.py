"""The mount step's IMU-at-rest reading: it waits longer for a slow IMU, and says how few samples it got."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from calibration.mount import imu_at_rest
from calibration.report import CalibrationError


class _SlowImu:
    """A fresh sample only every ``every``-th read; ``frozen``: never a fresh one."""

    def __init__(self, every: int, frozen: bool = False) -> None:
        self.every, self.frozen, self.reads = every, frozen, 0

    def read(self) -> SimpleNamespace:
        self.reads += 1
        k = 0 if self.frozen else self.reads // self.every
        return SimpleNamespace(accel_mps2=(0.001 * (k % 7), 0.0, 9.81))


class _Clock:
    """The test's own time: only the step's 4 ms sleeps move it, so a busy computer cannot starve the reads
    (the wall clock did: 7 fresh samples in 0.2 s beside a CPU hog)."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t

    def sleep(self, s: float) -> None:
        self.t += s


def test_a_slow_imu_is_read_for_longer() -> None:
    # 4 ms between reads, a fresh sample every third read: ~4 in the 0.05 s asked, 10 within 4x that.
    clock, imu = _Clock(), _SlowImu(3)
    mean, spread = imu_at_rest(imu, 0.05, lambda _: None, clock=clock, sleep=clock.sleep)  # type: ignore[arg-type]
    assert mean[2] == pytest.approx(9.81)
    assert spread < 0.01
    # It read on past the 0.05 s asked (about 13 reads), until the tenth fresh sample (read 27), not to 0.2 s.
    assert 0.05 < clock.t - 100.0 < 0.2 and imu.reads == 27


def test_a_frozen_imu_is_reported_with_its_count() -> None:
    with pytest.raises(CalibrationError, match=r"gave 1 fresh samples in 0\.[12]"):
        clock = _Clock()
        imu_at_rest(_SlowImu(1, frozen=True), 0.05, lambda _: None, clock=clock, sleep=clock.sleep)  # type: ignore[arg-type]
