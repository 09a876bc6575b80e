"""The coarse layer of person following: where the tagged person is, from the RFID reader's reads.

A recursive Bayes filter (the reference system's "Bayes rule over directions", ``seeds/
rtm-assistance-robot-system.txt`` §3.3, made recursive as in ``reference/eco.md`` §3) over a polar grid
around the robot: ``n_sectors`` bearing sectors times range bins, plus one "absent" state (out of reach,
or hidden so well that nothing is read). Per read cycle (a window of ``cycle_s``) the observation is, for
each antenna port, whether the tag was read and its mean RSSI:

    predict:  b'(c) = sum_c' M(c | c', robot motion, dt) b(c')         (robot turns and drives; person walks)
    update:   b(c) ∝ b'(c) [prod_a L_a(o_a | c)]^w                       (w: likelihood_weight)
              L_a = P_a(det | c) N(rssi_a; mu_a(c), sd_a(c))  if antenna a read the tag, else 1 - P_a(det | c)

The likelihood table (P, mu, sd per antenna, sector and range bin) comes from a physical model by default
(:func:`default_table`: log-distance path loss, an antenna pattern, a fading spread) and is replaced by a
calibrated one (``vlp-agent calibrate rfid``, :func:`fit_table`). Indoors the left/right RSSI difference of
two antennas is a weak cue (eco.md §3 measured a correlation of 0.13-0.37 with sin(bearing) while driving),
so the filter is a prior for the camera, not a tracker: its output carries a spread and a confidence.

Phase: a Mercury module reports the reply's phase (0-180 degrees), but it is not used. It wraps every
lambda/4 = 8 cm of range (round trip, 915 MHz), the reader hops over 50 channels (each with its own phase
offset) and reads a tag a few times a second, while a walking person moves 20 cm between reads: the phase
cannot be unwrapped into range or radial speed at that rate; and the two ports' phase difference (antennas
0.15 m apart) wraps several times over the possible angles of arrival.

Pure numpy: no threads, ports or files; time and robot motion are passed in.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

__all__ = [
    "Antenna",
    "CoarseEstimate",
    "CoarseFilter",
    "LikelihoodTable",
    "Observation",
    "RadioModel",
    "SectorGrid",
    "WindowEstimate",
    "antenna_gain_db",
    "default_table",
    "fit_table",
    "observation_from_reads",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

_SQRT_2PI = math.sqrt(2.0 * math.pi)
# Probabilities in the table stay inside this, so that one surprising read never zeroes a cell.
_P_MIN, _P_MAX = 0.02, 0.98
_SD_MIN_DB = 1.0


# -- the radio, as the agent models it -----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Antenna:
    """One reader antenna: its port, where it points on the base (yaw, CCW from forward) and its pattern."""

    port: int
    yaw_rad: float
    beamwidth_rad: float = math.radians(70.0)  # full width at half power (-3 dB), a typical circular patch
    front_to_back_db: float = 15.0


def antenna_gain_db(offset_rad: FloatArray | float, beamwidth_rad: float, front_to_back_db: float) -> Any:
    """Gain relative to boresight at ``offset_rad`` off it: the parabolic main-lobe model
    G = -12 (theta / theta_3dB)^2 dB (-3 dB at half the beam width), floored at the front-to-back ratio."""
    theta = np.abs(np.remainder(np.asarray(offset_rad) + np.pi, 2.0 * np.pi) - np.pi)
    return np.maximum(-12.0 * (theta / beamwidth_rad) ** 2, -front_to_back_db)


@dataclass(frozen=True, slots=True)
class RadioModel:
    """The physical prior: RSSI = rssi_at_1m - 10 n log10(r) + G(antenna) - body + fading, read when above
    ``sensitivity_dbm``. ``fading_sd_db`` is the spread multipath adds indoors; ``body_loss_db`` is lost
    when the wearer's back is to the robot, which the model takes as half the time (a mean loss of half
    of it, and as much again in spread)."""

    antennas: tuple[Antenna, ...]
    rssi_at_1m_dbm: float = -50.0
    path_loss_exponent: float = 2.0
    fading_sd_db: float = 5.0
    sensitivity_dbm: float = -80.0
    body_loss_db: float = 8.0

    @property
    def spread_db(self) -> float:
        """The RSSI spread about the mean: fading and the body's (0 or ``body_loss_db``, evenly)."""
        return math.hypot(self.fading_sd_db, self.body_loss_db / 2.0)

    def mean_rssi_dbm(self, antenna: Antenna, bearing_rad: FloatArray, range_m: FloatArray) -> FloatArray:
        gain = antenna_gain_db(bearing_rad - antenna.yaw_rad, antenna.beamwidth_rad, antenna.front_to_back_db)
        loss = 10.0 * self.path_loss_exponent * np.log10(np.maximum(range_m, 0.1))
        out: FloatArray = self.rssi_at_1m_dbm - loss + gain - self.body_loss_db / 2.0
        return out


