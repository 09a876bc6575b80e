"""LED tracking across frames: CamShift-Kalman with the Bhattacharyya coefficient, and id voting.

Per track and frame (``reference/vlp.md`` §1.3, the group's "improved CamShift-Kalman"):

1. **Kalman predict**, constant velocity on the image centre: x = [u, v, du, dv], F = [[I, dt I], [0, I]],
   Q from white acceleration noise (sigma_a^2 [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]]).
2. **Back-projection inside the predicted window only.** The window's pixels are closed vertically (grey
   closing bridges the dark stripes, so the LED is a solid disk, whatever the stripe phase), their levels
   normalised between the track's background and the window's own brightest pixel (so the histograms do
   not drift as vignetting and distance change the LED's brightness), and looked up in the target histogram
   q (``cv2.LUT``: the histogram back-projection). **CamShift** (``cv2.CamShift``) moves the search window
   onto the LED. A window with nothing near the LED's level is covered.
3. **Bhattacharyya coefficient** rho = sum_u sqrt(p_u q_u) between the candidate's kernel-weighted
   (Epanechnikov) histogram p around the CamShift centre and q. rho < ``coast_rho``: covered: coast on the
   prediction. Otherwise the outline fit measures the centre. When the outline is the whole circle of the
   track's size, the centre is trusted (Kalman update, used for the pose); when it is cut (a cover across
   the rim) the centre is measured again with the known radius, the cover's edge dropping out of the robust
   fit, for a weaker Kalman update only. The LED is *fully visible* (its stripes decoded, its id voted)
   when, besides a whole outline, rho >= ``full_rho`` and its bridged area is that of a whole disk;
   otherwise it is *partial*: a cover along the rows leaves a whole outline but darkens rows, which would
   corrupt the stripes.
   A track whose id has not settled may carry the radius and histogram of a poor first look (an LED
   entering at the image edge): it is measured by a disk search in a wider window, any radius the map
   allows counts as whole, and a whole outline with a whole disk's area gives it its model afresh. Two
   tracks on one LED are merged.
4. **Voting.** Each fully visible frame adds its per-signature log-likelihoods (each clipped at
   -``vote_clip`` relative to the frame's best, so one bad frame counts for little) to the track's tally; the
   id settles by evidence over frames: when its posterior passes ``settle_posterior`` *and* the last
   ``settle_frames`` (2) decided frames each named it, and then changes only when another id does both in
   turn. One confident frame makes it only *provisional* (``provisional_index``), which the solver may use
   where the geometry can check it. The tally's spread is bounded so a real change is followed within a few
   frames.

Steady frames touch only the pixels of the tracks' windows.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt

from agent.vlp.decode import Classification
from agent.vlp.detect import (
    Blob,
    DetectorConfig,
    TrackedLed,
    close_rows,
    measure_blob,
    measure_tracked,
    measure_tracked_many,
)

FloatArray = npt.NDArray[np.float64]
ImageU8 = npt.NDArray[np.uint8]

__all__ = ["KalmanCV", "LedTrack", "LedTracker", "TrackerConfig", "bhattacharyya"]

FULL, PARTIAL, BORDER, OCCLUDED = "full", "partial", "border", "occluded"


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    """Units: image pixels and seconds. ``accel_sigma_pxps2`` is the Kalman white-acceleration noise;
    ``measurement_sigma_px`` the outline fit's centre noise (``partial_sigma_px`` for a partly covered LED).
    ``bins`` histogram bins over the normalised level [0, 1.25]. ``hist_adapt``: how fast q follows a fully
    visible LED (vignetting changes its level across the image), every ``adapt_every`` frames and only
    while rho >= ``adapt_rho``, so that a cover never becomes the model. ``min_area_ratio``,
    ``max_outline_rms_px``: a disk whose bridged area is below this share of pi R^2, or whose outline is
    not a circle, is partly covered whatever the histogram says. An id settles when the tally's posterior
    passes ``settle_posterior`` and the last ``settle_frames`` decided frames in a row each named it (one
    confident read, right or wrong, is not enough: it makes the id provisional only); a settled id is
    *confirmed* while the last ``confirm_frames`` decided frames named it (a frame naming another id
    withdraws that until it is named again)."""

    accel_sigma_pxps2: float = 3000.0
    initial_speed_sigma_pxps: float = 400.0
    measurement_sigma_px: float = 0.15
    partial_sigma_px: float = 1.0
    full_rho: float = 0.95
    coast_rho: float = 0.55
    adapt_rho: float = 0.985
    min_area_ratio: float = 0.6
    max_outline_rms_px: float = 0.6
    min_level_fraction: float = 0.3
    max_coast_frames: int = 10
    bins: int = 10
    hist_adapt: float = 0.1
    adapt_every: int = 4
    search_margin_px: float = 5.0
    match_distance_px: float = 8.0
    vote_clip: float = 12.0
    vote_span: float = 60.0
    settle_posterior: float = 0.999
    settle_frames: int = 2
    confirm_frames: int = 2


def bhattacharyya(p: FloatArray, q: FloatArray) -> float:
    """rho = sum_u sqrt(p_u q_u) of two normalised histograms (1: identical, 0: disjoint)."""
    return float(np.sqrt(p * q).sum())


class KalmanCV:
    """Constant-velocity Kalman filter on an image point.

    The u and v axes have the same model (F, Q, H, R are the same for both and decoupled), so their 2x2
    covariances [[P_pp, P_pv], [P_pv, P_vv]] (position, velocity) are equal and one is kept: the filter is
    the textbook one, computed per axis in plain floats (it runs for every LED of every frame).
    """

    def __init__(self, u: float, v: float, sigma_px: float, speed_sigma_pxps: float) -> None:
        self.u, self.v, self.du, self.dv = u, v, 0.0, 0.0
        self.p_pp, self.p_pv, self.p_vv = sigma_px**2, 0.0, speed_sigma_pxps**2

    def predict(self, dt_s: float, accel_sigma: float) -> None:
        # x = F x, F = [[1, dt], [0, 1]]; P = F P F^T + Q, Q = sigma_a^2 [[dt^4/4, dt^3/2], [dt^3/2, dt^2]].
        dt = max(dt_s, 0.0)
        q = accel_sigma * accel_sigma
        self.u += dt * self.du
        self.v += dt * self.dv
        pp, pv, vv = self.p_pp, self.p_pv, self.p_vv
        self.p_pp = pp + 2.0 * dt * pv + dt * dt * vv + q * dt**4 / 4.0
        self.p_pv = pv + dt * vv + q * dt**3 / 2.0
        self.p_vv = vv + q * dt * dt

    def update(self, z: tuple[float, float], sigma_px: float) -> None:
        # S = P_pp + R; K = [P_pp, P_pv] / S; x += K (z - u); P = (I - K H) P.
        s = self.p_pp + sigma_px * sigma_px
        k_p, k_v = self.p_pp / s, self.p_pv / s
        yu, yv = z[0] - self.u, z[1] - self.v
        self.u += k_p * yu
        self.v += k_p * yv
        self.du += k_v * yu
        self.dv += k_v * yv
        pp, pv, vv = self.p_pp, self.p_pv, self.p_vv
        self.p_pp = (1.0 - k_p) * pp
        self.p_pv = (1.0 - k_p) * pv
        self.p_vv = vv - k_v * pv

    @property
    def position(self) -> tuple[float, float]:
        return self.u, self.v

    @property
    def velocity(self) -> tuple[float, float]:
        return self.du, self.dv

    @property
    def position_sigma_px(self) -> float:
        return math.sqrt(max(self.p_pp, 0.0))


class LedTrack:
    """One LED followed over frames: its filter, size, level, target histogram, and id tally."""

    def __init__(
        self, track_id: int, blob: Blob, time_s: float, n_signatures: int, config: TrackerConfig
    ) -> None:
        self.track_id = track_id
        self.kf = KalmanCV(blob.centre_px[0], blob.centre_px[1], 1.0, config.initial_speed_sigma_pxps)
        self.radius_px = blob.radius_px
        self.level_dn = blob.peak_dn
        self.background_dn = blob.background_dn
        self.time_s = time_s
        self.age = 0
        self.missed = 0
        if blob.at_border:
            self.visibility = BORDER
        else:
            self.visibility = FULL if math.isfinite(blob.outline_rms_px) else PARTIAL
        # Whether this frame's centre can be used for the pose (a whole, clean outline).
        self.centre_ok = self.visibility == FULL
        self.rho = 1.0
        self.blob: Blob | None = blob
        self.q: FloatArray | None = None
        self.tally = np.zeros(n_signatures)
        self.votes = 0
        self.id_index: int | None = None
        # Consecutive decided frames, up to now, whose own best signature was the settled id.
        self.confirmations = 0
        # The id the last decided frames in a row named (their own best), and how many of them.
        self._streak: tuple[int, int] = (-1, 0)
        self.frame: Classification | None = None
        # The track's age at its last vote (its last decoded frame).
        self.voted_at = -1
        self._best_posterior: tuple[int, float] = (-1, 0.0)
        self._bins_key: tuple[int, int, int] | None = None
        self._bins = np.zeros(256, dtype=np.uint8)
        self._lut_for: tuple[FloatArray, npt.NDArray[np.uint8]] | None = None
        self._lut = np.zeros(256, dtype=np.uint8)

    def bins_lut(self, peak_dn: float, bins: int) -> npt.NDArray[np.uint8]:
        """Histogram bin of every grey level, normalised between this track's background and ``peak_dn``
        (the window's own brightest closed pixel, so vignetting and distance do not shift the histogram);
        kept while the peak stays within the same 6 DN step)."""
        key = (round(self.background_dn), round(peak_dn / 6.0), bins)
        if self._bins_key != key:
            self._bins_key = key
            self._bins = _normalised_bins(self.background_dn, peak_dn, bins)
        return self._bins

    def back_projection(
        self, q: FloatArray, bins_lut: npt.NDArray[np.uint8], led_bins: npt.NDArray[np.bool_]
    ) -> npt.NDArray[np.uint8] | None:
        """The back-projection table of q: every grey level's probability under q, the bins below 30 % of
        the LED level counting as background (0), scaled so that the most likely LED bin is 255. Kept while
        q and the bins do not change; None when q has no LED bin."""
        if self._lut_for is not None and self._lut_for[0] is q and self._lut_for[1] is bins_lut:
            return self._lut
        weights = np.where(led_bins, q, 0.0)
        top = float(weights.max())
        if top <= 0.0:
            return None
        self._lut = (weights * (255.0 / top)).astype(np.uint8)[bins_lut]
        self._lut_for = (q, bins_lut)
        return self._lut

    # -- identity ----------------------------------------------------------------------------------------
    def vote(self, classification: Classification, config: TrackerConfig) -> None:
        """Add one frame's evidence: its log-likelihoods relative to its best, each clipped at
        -``vote_clip``; the tally's spread is then bounded by ``vote_span``. The id settles (or changes) when
        one posterior reaches ``settle_posterior`` and the last ``settle_frames`` decided frames in a row
        each named that id (an undecided frame neither breaks nor extends the run)."""
        self.frame = classification
        self.voted_at = self.age
        # A handful of signatures: plain floats (a numpy call costs more than the arithmetic here).
        ll = classification.log_likelihood
        tally = self.tally.tolist()
        if len(ll) != len(tally) or not all(math.isfinite(v) for v in ll):
            return
        top_ll, clip, span = max(ll), -config.vote_clip, -config.vote_span
        added = [t + max(v - top_ll, clip) for t, v in zip(tally, ll, strict=True)]
        top = max(added)
        tally = [max(t - top, span) for t in added]
        self.tally = np.array(tally, dtype=np.float64)
        self.votes += 1
        best = tally.index(max(tally))
        # Posterior of the best: 1 / sum_k exp(tally_k - tally_best), the best's own tally being 0.
        self._best_posterior = (best, 1.0 / math.fsum(math.exp(t) for t in tally))
        said = ll.index(top_ll) if classification.id is not None else None
        if said is not None:
            run_id, run = self._streak
            self._streak = (said, run + 1 if said == run_id else 1)
        settled = self.id_index
        run_id, run = self._streak
        if (
            self._best_posterior[1] >= config.settle_posterior
            and run_id == best
            and run >= max(config.settle_frames, 1)
        ):
            self.id_index = best
        if self.id_index != settled:
            # Settled now by the run that named it: those frames confirm it.
            self.confirmations = run if self.id_index == run_id else 0
        elif said is not None and self.id_index is not None:
            # This frame's own verdict (its best signature) for or against the settled id.
            self.confirmations = self.confirmations + 1 if said == self.id_index else 0

    @property
    def posterior(self) -> FloatArray:
        if self.tally.size == 0:
            return self.tally
        e = np.exp(self.tally - self.tally.max())
        result: FloatArray = e / e.sum()
        return result

    def provisional_index(self, config: TrackerConfig) -> int | None:
        """The id to solve with: the settled one, else the tally's best once its posterior passes
        ``settle_posterior`` (one confident frame: not settled, so never confirmed; the pipeline flags a
        fix that leans on it unless three LEDs or more check it)."""
        if self.id_index is not None:
            return self.id_index
        best, posterior = self._best_posterior
        return best if best >= 0 and posterior >= config.settle_posterior else None

    def confirmed(self, config: TrackerConfig) -> bool:
        """The settled id was named by the last ``confirm_frames`` decided frames in a row."""
        return self.id_index is not None and self.confirmations >= config.confirm_frames

    @property
    def id_confidence(self) -> float:
        """Posterior probability of the settled id (0 before it settles)."""
        if self.id_index is None or self.tally.size == 0:
            return 0.0
        best, posterior = self._best_posterior
        return posterior if best == self.id_index else float(self.posterior[self.id_index])


def _normalised_bins(background: float, level: float, bins: int) -> npt.NDArray[np.uint8]:
    """Bin of every grey level: floor(bins * (g - bg) / (1.25 (level - bg))), clipped to [0, bins - 1]."""
    g = np.arange(256, dtype=np.float64)
    x = (g - background) / max(1.25 * (level - background), 1.0)
    return np.clip(np.floor(x * bins), 0, bins - 1).astype(np.uint8)


class _Found(NamedTuple):
    """What :meth:`LedTracker._find` found of a track this frame: its predicted centre, radius, rho and the
    two histograms (q, p), where to measure the outline (``box`` in the image, ``hint`` CamShift's centre)
    and, when the LED lies inside the tracking window, that window's closed pixels (else None)."""

    track: LedTrack
    predicted: tuple[float, float]
    radius: float
    rho: float
    q: FloatArray
    p: FloatArray
    box: tuple[int, int, int, int]
    hint: tuple[float, float]
    closed: ImageU8 | None


def _without_duplicates(tracks: list[LedTrack]) -> list[LedTrack]:
    """One track per LED. A track that coasted off its LED can be joined there by a new one (started by a
    full-frame search while the first was not held); when two end up on one LED, the one measured this frame,
    with a settled id, fully visible, older (the first started), is kept."""
    if len(tracks) < 2:
        return tracks
    drop: set[int] = set()
    for i, a in enumerate(tracks):
        for b in tracks[i + 1 :]:
            if id(a) in drop or id(b) in drop:
                continue
            if math.dist(a.kf.position, b.kf.position) >= max(a.radius_px, b.radius_px):
                continue
            worse = min((a, b), key=_track_rank)
            drop.add(id(worse))
    return [t for t in tracks if id(t) not in drop] if drop else tracks


def _track_rank(track: LedTrack) -> tuple[bool, bool, bool, int, int]:
    settled = track.id_index is not None
    return (track.missed == 0, settled, track.visibility == FULL, track.age, -track.track_id)


def _usable(blob: Blob | None) -> Blob | None:
    """A measured blob whose outline fit worked (a finite rms), else None."""
    if blob is None or not math.isfinite(blob.outline_rms_px):
        return None
    return blob


class LedTracker:
    """The set of LED tracks of one camera (not thread-safe; one per camera loop)."""

    def __init__(self, detector: DetectorConfig, config: TrackerConfig = TrackerConfig()) -> None:
        self.detector = detector
        self.config = config
        self.tracks: list[LedTrack] = []
        self._next_id = itertools.count(1)
        self._kernel = np.ones((detector.bridge, 1), dtype=np.uint8)
        self._kernels: dict[int, FloatArray] = {}
        # Bins of the normalised level that are LED, not background (>= 30 % of the LED's level).
        self._led_bins = np.arange(config.bins) >= math.ceil(0.3 / 1.25 * config.bins)
        # Background noise of the frames (DN), set from the full-frame searches.
        self.noise_dn = 1.5

    def reset(self) -> None:
        self.tracks = []

    # -- histograms --------------------------------------------------------------------------------------
    def _kernel_weights(self, radius: float) -> FloatArray:
        """Epanechnikov weights K = max(1 - (d / h)^2, 0), h = 1.25 R, on a (2H+1)^2 grid centred on a pixel
        (H = ceil(h)); kept per h in quarter pixels."""
        key = round(5.0 * radius)  # h = 1.25 R in quarter pixels
        k = self._kernels.get(key)
        if k is None:
            h = key / 4.0
            half = math.ceil(h)
            d = np.arange(-half, half + 1, dtype=np.float64)
            k = np.maximum(1.0 - (d[:, None] ** 2 + d[None, :] ** 2) / (h * h), 0.0)
            self._kernels[key] = k
        return k

    def _histogram(
        self, closed: ImageU8, centre: tuple[float, float], radius: float, bins_lut: npt.NDArray[np.uint8]
    ) -> FloatArray:
        """Epanechnikov-weighted histogram of the closed window around ``centre`` (window coordinates,
        rounded to the nearest pixel), normalised to sum 1."""
        k = self._kernel_weights(radius)
        half = k.shape[0] // 2
        rows, cols = closed.shape
        cu, cv_ = round(centre[0]), round(centre[1])
        r0, r1 = max(cv_ - half, 0), min(cv_ + half + 1, rows)
        c0, c1 = max(cu - half, 0), min(cu + half + 1, cols)
        if r1 <= r0 or c1 <= c0:
            return np.zeros(self.config.bins)
        weights = k[r0 - cv_ + half : r1 - cv_ + half, c0 - cu + half : c1 - cu + half]
        bins = cv2.LUT(closed[r0:r1, c0:c1], bins_lut)
        # With weights, bincount counts in float64; given uint8 bins it converts them itself, at twice the
        # cost of the explicit cast to intp.
        hist = np.asarray(
            np.bincount(bins.ravel().astype(np.intp), weights=weights.ravel(), minlength=self.config.bins),
            dtype=np.float64,
        )
        total = float(hist.sum())
        result: FloatArray = hist * (1.0 / total) if total > 0 else hist
        return result

    # -- one frame ---------------------------------------------------------------------------------------
    def step(self, image: ImageU8, time_s: float) -> None:
        """Predict every track, find it with CamShift in its window, tell full / partial / covered by the
        Bhattacharyya coefficient, and measure its centre. Drops tracks that left the image or stayed
        covered too long.

        The tracks are independent, so this runs in three passes over them: find each LED (CamShift and
        the histograms), measure the outlines of all LEDs found inside their windows together
        (:func:`measure_tracked_many`), then judge and update each track."""
        cfg = self.config
        height, width = image.shape
        found: list[_Found] = []
        for track in self.tracks:
            track.kf.predict(time_s - track.time_s, cfg.accel_sigma_pxps2)
            track.time_s = time_s
            track.age += 1
            located = self._find(image, track)
            if located is not None:
                found.append(located)
        # The outlines of the LEDs found inside their tracking windows, all at once; the others alone.
        requests: list[TrackedLed] = []
        slots: list[int] = []
        for k, f in enumerate(found):
            if f.closed is not None:
                requests.append((f.closed, f.hint, f.track.radius_px, f.track.background_dn))
                slots.append(k)
        first: list[Blob | None] = [None] * len(found)
        for k, blob in zip(slots, measure_tracked_many(image, requests, self.detector), strict=True):
            first[k] = _usable(blob)
        for k, f in enumerate(found):
            if f.closed is None:
                first[k] = self._measure(image, f.box, f.track, f.hint, None, None)
            self._conclude(image, f, first[k])
        kept: list[LedTrack] = []
        for track in self.tracks:
            u, v = track.kf.position
            inside = (
                -track.radius_px < u < width + track.radius_px
                and -track.radius_px < v < height + track.radius_px
            )
            if inside and track.missed <= cfg.max_coast_frames:
                kept.append(track)
        self.tracks = _without_duplicates(kept)

    def _find(self, image: ImageU8, track: LedTrack) -> _Found | None:
        """CamShift in the track's predicted window and the Bhattacharyya test of what it found: where to
        measure the outline, or None when the track coasts (covered, or nothing like the LED there)."""
        cfg = self.config
        height, width = image.shape
        u, v = track.kf.position
        r = track.radius_px
        # A track without a settled id may have its radius from a poor first look (an LED entering at the
        # image edge): its window leaves room for a disk larger than it thinks, or the outline is cut. Not
        # while it is at the border, where it is cut anyway and is not used.
        unsure = track.id_index is None and track.visibility != BORDER
        disk_r = 1.6 * r if unsure else r
        half = disk_r + cfg.search_margin_px + 3.0 * track.kf.position_sigma_px
        x0, y0 = max(int(u - half), 0), max(int(v - half), 0)
        x1, y1 = min(int(u + half) + 2, width), min(int(v + half) + 2, height)
        track.blob = None
        if x1 - x0 < 4 or y1 - y0 < 4:
            self._coast(track)
            return None
        window = image[y0:y1, x0:x1]
        closed = close_rows(window, self._kernel)
        peak = float(cv2.minMaxLoc(closed)[1])
        if peak - track.background_dn < cfg.min_level_fraction * (track.level_dn - track.background_dn):
            # Nothing near the LED's brightness in the window: covered (or gone).
            track.rho = 0.0
            self._coast(track)
            return None
        bins_lut = track.bins_lut(peak, cfg.bins)
        q = track.q if track.q is not None else self._histogram(closed, (u - x0, v - y0), r, bins_lut)
        lut = track.back_projection(q, bins_lut, self._led_bins)
        if lut is None:
            self._coast(track)
            return None
        prob = cv2.LUT(closed, lut)
        ww, wh = x1 - x0, y1 - y0
        sx = int(min(max(round(u - x0 - r), 0), ww - 2))
        sy = int(min(max(round(v - y0 - r), 0), wh - 2))
        sw = max(min(round(2 * r) + 1, ww - sx), 2)
        sh = max(min(round(2 * r) + 1, wh - sy), 2)
        if cv2.countNonZero(prob) == 0:
            self._coast(track)
            return None
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 10, 0.2)
        rotated, _ = cv2.CamShift(prob, (sx, sy, sw, sh), criteria)
        (cu, cv_), _, _ = rotated
        p = self._histogram(closed, (cu, cv_), r, bins_lut)
        rho = bhattacharyya(p, q)
        track.rho = rho
        if rho < cfg.coast_rho:
            self._coast(track)
            return None
        hint = (x0 + cu, y0 + cv_)
        if unsure:
            # Its radius may be off: measured by a search for the disk in the whole window, not in a window
            # of the radius it thinks (which would cut a larger disk's outline).
            return _Found(track, (u, v), r, rho, q, p, (x0, y0, x1, y1), hint, None)
        # The LED lies inside the window (on a side where the window ends at the image's edge, it is cut by
        # the image anyway, and a wider window would hold no more of it).
        reach = r + 2.0
        if (
            (cu - reach >= 0 or x0 == 0)
            and (cv_ - reach >= 0 or y0 == 0)
            and (cu + reach < ww or x1 == width)
            and (cv_ + reach < wh or y1 == height)
        ):
            return _Found(track, (u, v), r, rho, q, p, (x0, y0, x1, y1), hint, closed)
        # CamShift found the LED near the window's edge: measure it in a window around it instead.
        m = r + cfg.search_margin_px
        box = (int(hint[0] - m), int(hint[1] - m), int(hint[0] + m) + 2, int(hint[1] + m) + 2)
        return _Found(track, (u, v), r, rho, q, p, box, hint, None)

    def _conclude(self, image: ImageU8, found: _Found, blob: Blob | None) -> None:
        """Judge the outline measured at CamShift's centre and update the track.

        The outline decides whether the centre can be trusted: a clean circle of the track's size (a cover
        along the rows leaves whole chords, and the right circle). A cut outline is measured again with
        the known radius, the cover's edge dropping out of the robust fit."""
        cfg = self.config
        track, r, rho = found.track, found.radius, found.rho
        whole = blob is not None and self._whole(blob, r, settled=track.id_index is not None)
        if not whole:
            # Start from the prediction: CamShift's centroid of a half-covered disk is half a radius off.
            blob = self._measure(image, found.box, track, found.predicted, r, found.closed)
        if blob is None:
            self._coast(track)
            return
        track.blob = blob
        track.missed = 0
        track.centre_ok = whole and not blob.at_border
        # Fully visible (decoded, voting): the histogram and the bridged area agree with the whole LED too.
        full = whole and rho >= cfg.full_rho and blob.area_px >= cfg.min_area_ratio * math.pi * r * r
        if blob.at_border:
            track.visibility = BORDER
        else:
            track.visibility = FULL if full else PARTIAL
        track.kf.update(blob.centre_px, cfg.measurement_sigma_px if whole else cfg.partial_sigma_px)
        if whole:
            # The outline is the LED's whole circle: its size is right whatever the histogram says.
            track.radius_px += 0.3 * (blob.radius_px - r)
        if full:
            # Follow slow changes of brightness, and of the histogram (vignetting, distance).
            track.level_dn += 0.3 * (blob.peak_dn - track.level_dn)
            if rho >= cfg.adapt_rho and track.age % cfg.adapt_every == 0:
                track.q = (1.0 - cfg.hist_adapt) * found.q + cfg.hist_adapt * found.p
        elif (
            whole
            and track.id_index is None
            and not blob.at_border
            and blob.area_px >= cfg.min_area_ratio * math.pi * r * r
        ):
            # A new LED whose model q was taken from a poor first look (entering the image at its edge,
            # half in a stripe): the outline and the bridged area say it is whole now, so q is taken again
            # from what is there. Without this it never counts as fully visible, never adapts, and never
            # gets an id. Not once the id is settled: a cover must not become the model.
            track.q = found.p
            track.level_dn = blob.peak_dn
            track.radius_px = blob.radius_px

    def _whole(self, blob: Blob, radius: float, settled: bool = True) -> bool:
        """Is the measured outline the LED's whole circle? Its radius within 25 % of the track's (for a track
        whose id is not settled yet, within the map's range of LED sizes: its radius may come from a poor
        first look) and its edge points on it (rms within ``max_outline_rms_px``, none dropped as
        outliers)."""
        cfg = self.config
        if not math.isfinite(blob.outline_rms_px):
            return False
        if settled:
            if abs(blob.radius_px - radius) > max(0.25 * radius, 2.0):
                return False
        else:
            det = self.detector
            lo, hi = det.radius_range_px or (0.5 * det.min_diameter_px, 0.5 * det.max_diameter_px)
            if not 0.85 * lo <= blob.radius_px <= 1.15 * hi:
                return False
        return (
            blob.outline_rms_px <= max(cfg.max_outline_rms_px, 0.05 * radius) and blob.inlier_fraction >= 0.9
        )

    def _measure(
        self,
        image: ImageU8,
        box: tuple[int, int, int, int],
        track: LedTrack,
        hint: tuple[float, float],
        radius: float | None,
        closed: ImageU8 | None,
    ) -> Blob | None:
        """The LED's outline: in the closed window when the LED lies inside it (its place and size known,
        no component search), else by a full measurement around ``hint``."""
        if closed is not None:
            blob = measure_tracked(
                image, closed, hint, track.radius_px, track.background_dn, self.detector, radius_hint=radius
            )
        else:
            blob = measure_blob(
                image,
                box,
                track.background_dn,
                self.noise_dn,
                self.detector,
                radius_hint=radius,
                centre_hint=hint,
                radius_prior=track.radius_px,
            )
        return _usable(blob)

    def _target_model(self, image: ImageU8, track: LedTrack) -> FloatArray:
        """q: the kernel-weighted histogram of the closed pixels around the track's centre."""
        height, width = image.shape
        u, v = track.kf.position
        half = 1.25 * track.radius_px + 2.0
        x0, y0 = max(int(u - half), 0), max(int(v - half), 0)
        x1, y1 = min(int(u + half) + 2, width), min(int(v + half) + 2, height)
        closed = close_rows(image[y0:y1, x0:x1], self._kernel)
        peak = float(cv2.minMaxLoc(closed)[1])
        return self._histogram(
            closed, (u - x0, v - y0), track.radius_px, track.bins_lut(peak, self.config.bins)
        )

    def _coast(self, track: LedTrack) -> None:
        track.visibility = OCCLUDED
        track.centre_ok = False
        track.missed += 1
        track.blob = None

    # -- new LEDs -------------------------------------------------------------------------------------
    def add(self, image: ImageU8, blobs: list[Blob], time_s: float, n_signatures: int) -> list[LedTrack]:
        """Start tracks for blobs no existing track explains, each with its target histogram q from this
        frame; returns the new tracks."""
        new: list[LedTrack] = []
        for blob in blobs:
            taken = False
            for track in self.tracks:
                u, v = track.kf.position
                if math.dist((u, v), blob.centre_px) < max(self.config.match_distance_px, track.radius_px):
                    taken = True
                    break
            if taken:
                continue
            track = LedTrack(next(self._next_id), blob, time_s, n_signatures, self.config)
            track.kf.update(blob.centre_px, self.config.measurement_sigma_px)
            track.q = self._target_model(image, track)
            self.tracks.append(track)
            new.append(track)
        return new
