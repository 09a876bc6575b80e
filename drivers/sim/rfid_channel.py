"""The UHF radio channel between the robot's reader antennas and a worn tag: what RSSI and phase a read has.

Pure numpy, no I/O; the fake Mercury reader (``drivers/fakes/rfid.py``) calls it per read. The model
(``docs/world.md``, ``[rfid]``):

* **Direct path and wall reflections** (first-order image sources): the one-way channel of antenna a is
  h = sum_k rho_k sqrt(G_a(theta_k)) exp(-i 2 pi d_k / lambda) / d_k over the direct path (rho = 1) and the
  mirror images of the tag in every wall within reach whose reflection point lies on the wall
  (rho = ``wall_reflection``), plus ``scatterers`` fixed random points of the floor plan (furniture,
  fittings) that re-radiate with ``scatter_amplitude``. lambda follows the hopped carrier, so the fading
  pattern changes from channel to channel as on a real frequency-hopping reader.
* **RSSI** = rssi_at_1m_dbm + 20 log10 |h| - body loss + N(0, noise_db): free-space slope 2 as the fake's
  legacy model, with multipath fading on top; ``body_loss_db`` when the wearer's body is between the tag
  (worn on the chest) and the robot, i.e. the person walks away from the robot (what a follower sees).
* **Phase**: the round trip's 2 arg h, as the M6e reports it, 0-180 degrees.
* **Antenna pattern** G: -12 (theta / beamwidth)^2 dB, floored at -front_to_back_db.

This is why the left/right RSSI cue is weak indoors (``reference/eco.md`` §3): the reflections fill in
the pattern's nulls, and a one-metre step moves the fading by several dB on every antenna.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

__all__ = ["SPEED_OF_LIGHT_MPS", "AntennaSite", "RfidChannel"]

FloatArray = npt.NDArray[np.float64]

SPEED_OF_LIGHT_MPS = 299_792_458.0
_MIN_PATH_M = 0.1


@dataclass(frozen=True, slots=True)
class AntennaSite:
    """An antenna on the robot base: position (x forward, y left) and boresight yaw."""

    x_m: float
    y_m: float
    yaw_rad: float


class RfidChannel:
    """The channel of one world (its walls, its scatterers) for a set of antennas."""

    def __init__(
        self,
        segments: FloatArray,
        antennas: tuple[AntennaSite, ...],
        *,
        beamwidth_rad: float,
        front_to_back_db: float,
        rssi_at_1m_dbm: float,
        wall_reflection: float,
        scatterers: int,
        scatter_amplitude: float,
        body_loss_db: float,
        noise_db: float,
        seed: int = 0,
        layout_seed: int = 0,
        reach_m: float = 8.0,
    ) -> None:
        self.segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
        self.antennas = antennas
        self.beamwidth_rad = beamwidth_rad
        self.front_to_back_db = front_to_back_db
        self.rssi_at_1m_dbm = rssi_at_1m_dbm
        self.wall_reflection = wall_reflection
        self.scatter_amplitude = scatter_amplitude
        self.body_loss_db = body_loss_db
        self.noise_db = noise_db
        self.reach_m = reach_m
        # The scatterers are the world's (its furniture: ``layout_seed``); the noise is the run's (``seed``).
        rng = np.random.default_rng(layout_seed)
        if self.segments.size:
            lo = np.minimum(self.segments[:, [0, 1]], self.segments[:, [2, 3]]).min(axis=0)
            hi = np.maximum(self.segments[:, [0, 1]], self.segments[:, [2, 3]]).max(axis=0)
        else:
            lo, hi = np.array([-5.0, -5.0]), np.array([5.0, 5.0])
        self.scatter_xy = rng.uniform(lo, hi, size=(scatterers, 2))
        # Each scatterer re-radiates with its own phase (its shape), fixed for the world.
        self.scatter_phase = rng.uniform(0.0, 2.0 * math.pi, size=scatterers)
        self._rng = np.random.default_rng(seed)

    def gain_db(self, offset_rad: FloatArray) -> FloatArray:
        theta = np.abs(np.remainder(offset_rad + np.pi, 2.0 * np.pi) - np.pi)
        out: FloatArray = np.maximum(-12.0 * (theta / self.beamwidth_rad) ** 2, -self.front_to_back_db)
        return out

    def _sources(self, tag_xy: FloatArray, near_xy: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The tag and its mirror images in walls within reach of ``near_xy`` (the robot): (K, 2) points
        and their amplitudes. An image counts when the reflection point of the path to the robot lies on
        the wall segment."""
        points = [tag_xy[None, :]]
        amps = [np.ones(1)]
        seg = self.segments
        if seg.size and self.wall_reflection > 0:
            a, b = seg[:, :2], seg[:, 2:]
            d = b - a
            length2 = np.maximum(np.sum(d * d, axis=1), 1e-12)
            # Mirror the tag in each wall's line: p' = 2 proj - p.
            t = np.sum((tag_xy - a) * d, axis=1) / length2
            foot = a + t[:, None] * d
            image = 2.0 * foot - tag_xy
            # Reflection point: where the robot-image line crosses the wall line.
            r = image - near_xy
            denom = r[:, 0] * d[:, 1] - r[:, 1] * d[:, 0]
            with np.errstate(divide="ignore", invalid="ignore"):
                u = ((a[:, 0] - near_xy[0]) * d[:, 1] - (a[:, 1] - near_xy[1]) * d[:, 0]) / denom
                hit = near_xy + u[:, None] * r
                s = np.sum((hit - a) * d, axis=1) / length2
            ok = (np.abs(denom) > 1e-9) & (s >= 0) & (s <= 1) & (u > 0) & (u < 1)
            ok &= np.hypot(*(image - near_xy).T) < self.reach_m
            points.append(image[ok])
            amps.append(np.full(int(ok.sum()), self.wall_reflection))
        if len(self.scatter_xy):
            points.append(self.scatter_xy)
            amps.append(np.full(len(self.scatter_xy), self.scatter_amplitude))
        return np.vstack(points), np.concatenate(amps)

    def read(
        self,
        robot_xy: tuple[float, float],
        robot_yaw_rad: float,
        tag_xy: tuple[float, float],
        facing_away: bool,
        frequency_hz: float,
    ) -> tuple[FloatArray, FloatArray]:
        """(RSSI dBm, phase degrees) per antenna for a tag at ``tag_xy``, with fresh noise."""
        tag = np.asarray(tag_xy, dtype=np.float64)
        robot = np.asarray(robot_xy, dtype=np.float64)
        sources, amps = self._sources(tag, robot)
        wavelength = SPEED_OF_LIGHT_MPS / frequency_hz
        c, s = math.cos(robot_yaw_rad), math.sin(robot_yaw_rad)
        rssi = np.empty(len(self.antennas))
        phase = np.empty(len(self.antennas))
        n_scatter = len(self.scatter_xy)
        for i, site in enumerate(self.antennas):
            pos = robot + np.array([c * site.x_m - s * site.y_m, s * site.x_m + c * site.y_m])
            v = sources - pos
            dist = np.maximum(np.hypot(v[:, 0], v[:, 1]), _MIN_PATH_M)
            if n_scatter:
                # A scatterer's path is antenna -> scatterer -> tag.
                dist[-n_scatter:] += np.hypot(*(self.scatter_xy - tag).T)
            angle = np.arctan2(v[:, 1], v[:, 0]) - (robot_yaw_rad + site.yaw_rad)
            gain = 10.0 ** (self.gain_db(angle) / 20.0)
            extra = np.zeros(len(sources))
            if n_scatter:
                extra[-n_scatter:] = self.scatter_phase
            h = np.sum(amps * gain * np.exp(-1j * (2.0 * math.pi * dist / wavelength + extra)) / dist)
            magnitude = max(abs(h), 1e-6)
            rssi[i] = self.rssi_at_1m_dbm + 20.0 * math.log10(magnitude)
            phase[i] = math.degrees(2.0 * float(np.angle(h))) % 180.0
        if facing_away:
            rssi -= self.body_loss_db
        rssi += self._rng.normal(0.0, self.noise_db, size=len(self.antennas))
        return rssi, phase