# -- the grid ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SectorGrid:
    """Bearing sectors (sector 0 centred straight ahead, counter-clockwise) times range bins.

    A person beyond the last range edge is "absent" (the filter's extra state)."""

    n_sectors: int = 16
    range_edges_m: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.5)

    def __post_init__(self) -> None:
        if self.n_sectors < 4:
            raise ValueError(f"n_sectors must be at least 4, got {self.n_sectors}")
        edges = self.range_edges_m
        if len(edges) < 2 or edges[0] < 0 or any(b <= a for a, b in itertools.pairwise(edges)):
            raise ValueError(f"range_edges_m must rise from >= 0 with at least one bin, got {edges}")

    @property
    def n_ranges(self) -> int:
        return len(self.range_edges_m) - 1

    @property
    def n_cells(self) -> int:
        return self.n_sectors * self.n_ranges

    @property
    def sector_width_rad(self) -> float:
        return 2.0 * math.pi / self.n_sectors

    @property
    def bearings_rad(self) -> FloatArray:
        """Sector centres, wrapped to (-pi, pi]."""
        b = np.arange(self.n_sectors) * self.sector_width_rad
        out: FloatArray = np.remainder(b + np.pi, 2.0 * np.pi) - np.pi
        return out

    @property
    def range_centres_m(self) -> FloatArray:
        e = np.asarray(self.range_edges_m)
        out: FloatArray = (e[:-1] + e[1:]) / 2.0
        return out

    @property
    def max_range_m(self) -> float:
        return self.range_edges_m[-1]

    def sector_of(self, bearing_rad: FloatArray | float) -> Any:
        return np.round(np.asarray(bearing_rad) / self.sector_width_rad).astype(np.int64) % self.n_sectors

    def range_bin_of(self, range_m: FloatArray | float) -> Any:
        """Range bin index; ``n_ranges`` (the absent state's slot) beyond the last edge."""
        r = np.asarray(range_m)
        edges = np.asarray(self.range_edges_m)
        idx = np.searchsorted(edges, r, side="right") - 1
        return np.where(r >= edges[-1], self.n_ranges, np.clip(idx, 0, self.n_ranges - 1))

    def samples(self, per_side: int = 3) -> tuple[FloatArray, FloatArray]:
        """Stratified points inside every cell: (bearing, range) arrays of shape (S, R, per_side**2)."""
        offsets = (np.arange(per_side) + 0.5) / per_side  # (k,)
        w = self.sector_width_rad
        b = self.bearings_rad[:, None] + (offsets - 0.5) * w  # (S, k)
        e = np.asarray(self.range_edges_m)
        r = e[:-1, None] + offsets[None, :] * np.diff(e)[:, None]  # (R, k)
        bearing = np.broadcast_to(b[:, None, :, None], (self.n_sectors, self.n_ranges, per_side, per_side))
        rng = np.broadcast_to(r[None, :, None, :], (self.n_sectors, self.n_ranges, per_side, per_side))
        n = per_side * per_side
        return (
            bearing.reshape(self.n_sectors, self.n_ranges, n).copy(),
            rng.reshape(self.n_sectors, self.n_ranges, n).copy(),
        )


# -- the likelihood table ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LikelihoodTable:
    """Per antenna port a, sector s, range bin r: P(read in a cycle), RSSI mean and sd when read.

    ``p_detect_absent``: the chance a port reads the tag in a cycle while the person is "absent" (beyond
    the grid: a freak reflection); absent reads are taken as near the sensitivity (``absent_rssi_dbm``).
    """

    grid: SectorGrid
    ports: tuple[int, ...]
    p_detect: FloatArray  # (A, S, R)
    rssi_mean_dbm: FloatArray  # (A, S, R)
    rssi_sd_db: FloatArray  # (A, S, R)
    p_detect_absent: float = 0.03
    absent_rssi_dbm: float = -78.0
    absent_sd_db: float = 4.0
    source: str = "model"

    def __post_init__(self) -> None:
        shape = (len(self.ports), self.grid.n_sectors, self.grid.n_ranges)
        if not self.ports or len(set(self.ports)) != len(self.ports):
            raise ValueError(f"ports must be distinct and at least one, got {self.ports}")
        for name in ("p_detect", "rssi_mean_dbm", "rssi_sd_db"):
            value = np.asarray(getattr(self, name), dtype=np.float64)
            if value.shape != shape:
                raise ValueError(
                    f"{name} must have shape {shape} (ports, sectors, ranges), got {value.shape}"
                )
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{name} must be finite")
            object.__setattr__(self, name, value)
        if np.any(self.p_detect < 0) or np.any(self.p_detect > 1):
            raise ValueError("p_detect must be probabilities in [0, 1]")
        if np.any(self.rssi_sd_db <= 0):
            raise ValueError("rssi_sd_db must be > 0")
        if not 0.0 <= self.p_detect_absent < 1.0:
            raise ValueError("p_detect_absent must be in [0, 1)")

    def to_dict(self) -> dict[str, Any]:
        """The table as plain lists (TOML/JSON): ``p_detect[a][s][r]`` etc., a = index in ``ports``."""
        return {
            "n_sectors": self.grid.n_sectors,
            "range_edges_m": list(self.grid.range_edges_m),
            "ports": list(self.ports),
            "p_detect": np.round(self.p_detect, 4).tolist(),
            "rssi_mean_dbm": np.round(self.rssi_mean_dbm, 2).tolist(),
            "rssi_sd_db": np.round(self.rssi_sd_db, 2).tolist(),
            "p_detect_absent": self.p_detect_absent,
            "absent_rssi_dbm": self.absent_rssi_dbm,
            "absent_sd_db": self.absent_sd_db,
            "source": self.source,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> LikelihoodTable:
        """Inverse of :meth:`to_dict`. Raises ValueError (naming the key) on a malformed table."""
        try:
            grid = SectorGrid(int(data["n_sectors"]), tuple(float(e) for e in data["range_edges_m"]))
            return cls(
                grid,
                tuple(int(p) for p in data["ports"]),
                np.asarray(data["p_detect"], dtype=np.float64),
                np.asarray(data["rssi_mean_dbm"], dtype=np.float64),
                np.asarray(data["rssi_sd_db"], dtype=np.float64),
                float(data.get("p_detect_absent", 0.03)),
                float(data.get("absent_rssi_dbm", -78.0)),
                float(data.get("absent_sd_db", 4.0)),
                str(data.get("source", "file")),
            )
        except KeyError as exc:
            raise ValueError(f"missing key {exc.args[0]!r}") from exc
        except (TypeError, ValueError) as exc:
            raise ValueError(str(exc)) from exc


def default_table(model: RadioModel, grid: SectorGrid | None = None) -> LikelihoodTable:
    """The table the physical model predicts: per cell, the mean over points spread inside it of the
    model RSSI; its sd adds the spread inside the cell to the fading; P(read) = P(RSSI > sensitivity)."""
    grid = grid or SectorGrid()
    bearing, rng = grid.samples(per_side=5)
    p, mu, sd = [], [], []
    for antenna in model.antennas:
        m = model.mean_rssi_dbm(antenna, bearing, rng)  # (S, R, k)
        total_sd = np.sqrt(model.spread_db**2 + m.var(axis=2))
        mu.append(m.mean(axis=2))
        sd.append(total_sd)
        z = (m - model.sensitivity_dbm) / model.spread_db
        p.append(np.mean(_normal_cdf(z), axis=2))
    return LikelihoodTable(
        grid,
        tuple(a.port for a in model.antennas),
        np.clip(np.array(p), _P_MIN, _P_MAX),
        np.array(mu),
        np.maximum(np.array(sd), _SD_MIN_DB),
        absent_rssi_dbm=model.sensitivity_dbm + 2.0,
        source="model",
    )


def _normal_cdf(z: FloatArray) -> FloatArray:
    from scipy.special import ndtr

    out: FloatArray = ndtr(z)
    return out


# -- observations --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Observation:
    """One read cycle: per antenna port (in the table's order) whether the tag was read, and the mean RSSI
    of its reads (NaN where it was not read or the reader reports no RSSI)."""

    detected: BoolArray
    rssi_dbm: FloatArray

    @classmethod
    def of(cls, detected: Sequence[bool], rssi_dbm: Sequence[float]) -> Observation:
        d = np.asarray(detected, dtype=np.bool_)
        r = np.asarray(rssi_dbm, dtype=np.float64)
        if d.shape != r.shape or d.ndim != 1:
            raise ValueError(f"detected {d.shape} and rssi_dbm {r.shape} must be equal 1-D shapes")
        return cls(d, r)


class _Read(Protocol):
    @property
    def tag_id(self) -> str: ...
    @property
    def rssi_dbm(self) -> float | None: ...
    @property
    def antenna(self) -> int | None: ...


def observation_from_reads(reads: Iterable[_Read], ports: Sequence[int], tag_id: str) -> Observation:
    """The observation of one cycle from the reads of that cycle (``drivers.samples.TagRead`` or alike):
    only ``tag_id``'s reads count; a read without an antenna counts for the first port."""
    sums = np.zeros(len(ports))
    counts = np.zeros(len(ports), dtype=np.int64)
    with_rssi = np.zeros(len(ports), dtype=np.int64)
    index = {p: i for i, p in enumerate(ports)}
    wanted = tag_id.upper()
    for read in reads:
        if read.tag_id.upper() != wanted:
            continue
        i = index.get(read.antenna if read.antenna is not None else ports[0])
        if i is None:
            continue
        counts[i] += 1
        if read.rssi_dbm is not None:
            sums[i] += read.rssi_dbm
            with_rssi[i] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        rssi = np.where(with_rssi > 0, sums / np.maximum(with_rssi, 1), np.nan)
    return Observation(counts > 0, rssi)


# -- the filter ----------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class CoarseEstimate:
    """The filter's answer. ``bearing_rad``: the most likely direction (CCW from forward), refined inside
    the best sector; ``spread_rad``: the circular standard deviation of the whole bearing posterior;
    ``confidence``: the probability that the person is present and within one sector of ``bearing_rad``;
    ``p_absent``: the probability of the "absent" state; ``range_m``: expected range when present;
    ``p_front``: the probability that the person is present and ahead (|bearing| < 90 degrees): two
    forward-looking antennas tell front from back poorly (the RSSI level is all they have for it), so a
    follower should look ahead when this is not small, whatever ``bearing_rad`` says."""

    bearing_rad: float
    spread_rad: float
    range_m: float
    confidence: float
    p_absent: float
    sector: int
    p_front: float = math.nan


@dataclass(frozen=True, slots=True)
class WindowEstimate:
    """The posterior inside a window of bearings (a camera's field of view): ``probability`` that the person
    is present there, and their most likely ``bearing_rad`` within it (the circular mean of the window's
    mass; NaN when it holds none)."""

    probability: float
    bearing_rad: float


@dataclass
class CoarseFilter:
    """The recursive filter over ``table.grid`` plus the absent state (index ``n_cells``).

    ``person_speed_mps``: how fast the person may walk in any direction (the diffusion per step has an sd
    of ``person_speed_mps * dt`` per axis); ``leave_rate_hz``/``return_rate_hz``: how quickly present turns
    into absent and back; ``floor``: the share of belief spread uniformly at each step, so the filter can
    always recover from a wrong lock; ``likelihood_weight``: the exponent on each cycle's likelihood, < 1
    because successive cycles share the same multipath fading, which the product over cycles would count
    as independent evidence (0.3: the reported confidence then about matches the hit rate on simulated
    walks, ``benchmarks/rfid_coarse.py``).
    """

    table: LikelihoodTable
    person_speed_mps: float = 1.0
    leave_rate_hz: float = 0.05
    return_rate_hz: float = 0.5
    floor: float = 1e-3
    likelihood_weight: float = 0.3
    belief: FloatArray = field(init=False)
    _bearing_samples: FloatArray = field(init=False, repr=False)
    _range_samples: FloatArray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        b, r = self.table.grid.samples(per_side=3)
        self._bearing_samples = b.reshape(-1, b.shape[2])  # (cells, k), cell = s * R + r
        self._range_samples = r.reshape(-1, r.shape[2])
        self.reset()

    @property
    def grid(self) -> SectorGrid:
        return self.table.grid

    def reset(self) -> None:
        """Back to "anywhere, or absent": uniform over the cells, half the mass absent."""
        n = self.grid.n_cells
        self.belief = np.full(n + 1, 0.5 / n)
        self.belief[n] = 0.5

    # predict -------------------------------------------------------------------------------------------
    def predict(
        self, dt_s: float, forward_m: float = 0.0, left_m: float = 0.0, turn_rad: float = 0.0
    ) -> None:
        """Advance by ``dt_s``: the robot moved (``forward_m``, ``left_m``) in its previous frame and
        turned by ``turn_rad`` (CCW); the person walked anywhere at up to ``person_speed_mps``.

        Each cell's mass is carried by stratified points inside it, moved into the new robot frame
        p' = R(-turn) (p - t) and spread by six offsets of radius sqrt(2) sigma (sigma = speed dt, which
        gives that sd per axis), then binned: M(c | c') = share of c''s points landing in c."""
        if dt_s < 0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        grid = self.grid
        n = grid.n_cells
        x = self._range_samples * np.cos(self._bearing_samples) - forward_m  # (cells, k)
        y = self._range_samples * np.sin(self._bearing_samples) - left_m
        c, s = math.cos(turn_rad), math.sin(turn_rad)
        x, y = c * x + s * y, -s * x + c * y
        sigma = self.person_speed_mps * dt_s
        if sigma > 0:
            angles = np.arange(6) * (math.pi / 3.0)
            radius = math.sqrt(2.0) * sigma
            x = (x[:, :, None] + radius * np.cos(angles)).reshape(n, -1)
            y = (y[:, :, None] + radius * np.sin(angles)).reshape(n, -1)
        k = x.shape[1]
        sector = grid.sector_of(np.arctan2(y, x))
        rbin = grid.range_bin_of(np.hypot(x, y))
        dest = np.where(rbin >= grid.n_ranges, n, sector * grid.n_ranges + rbin)  # (cells, k)
        weights = np.repeat(self.belief[:n, None] / k, k, axis=1)
        moved = np.bincount(dest.ravel(), weights=weights.ravel(), minlength=n + 1)
        # Absent and present exchange mass; the absent return to the outermost ring.
        leave = 1.0 - math.exp(-self.leave_rate_hz * dt_s)
        back = 1.0 - math.exp(-self.return_rate_hz * dt_s)
        absent = self.belief[n]
        new: FloatArray = moved.astype(np.float64)  # new[n]: the mass that walked beyond the grid
        present = new[:n].sum()
        new[:n] *= 1.0 - leave
        new[n] += absent + leave * present - back * absent
        outer = np.arange(grid.n_sectors) * grid.n_ranges + (grid.n_ranges - 1)
        new[outer] += back * absent / grid.n_sectors
        new = (1.0 - self.floor) * new + self.floor / (n + 1)
        self.belief = new / new.sum()

    # update --------------------------------------------------------------------------------------------
    def log_likelihood(self, obs: Observation) -> FloatArray:
        """log P(obs | cell) for every cell and the absent state (length n_cells + 1)."""
        table = self.table
        if obs.detected.shape != (len(table.ports),):
            raise ValueError(f"observation has {obs.detected.shape[0]} ports, the table {len(table.ports)}")
        n = self.grid.n_cells
        p = table.p_detect.reshape(len(table.ports), n)
        mu = table.rssi_mean_dbm.reshape(len(table.ports), n)
        sd = table.rssi_sd_db.reshape(len(table.ports), n)
        out = np.zeros(n + 1)
        for a in range(len(table.ports)):
            if obs.detected[a]:
                out[:n] += np.log(p[a])
                out[n] += math.log(max(table.p_detect_absent, 1e-6))
                r = obs.rssi_dbm[a]
                if np.isfinite(r):
                    out[:n] += -0.5 * ((r - mu[a]) / sd[a]) ** 2 - np.log(sd[a] * _SQRT_2PI)
                    z = (r - table.absent_rssi_dbm) / table.absent_sd_db
                    out[n] += -0.5 * z * z - math.log(table.absent_sd_db * _SQRT_2PI)
            else:
                out[:n] += np.log1p(-p[a])
                out[n] += math.log1p(-table.p_detect_absent)
        return out

    def update(self, obs: Observation) -> None:
        """Bayes' rule with one cycle's observation."""
        log_post = np.log(np.maximum(self.belief, 1e-300)) + self.likelihood_weight * self.log_likelihood(obs)
        log_post -= log_post.max()
        post = np.exp(log_post)
        self.belief = post / post.sum()

    # answer --------------------------------------------------------------------------------------------
    def bearing_posterior(self) -> FloatArray:
        """P(sector | present), shape (n_sectors,)."""
        grid = self.grid
        m = self.belief[: grid.n_cells].reshape(grid.n_sectors, grid.n_ranges).sum(axis=1)
        total = m.sum()
        out: FloatArray = m / total if total > 0 else np.full(grid.n_sectors, 1.0 / grid.n_sectors)
        return out

    def estimate(self) -> CoarseEstimate:
        grid = self.grid
        n = grid.n_cells
        p_absent = float(self.belief[n])
        m = self.bearing_posterior()
        bearings = grid.bearings_rad
        best = int(np.argmax(m))
        # Refine inside the best sector: circular mean of it and its two neighbours.
        near = [(best + d) % grid.n_sectors for d in (-1, 0, 1)]
        z = np.sum(m[near] * np.exp(1j * bearings[near]))
        bearing = float(np.angle(z)) if abs(z) > 0 else float(bearings[best])
        resultant = abs(np.sum(m * np.exp(1j * bearings)))
        spread = math.sqrt(-2.0 * math.log(resultant)) if resultant > 1e-12 else math.pi
        confidence = (1.0 - p_absent) * float(m[near].sum())
        cells = self.belief[:n].reshape(grid.n_sectors, grid.n_ranges)
        ring = cells.sum(axis=0)
        range_m = float(ring @ grid.range_centres_m / ring.sum()) if ring.sum() > 0 else math.nan
        p_front = (1.0 - p_absent) * float(m[np.abs(bearings) < math.pi / 2].sum())
        return CoarseEstimate(bearing, min(spread, math.pi), range_m, confidence, p_absent, best, p_front)

    def within(self, centre_rad: float, half_width_rad: float) -> WindowEstimate:
        """The posterior inside bearings ``centre_rad`` +- ``half_width_rad`` (sectors whose centre is
        inside): for the fine layer, where in the camera's view to look, and how likely they are there."""
        grid = self.grid
        m = self.bearing_posterior() * (1.0 - float(self.belief[grid.n_cells]))
        offset = np.abs(np.remainder(grid.bearings_rad - centre_rad + np.pi, 2.0 * np.pi) - np.pi)
        inside = offset <= half_width_rad
        mass = float(m[inside].sum())
        z = np.sum(m[inside] * np.exp(1j * grid.bearings_rad[inside]))
        return WindowEstimate(mass, float(np.angle(z)) if mass > 0 else math.nan)


def fit_table(
    prior: LikelihoodTable,
    bearing_rad: FloatArray,
    range_m: FloatArray,
    detected: BoolArray,
    rssi_dbm: FloatArray,
    *,
    prior_weight: float = 4.0,
) -> tuple[LikelihoodTable, npt.NDArray[np.int64]]:
    """Calibrate a table from recorded cycles with known truth (``vlp-agent calibrate rfid``).

    Inputs are per cycle: the person's true bearing and range (N,), and per port whether the tag was read
    and its mean RSSI (N, A). Each cell's values are the data's, shrunk towards ``prior``'s by
    ``prior_weight`` pseudo-cycles (cells without data keep the prior):
    p = (reads + w p0) / (cycles + w), mu = (sum rssi + w mu0) / (k + w),
    sd^2 = (sum (rssi - mu)^2 + w sd0^2) / (k + w). Returns the table and the cycles per cell (S, R).
    """
    grid = prior.grid
    bearing_rad = np.asarray(bearing_rad, dtype=np.float64)
    range_m = np.asarray(range_m, dtype=np.float64)
    detected = np.asarray(detected, dtype=np.bool_)
    rssi_dbm = np.asarray(rssi_dbm, dtype=np.float64)
    n_ports = len(prior.ports)
    if bearing_rad.shape != range_m.shape or bearing_rad.ndim != 1:
        raise ValueError("bearing_rad and range_m must be equal 1-D arrays")
    if detected.shape != (bearing_rad.size, n_ports) or rssi_dbm.shape != detected.shape:
        raise ValueError(f"detected and rssi_dbm must have shape ({bearing_rad.size}, {n_ports})")
    sector = grid.sector_of(bearing_rad)
    rbin = grid.range_bin_of(range_m)
    inside = rbin < grid.n_ranges
    cell = (sector * grid.n_ranges + np.minimum(rbin, grid.n_ranges - 1))[inside]
    n = grid.n_cells
    cycles = np.bincount(cell, minlength=n).astype(np.float64)
    w = prior_weight
    p, mu, sd = [], [], []
    for a in range(n_ports):
        det = detected[inside, a]
        r = rssi_dbm[inside, a]
        has = det & np.isfinite(r)
        reads = np.bincount(cell, weights=det.astype(np.float64), minlength=n)
        k = np.bincount(cell[has], minlength=n).astype(np.float64)
        s1 = np.bincount(cell[has], weights=r[has], minlength=n)
        p0 = prior.p_detect[a].reshape(n)
        mu0 = prior.rssi_mean_dbm[a].reshape(n)
        sd0 = prior.rssi_sd_db[a].reshape(n)
        m = (s1 + w * mu0) / (k + w)
        s2 = np.bincount(cell[has], weights=(r[has] - m[cell[has]]) ** 2, minlength=n)
        p.append(((reads + w * p0) / (cycles + w)).reshape(grid.n_sectors, grid.n_ranges))
        mu.append(m.reshape(grid.n_sectors, grid.n_ranges))
        sd.append(np.sqrt((s2 + w * sd0**2) / (k + w)).reshape(grid.n_sectors, grid.n_ranges))
    outside = ~inside
    p_absent = prior.p_detect_absent
    if np.count_nonzero(outside) > 0:
        seen = detected[outside].mean()
        p_absent = float((seen * outside.sum() * n_ports + w * p_absent) / (outside.sum() * n_ports + w))
    table = LikelihoodTable(
        grid,
        prior.ports,
        np.clip(np.array(p), _P_MIN, _P_MAX),
        np.array(mu),
        np.maximum(np.array(sd), _SD_MIN_DB),
        min(max(p_absent, 1e-3), 0.5),
        prior.absent_rssi_dbm,
        prior.absent_sd_db,
        source="calibrated",
    )
    return table, cycles.reshape(grid.n_sectors, grid.n_ranges).astype(np.int64)
