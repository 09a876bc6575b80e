"""The fine layer of person following: multi-feature mean shift (colour and LBP texture under a silhouette
kernel), with scale adaptation, occlusion detection, coasting and re-acquisition.

Seed paper (``rtm-assistance-robot-system.txt`` §3.3, eqs. 6-13), after Comaniciu, Ramesh and Meer,
"Kernel-based object tracking" (TPAMI 2003):

* The target model is a colour histogram ``q_u`` and a texture histogram ``q_v`` (riu2 LBP labels,
  ``agent.following.lbp``), each pixel counted with the kernel ``k_new = k(||(x - x0)/h||^2) * B(x)``: the
  Epanechnikov profile ``k(r) = 1 - r`` times a binary silhouette ``B`` (eq. 6; :class:`Silhouette`).
* The candidate at ``y`` has histograms ``p_u(y)``, ``p_v(y)`` the same way (eqs. 7, 9), and the similarity
  is the product of the Bhattacharyya coefficients ``rho = rho_c * rho_t`` with
  ``rho_c = sum_u sqrt(p_u q_u)`` (eq. 10).
* A mean-shift step moves ``y`` to the weighted mean of the pixels under the kernel (eq. 13; the
  Epanechnikov profile's ``g = -k'`` is constant on its support) with the weights of eq. 12, the gradient of
  the product: ``w_i = rho_t * sqrt(q_u / p_u(y0))[u_i] + rho_c * sqrt(q_v / p_v(y0))[v_i]``. The colour-only
  baseline (:attr:`Features.COLOUR`) is the same code with ``rho = rho_c`` and ``w_i = sqrt(q_u/p_u)[u_i]``.

Additions, each a standard one:

* Background-weighted target model (Ning, Zhang, Zhang, Wu, "Robust mean-shift tracking with corrected
  background-weighted histogram", IET CV 2012): the target model's bins are scaled by
  ``min(o* / o_u, 1)``, ``o`` the histogram of a ring around the target, ``o*`` its smallest non-zero bin,
  so colours the surroundings share count less.
* Scale: after convergence, ``rho`` at +-``scale_step`` of the size; the best one pulls the size by
  ``scale_gain`` (Comaniciu's "plus or minus 10 %" test with his gamma).
* Motion: a constant-velocity prediction starts the search each frame.
* Occlusion: ``rho`` below ``occlusion_ratio`` times its running level (``rho_ref``, averaged while
  tracking) marks the target occluded; the box then coasts on the constant-velocity prediction and the
  model is frozen. Each occluded frame searches a grid around the prediction that widens with the time
  lost, plus any boxes the caller hints (the coarse layer's band, the head-shoulder pre-locator); the
  best start climbs by mean shift and is accepted when its ``rho`` is back over ``reacquire_ratio`` times
  ``rho_ref``.
* Model update: ``q <- (1 - update_rate) q + update_rate p(y)`` only when ``rho`` is at least
  ``update_ratio`` times ``rho_ref``: slow, and never on an occluder.
* Feature weights (``rho = rho_c^a * rho_t^b``) and feature selection (``texture_weighting=select``, the
  default): texture's exponent is exactly 0, and the full tracker computes exactly what the colour-only
  one does, unless texture measurably tells the target from a look-alike where colour does not.

Images are BGR ``uint8`` (H, W, 3), as OpenCV reads them; boxes are ``(x, y, w, h)`` floats, top-left
corner and size in pixels, 0-based. Only a window around the target is quantised and LBP-labelled each
frame, and a large box's window is first shrunk (``cv2.resize``, area averaging) so that the kernel holds
about ``max_pixels`` cells: the cost per frame grows neither with the image nor with the person, and the
texture is measured at a scale relative to the person.
"""

from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from agent.following.lbp import RIU2_LABELS, RIU2_LUT, U2_LABELS, U2_LUT, lbp_codes
from agent.following.scale import ScaleFilter, ScaleFilterConfig
from agent.following.translation import TranslationFilter, TranslationFilterConfig

__all__ = [
    "ColourSpace",
    "Features",
    "MeanShiftTracker",
    "ScaleSearch",
    "Silhouette",
    "TextureWeighting",
    "TrackResult",
    "TrackState",
    "TrackerConfig",
]

log = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]
ImageU8 = npt.NDArray[np.uint8]


class Features(enum.StrEnum):
    FULL = "full"  # colour and texture, rho = rho_colour * rho_texture
    COLOUR = "colour"  # colour only (the baseline)


class Silhouette(enum.StrEnum):
    """The binary silhouette ``B`` of eq. 6, in the box's normalised coordinates (u, v) in [-1, 1]^2,
    v down. Always intersected with the kernel's ellipse u^2 + v^2 < 1."""

    ELLIPSE = "ellipse"  # the whole ellipse inscribed in the box
    BODY = "body"  # a standing person: a head on top, shoulders below it, the ellipse's corners cut
    OMEGA = "omega"  # a head-shoulder box (the pre-locator's): the Omega of a head over two shoulders


class LbpMapping(enum.StrEnum):
    RIU2 = "riu2"  # rotation-invariant uniform: 10 labels
    U2 = "u2"  # uniform: 59 labels, edge orientation kept


class ColourSpace(enum.StrEnum):
    BGR = "bgr"  # levels^3 bins of B, G, R
    # Hue x saturation (levels^2 bins), plus two bins, dark and light, for the pixels whose hue means
    # nothing (saturation under a quarter, or value under 50): a change of the light's gain moves B, G
    # and R across bin edges together but leaves hue and saturation where they were.
    HSV = "hsv"


class TextureWeighting(enum.StrEnum):
    """What the texture's exponent ``b`` in ``rho = rho_c^a * rho_t^b`` is measured against
    (``adaptive_weights``)."""

    # The ring around the target at each model update: each feature's distance from the surroundings.
    RING = "ring"
    # The distractors: the neighbouring regions whose colour alone the tracker would take for the
    # target. With one, each feature counts by how well it tells the target from it (at least
    # min_feature_weight); with none, the weights relax to the ring's, texture unfloored.
    DISTRACTOR = "distractor"
    # Feature selection: texture's exponent is exactly 0 (the tracker then computes what colour-only
    # does) unless texture measurably tells the target from a distractor found as above (its texture
    # match under the target's own running match by select_on noise levels; off again under
    # select_off), or tells the target from its ring better than colour does.
    SELECT = "select"


class ScaleSearch(enum.StrEnum):
    """How the box's size follows the target (the same for both feature sets)."""

    # Comaniciu's +-scale_step test at the converged centre, scored by the contrast with a ring, the
    # winner pulling the size by scale_gain: a walk of 1 % steps.
    CONTRAST = "contrast"
    # A discriminative scale-space filter (DSST's, agent.following.scale) over scale_rungs sizes
    # scale_ladder_step apart at the converged centre, learnt online on confident frames: the size jumps
    # to the best rung.
    LADDER = "ladder"


class Translation(enum.StrEnum):
    """What DSST's translation filter (agent.following.translation: learnt at the start box, then at the
    body it finds each tracking frame) does beside the mean shift, which stays the tracker."""

    NONE = "none"  # not run
    # It finds the body's offset from the converged mean-shift centre; the scale filter's ladder is read
    # and learnt there (scale_search=ladder only).
    PLACE = "place"
    # The same, and the reported box is centred there too (the mean shift climbs on from its own centre).
    REFINE = "refine"


class TrackState(enum.StrEnum):
    TRACKING = "tracking"
    OCCLUDED = "occluded"  # rho too low: coasting on the motion model, searching each frame


@dataclass(frozen=True)
class TrackerConfig:
    features: Features = Features.FULL
    silhouette: Silhouette = Silhouette.ELLIPSE
    colour_levels: int = 8  # per B, G, R channel: levels^3 colour bins
    colour_space: ColourSpace = ColourSpace.BGR
    lbp_threshold: int = 3  # grey levels (lbp.py: keeps flat cloth flat)
    lbp_mapping: LbpMapping = LbpMapping.RIU2
    background_weighting: bool = True
    background_every: int = 1  # model updates between looks at the background ring (1: every update)
    adaptive_weights: bool = True  # rho = rho_c^a * rho_t^b, a and b from how each feature stands out
    min_feature_weight: float = 0.5  # floor of a and b (of a only with texture_weighting=distractor)
    texture_weighting: TextureWeighting = TextureWeighting.SELECT
    # distractor weighting: a neighbour (the box moved by distractor_offset box sizes, 8 directions) is a
    # distractor when its rho_colour is at least distractor_ratio times the target's; with none, a and b
    # relax toward the ring's by distractor_forget per confident tracking frame.
    distractor_offset: float = 1.0
    distractor_ratio: float = 0.75
    distractor_forget: float = 0.05
    # ... and the box moved by distractor_near box sizes (overlapping the target) is one when its
    # rho_colour is at least distractor_near_ratio times the target's: with 1, colour has no peak at the
    # converged box (it does not localise the target: a large, evenly coloured person near the camera);
    # distractor_near = 0 turns this off.
    distractor_near: float = 0.5
    distractor_near_ratio: float = 1.0
    # texture_weighting=select: texture switches on when a distractor's texture match lies select_on
    # noise levels under the target's running match (the noise: the running deviation of the target's
    # own match, at least the sampling mismatch of the kernel's histogram), and stays on while it lies
    # select_off under; the running match needs select_samples confident frames first.
    select_on: float = 3.0
    select_off: float = 1.5
    select_samples: int = 5
    max_iterations: int = 12
    epsilon_px: float = 0.5  # converged when a step is shorter
    max_pixels: int = 2500  # kernel samples per evaluation; bigger boxes are sampled on a grid
    scale_step: float = 0.1
    scale_gain: float = 0.1
    scale_ring: float = 1.2  # the scale test's ring reaches this many times the size
    scale_search: ScaleSearch = ScaleSearch.CONTRAST
    # scale_search=ladder: the ladder's rungs (odd), their ratio, the filter's learning rate, the
    # template's area (agent.following.scale.ScaleFilterConfig).
    scale_rungs: int = 17
    scale_ladder_step: float = 1.04
    scale_learning_rate: float = 0.025
    scale_sigma_factor: float = 0.25
    scale_template_area: int = 512
    translation: Translation = Translation.NONE
    # translation != none: the translation filter's template area for the target's part, pixels
    # (agent.following.translation.TranslationFilterConfig; its other values are DSST's).
    translation_template_area: int = 1024
    # translation != none: the filter's offset is taken (and the filter learnt) only on frames whose
    # response peak is at least this many times its running level (rho_ref_rate); else the last offset
    # is held (0: always taken).
    translation_confidence: float = 0.0
    min_scale: float = 0.5  # of the starting size
    max_scale: float = 2.0
    velocity_gain: float = 0.5  # v <- gain * (y1 - y0) + (1 - gain) * v
    # The velocity a hidden target coasts on: the same average, slower (0: the one above). One frame's
    # prediction wants the latest motion; many frames' want the steady one, not the last few steps' noise.
    coast_velocity_gain: float = 0.1
    climb_from_last: bool = True  # also climb from the last position, not only from the prediction
    occlusion_ratio: float = 0.6
    reacquire_ratio: float = 0.75
    update_ratio: float = 0.9
    update_rate: float = 0.02
    rho_ref_rate: float = 0.05
    search_start: float = 1.0  # box sizes: the search radius on the first occluded frame
    search_growth: float = 0.15  # search radius grows by this many box sizes per occluded frame
    search_max: float = 2.0  # box sizes
    motion_prior: float = 1.0  # box sizes: sigma of the motion prior that ranks re-acquisition starts

    def __post_init__(self) -> None:
        if not 2 <= self.colour_levels <= 32:
            raise ValueError("colour_levels must be 2..32")
        if not (
            self.distractor_offset > 0.0
            and self.distractor_ratio > 0.0
            and 0.0 <= self.distractor_forget <= 1.0
            and self.distractor_near >= 0.0
            and self.distractor_near_ratio > 0.0
        ):
            raise ValueError(
                "need distractor_offset > 0, distractor_ratio > 0, 0 <= distractor_forget <= 1, "
                "distractor_near >= 0, distractor_near_ratio > 0"
            )
        # The filters' own checks, at construction rather than at the first frame.
        self.scale_filter_config()
        self.translation_filter_config()
        if self.translation_confidence < 0.0:
            raise ValueError("translation_confidence must be at least 0")
        if self.translation == Translation.PLACE and self.scale_search != ScaleSearch.LADDER:
            raise ValueError("translation=place places the scale ladder: it needs scale_search=ladder")
        if not (0.0 <= self.select_off <= self.select_on and self.select_samples >= 1):
            raise ValueError("need 0 <= select_off <= select_on and select_samples >= 1")
        if self.background_every < 1:
            raise ValueError("background_every must be at least 1")
        if not 0.0 < self.occlusion_ratio <= self.reacquire_ratio <= 1.0:
            raise ValueError("need 0 < occlusion_ratio <= reacquire_ratio <= 1")

    def scale_filter_config(self) -> ScaleFilterConfig:
        """The ladder's configuration (``scale_search=ladder``)."""
        return ScaleFilterConfig(
            scales=self.scale_rungs,
            step=self.scale_ladder_step,
            learning_rate=self.scale_learning_rate,
            sigma_factor=self.scale_sigma_factor,
            max_area=self.scale_template_area,
        )

    def translation_filter_config(self) -> TranslationFilterConfig:
        """The translation filter's configuration (``translation`` != none)."""
        return TranslationFilterConfig(max_area=self.translation_template_area)


@dataclass(frozen=True)
class TrackResult:
    box: FloatArray  # (4,) x, y, w, h
    state: TrackState
    rho: float
    rho_colour: float
    rho_texture: float  # 1.0 for the colour-only tracker
    iterations: int
    frames_lost: int = 0


@dataclass
class _Window:
    """The feature images of one frame's window: colour bin and LBP label per cell, where the window sits
    in the frame, and its cell size: ``factor`` x ``factor`` frame pixels averaged into one (large boxes
    are tracked on a coarser grid, their LBP at a scale relative to the person)."""

    x0: int
    y0: int
    colour: npt.NDArray[np.int32]
    texture: ImageU8 | None
    factor: int = 1

    @property
    def shape(self) -> tuple[int, int]:
        return (self.colour.shape[0], self.colour.shape[1])

    @property
    def end(self) -> tuple[int, int]:
        """The frame pixel (x, y) just past the window's last cell."""
        return (self.x0 + self.shape[1] * self.factor, self.y0 + self.shape[0] * self.factor)

    def cells(self, xs: IntArray, ys: IntArray) -> tuple[IntArray, IntArray, npt.NDArray[np.bool_]]:
        """Frame pixels -> (rows, cols) of the cells holding them, and which lie inside the window."""
        cols = (xs - self.x0) // self.factor
        rows = (ys - self.y0) // self.factor
        h, w = self.shape
        valid = (xs >= self.x0) & (ys >= self.y0) & (cols < w) & (rows < h)
        return rows, cols, valid


@dataclass(frozen=True)
class _Kernel:
    dx: IntArray  # sample offsets from the centre pixel
    dy: IntArray
    k: FloatArray  # k_new = (1 - r^2) * B at each sample
    step: int  # sampling step in pixels


@dataclass(frozen=True)
class _Evaluation:
    rho: float
    rho_colour: float
    rho_texture: float
    p_colour: FloatArray
    p_texture: FloatArray | None
    weights: FloatArray  # eq. 12 per valid sample
    x: FloatArray  # frame coordinates of the valid samples
    y: FloatArray


def _silhouette(kind: Silhouette, u: FloatArray, v: FloatArray) -> npt.NDArray[np.bool_]:
    inside = u * u + v * v < 1.0
    if kind == Silhouette.ELLIPSE:
        return inside
    if kind == Silhouette.BODY:
        # Head: a disc in the top fifth, a third of the box wide; below it the ellipse (shoulders down).
        head = (u / 0.3) ** 2 + ((v + 0.75) / 0.25) ** 2 < 1.0
        return inside & ((v > -0.55) | head)
    # OMEGA: head disc in the upper half, the shoulders a half-ellipse across the lower half.
    head = (u / 0.45) ** 2 + ((v + 0.45) / 0.55) ** 2 < 1.0
    shoulders = (v > 0.0) & (u * u + (v - 1.0) ** 2 < 1.0)
    return inside & (head | shoulders)


class MeanShiftTracker:
    """One target. :meth:`start` with a box on a frame, then :meth:`update` with each next frame."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self._levels = self.config.colour_levels
        self._bins = self._levels**3
        self._texture = self.config.features == Features.FULL
        self._select = (
            self._texture
            and self.config.adaptive_weights
            and self.config.texture_weighting == TextureWeighting.SELECT
        )
        self._distractor_weighting = (
            self._texture
            and self.config.adaptive_weights
            and self.config.texture_weighting in (TextureWeighting.DISTRACTOR, TextureWeighting.SELECT)
        )
        riu2 = self.config.lbp_mapping == LbpMapping.RIU2
        self._lut = RIU2_LUT if riu2 else U2_LUT
        self._labels = RIU2_LABELS if riu2 else U2_LABELS
        self._kernels: dict[tuple[int, int, int], _Kernel] = {}
        self._centre = np.zeros(2)
        self._size = np.ones(2)
        self._size0 = np.ones(2)
        self._velocity = np.zeros(2)
        self._coast_velocity = np.zeros(2)
        self._q_colour_raw = np.zeros(self._bins)
        self._q_texture_raw = np.zeros(self._labels)
        self._q_colour = np.zeros(self._bins)
        self._q_texture = np.zeros(self._labels)
        self._rho_ref = 1.0
        self._exponents = (1.0, 1.0)  # a, b in rho = rho_c^a * rho_t^b
        self._ring_exponents = (1.0, 0.0)  # distractor weighting: the exponents with no distractor near
        # Feature selection (texture_weighting=select): the target's own colour and texture matches on
        # confident tracking frames: running means and mean square deviations, and their count.
        self._feature_match: tuple[float, float, float, float, int] = (1.0, 0.0, 1.0, 0.0, 0)
        self._texture_on = False
        self._colour_factor = np.ones(self._bins)  # the background weighting of the colour bins
        self._updates = 0
        self._ladder: ScaleFilter | None = None
        if self.config.scale_search == ScaleSearch.LADDER:
            self._ladder = ScaleFilter(self.config.scale_filter_config())
        self._translation: TranslationFilter | None = None
        self._offset = np.zeros(2)  # the translation filter's body from the mean-shift centre (x, y)
        self._peak_ref: float | None = None  # the translation filter's running peak level
        self.state = TrackState.TRACKING
        self.frames_lost = 0
        self._started = False

    # -- public -----------------------------------------------------------------------------------------

    @property
    def box(self) -> FloatArray:
        centre = self._centre
        if self.config.translation == Translation.REFINE:
            centre = centre + self._offset
        return np.concatenate([centre - self._size / 2.0, self._size])

    @property
    def feature_weights(self) -> tuple[float, float]:
        """The exponents (a, b) of ``rho = rho_c^a * rho_t^b`` now ((1, 1) for the colour-only tracker:
        it has no texture term)."""
        return self._exponents

    def start(self, frame: ImageU8, box: FloatArray | tuple[float, float, float, float]) -> None:
        """Build the target model from ``box`` (x, y, w, h) on ``frame``."""
        frame = _check_frame(frame)
        x, y, w, h = (float(b) for b in box)
        if not (w >= 2.0 and h >= 2.0):
            raise ValueError(f"box {box} is smaller than 2 x 2 pixels")
        self._size = np.array([w, h])
        self._size0 = self._size.copy()
        self._centre = np.array([x + w / 2.0, y + h / 2.0])
        self._velocity = np.zeros(2)
        self._coast_velocity = np.zeros(2)
        window = self._window(frame, self._centre, self._size * 2.0 + 8.0)
        ev = self._evaluate(window, self._centre, self._size, model=False)
        self._q_colour_raw = ev.p_colour
        self._q_texture_raw = ev.p_texture if ev.p_texture is not None else np.zeros(self._labels)
        self._background(window)
        if self.config.scale_search == ScaleSearch.LADDER:
            # Learnt from the first tracking frame on (``_accept``), not here: see there.
            self._ladder = ScaleFilter(self.config.scale_filter_config())
        self._offset = np.zeros(2)
        self._peak_ref = None
        self._translation = None
        if self.config.translation != Translation.NONE:
            # Learnt at the start box: the target as given, not the colour model's mode.
            self._translation = TranslationFilter(self.config.translation_filter_config())
            self._translation.start(frame, self._centre, self._size)
        self._feature_match = (1.0, 0.0, 1.0, 0.0, 0)
        self._texture_on = False
        if self._select:
            self._ring_exponents = (1.0, 0.0)
        if self._distractor_weighting:
            self._exponents = self._ring_exponents
        self._rho_ref = 1.0
        ev = self._evaluate(window, self._centre, self._size)
        self._rho_ref = max(ev.rho, 1e-3)
        self._weigh_distractors(window, self._centre, ev)
        self.state = TrackState.TRACKING
        self.frames_lost = 0
        self._started = True

    def correct(self, box: FloatArray | tuple[float, float, float, float], gain: float = 0.5) -> None:
        """Pull the box toward ``box`` (a pre-locator's detection of the target) by ``gain``, centre and
        size (within the scale limits): the scale test follows a target that comes nearer or goes
        farther only slowly."""
        cfg = self.config
        x, y, w, h = (float(b) for b in box)
        centre = np.array([x + w / 2.0, y + h / 2.0])
        if cfg.translation == Translation.REFINE:
            centre = centre - self._offset  # the reported box is the mean shift's plus the offset
        self._centre = self._centre + gain * (centre - self._centre)
        size = self._size + gain * (np.array([w, h]) - self._size)
        self._size = np.clip(size, cfg.min_scale * self._size0, cfg.max_scale * self._size0)

    def rescale(self, factor: float, centre: FloatArray | None = None) -> None:
        """Multiply the size by ``factor`` (within the scale limits), keeping the aspect; and move the
        mean shift's centre to ``centre`` if given (the reported box's centre, as :meth:`correct`): a
        detector's anchor on the size (``agent.following.anchor``)."""
        cfg = self.config
        if not (math.isfinite(factor) and factor > 0.0):
            raise ValueError(f"scale factor must be finite and > 0, got {factor}")
        if centre is not None:
            target = np.asarray(centre, dtype=np.float64)
            if cfg.translation == Translation.REFINE:
                target = target - self._offset
            self._centre = target.copy()
        size = self._size * factor
        self._size = np.clip(size, cfg.min_scale * self._size0, cfg.max_scale * self._size0)

    def update(self, frame: ImageU8, hints: tuple[FloatArray, ...] | list[FloatArray] = ()) -> TrackResult:
        """Track into ``frame``. ``hints``: candidate boxes (x, y, w, h) from elsewhere (the pre-locator,
        the coarse layer's bearing band) tried as re-acquisition starts while the target is occluded."""
        if not self._started:
            raise RuntimeError("MeanShiftTracker.update before start")
        frame = _check_frame(frame)
        cfg = self.config
        predicted = self._centre + self._velocity
        if self.state is TrackState.OCCLUDED:
            # A hidden person coasts sideways only: people walk on the floor, so their image moves
            # mostly across; its vertical motion (the camera's shake, a step's bob) does not go on.
            coast = self._coast_velocity if cfg.coast_velocity_gain > 0.0 else self._velocity
            predicted = self._centre + np.array([coast[0], 0.0])
        if self.state is TrackState.TRACKING:
            window = self._window(frame, predicted, self._size * 2.0 + 2.0 * np.abs(self._velocity) + 8.0)
            centre, ev, iterations = self._climb(window, predicted, self._size)
            if cfg.climb_from_last and float(np.hypot(*self._velocity)) > cfg.epsilon_px:
                # The motion model can be wrong (a camera shaken by hand, a turn): climb from where the
                # target was too and keep the better match.
                centre2, ev2, iterations2 = self._climb(window, self._centre, self._size)
                if ev2.rho > ev.rho:
                    centre, ev, iterations = centre2, ev2, iterations + iterations2
            if ev.rho >= cfg.occlusion_ratio * self._rho_ref:
                self._accept(frame, window, centre, ev)
                return self._result(ev, iterations)
            log.debug("rho %.3f under %.3f: occluded", ev.rho, cfg.occlusion_ratio * self._rho_ref)
            self.state = TrackState.OCCLUDED
            self.frames_lost = 0
        return self._search(frame, predicted, hints)

    # -- one frame ------------------------------------------------------------------------------------

    def _accept(self, frame: ImageU8, window: _Window, centre: FloatArray, ev: _Evaluation) -> None:
        cfg = self.config
        body = centre
        trusted = False
        if self._translation is not None:
            # Where the target as learnt sits in the window around the converged centre; an unsure
            # answer (a peak well under its running level: something else overlaps the target) is not
            # taken, the last offset is held.
            offset, peak = self._translation.estimate(frame, centre, self._size)
            if self._peak_ref is None:
                self._peak_ref = peak
            if cfg.translation_confidence <= 0.0 or peak >= cfg.translation_confidence * self._peak_ref:
                trusted = True
                self._offset = offset
                self._peak_ref += cfg.rho_ref_rate * (peak - self._peak_ref)
            body = centre + self._offset
        ladder_centre = body if cfg.translation != Translation.NONE else centre
        if self._ladder is None:
            self._scale(window, centre, ev)
        elif not self._ladder.started:
            # The ladder learns its first look at the mean shift's converged centre, not at the box the
            # tracker was started with: the colour model's mode is not the box's centre (on OTB Woman it
            # sits 10-17 px above it from the second frame on), and a ladder learnt at one centre and
            # read at another takes the offset for a change of scale (measured: Woman's box grew from 95
            # to 117 px in 22 frames, the truth's 95-96).
            self._ladder.start(frame, ladder_centre, self._size)
        else:
            factor, _ = self._ladder.estimate(frame, ladder_centre, self._size)
            size = self._size * factor
            self._size = np.clip(size, cfg.min_scale * self._size0, cfg.max_scale * self._size0)
        step = centre - self._centre
        self._velocity = cfg.velocity_gain * step + (1.0 - cfg.velocity_gain) * self._velocity
        g = cfg.coast_velocity_gain
        self._coast_velocity = g * step + (1.0 - g) * self._coast_velocity
        self._centre = centre
        if ev.rho >= cfg.update_ratio * self._rho_ref:
            # q <- (1 - a) q + a p(y): slow, and only on a confident match; p(y) at the new size.
            a = cfg.update_rate
            cur = self._evaluate(window, centre, self._size, model=False)
            self._q_colour_raw = (1.0 - a) * self._q_colour_raw + a * cur.p_colour
            if cur.p_texture is not None:
                self._q_texture_raw = (1.0 - a) * self._q_texture_raw + a * cur.p_texture
            self._updates += 1
            if self._ladder is not None:
                # The scale filter learns where the colour model does: on confident frames only.
                self._ladder.learn(frame, ladder_centre, self._size)
            if self._translation is not None and trusted:
                # At the body it found: this frame's patch, the desired peak moved to the offset.
                self._translation.learn_last(self._offset)
            if self._updates % cfg.background_every == 0:
                self._background(window)
            else:
                self._reweight()
        self._rho_ref += cfg.rho_ref_rate * (ev.rho - self._rho_ref)
        self._weigh_distractors(window, centre, ev)

    def _search(
        self, frame: ImageU8, predicted: FloatArray, hints: tuple[FloatArray, ...] | list[FloatArray]
    ) -> TrackResult:
        """An occluded frame: coast on the motion model; climb from the best starts of a widening grid
        around the prediction and from the hints; accept the best if its rho is back."""
        cfg = self.config
        self.frames_lost += 1
        size = self._size
        radius = min(cfg.search_max, cfg.search_start + cfg.search_growth * self.frames_lost) * size
        window = self._window(frame, predicted, size + 2.0 * radius + 4.0)
        starts = [predicted]
        nx = max(1, math.ceil(radius[0] / (0.5 * size[0])))
        ny = max(1, math.ceil(radius[1] / (0.5 * size[1])))
        for gy in range(-ny, ny + 1):
            for gx in range(-nx, nx + 1):
                if gx or gy:
                    starts.append(predicted + np.array([gx * radius[0] / nx, gy * radius[1] / ny]))
        sizes = [size] * len(starts)
        for hint in hints:
            hx, hy, hw, hh = (float(b) for b in hint)
            starts.append(np.array([hx + hw / 2.0, hy + hh / 2.0]))
            # A hint (the pre-locator's box) is tried at its own size, within the tracker's scale limits:
            # the target may have come nearer or gone farther while it was hidden (or while the scale
            # test lagged behind it).
            sizes.append(
                np.clip(np.array([hw, hh]), cfg.min_scale * self._size0, cfg.max_scale * self._size0)
            )
        if hints:
            window = self._window_union(
                frame, window, [s for s in starts[-len(hints) :]], np.max(sizes, axis=0)
            )
        sigma = cfg.motion_prior * float(np.max(size)) * (1.0 + 0.1 * self.frames_lost)

        def prior(c: FloatArray) -> float:
            return math.exp(-0.5 * float(np.sum((c - predicted) ** 2)) / sigma**2)

        scored = sorted(
            (
                (self._evaluate(window, s, z).rho * prior(s), i)
                for i, (s, z) in enumerate(zip(starts, sizes, strict=True))
            ),
            reverse=True,
        )
        best: tuple[float, FloatArray, _Evaluation, int, FloatArray] | None = None
        for _, i in scored[:3]:
            centre, ev, iterations = self._climb(window, starts[i], sizes[i])
            score = ev.rho * prior(centre)
            if best is None or score > best[0]:
                best = (score, centre, ev, iterations, sizes[i])
        assert best is not None
        _, centre, ev, iterations, found_size = best
        if ev.rho >= cfg.reacquire_ratio * self._rho_ref:
            log.debug("re-acquired after %d frames, rho %.3f", self.frames_lost, ev.rho)
            self.state = TrackState.TRACKING
            self._centre = centre
            self._size = found_size.copy()
            self.frames_lost = 0
            return self._result(ev, iterations)
        # Coast, but not out of the frame: a person who walked out is searched for at its edge.
        height, width = frame.shape[:2]
        self._centre = np.clip(predicted, 0.0, [width - 1.0, height - 1.0])
        coast = self._evaluate(window, self._centre, size)
        return self._result(coast, iterations)

    def _climb(
        self, window: _Window, start: FloatArray, size: FloatArray
    ) -> tuple[FloatArray, _Evaluation, int]:
        """Mean shift from ``start`` (eq. 13), halving a step that lowers rho (Comaniciu's step 5)."""
        cfg = self.config
        y0 = start.copy()
        ev0 = self._evaluate(window, y0, size)
        iterations = 0
        for iterations in range(1, cfg.max_iterations + 1):  # noqa: B007
            total = float(np.sum(ev0.weights))
            if total <= 0.0:
                break
            y1 = np.array([np.dot(ev0.weights, ev0.x), np.dot(ev0.weights, ev0.y)]) / total
            ev1 = self._evaluate(window, y1, size)
            halvings = 0
            while ev1.rho < ev0.rho and halvings < 3 and np.hypot(*(y1 - y0)) > cfg.epsilon_px:
                y1 = (y0 + y1) / 2.0
                ev1 = self._evaluate(window, y1, size)
                halvings += 1
            if ev1.rho < ev0.rho:
                break
            moved = float(np.hypot(*(y1 - y0)))
            y0, ev0 = y1, ev1
            if moved < cfg.epsilon_px:
                break
        return y0, ev0, iterations

    def _scale(self, window: _Window, centre: FloatArray, ev: _Evaluation) -> None:
        """Comaniciu's +-10 % test at the converged centre; the winner pulls the size by ``scale_gain``.

        Comaniciu's test compares rho alone, and a smaller window, purer target, always scores higher: the
        box shrinks (measured on OTB Couple: 25 x 62 px to 15 x 37 in 100 frames while the couple grew
        to 33 x 89). The test here scores a size by its contrast ``rho(inside) - rho(ring)``, the ring
        reaching ``scale_ring`` times the size: a box smaller than the target leaves target in its ring,
        a larger one takes background inside."""
        cfg = self.config
        if cfg.scale_gain <= 0.0 or cfg.scale_step <= 0.0:
            return
        scores = []
        for factor in (1.0, 1.0 - cfg.scale_step, 1.0 + cfg.scale_step):
            size = self._size * factor
            scores.append((self._contrast(window, centre, size), factor))
        best = max(scores)[1] if max(scores)[0] > scores[0][0] else 1.0
        size = self._size * (cfg.scale_gain * best + 1.0 - cfg.scale_gain)
        self._size = np.clip(size, cfg.min_scale * self._size0, cfg.max_scale * self._size0)

    def _contrast(self, window: _Window, centre: FloatArray, size: FloatArray) -> float:
        inner = self._counts(window, centre, size)
        outer = self._counts(window, centre, size * self.config.scale_ring)
        ring = tuple(np.clip(o - i, 0.0, None) for o, i in zip(outer, inner, strict=True))
        return self._similarity(inner) - self._similarity(ring)

    def _similarity(self, counts: tuple[FloatArray, ...]) -> float:
        rho = float(_bhattacharyya(counts[0], self._q_colour) ** self._exponents[0])
        if len(counts) > 1 and self._exponents[1] != 0.0:
            rho *= float(_bhattacharyya(counts[1], self._q_texture) ** self._exponents[1])
        return rho

    def _counts(self, window: _Window, centre: FloatArray, size: FloatArray) -> tuple[FloatArray, ...]:
        """Unweighted feature counts under the silhouette at ``size``, in pixels (each sample stands for
        step^2 of them)."""
        kernel = self._kernel(size)
        rows, cols, valid = window.cells(round(centre[0]) + kernel.dx, round(centre[1]) + kernel.dy)
        cols, rows = cols[valid], rows[valid]
        area = float(kernel.step**2)
        counts = [np.bincount(window.colour[rows, cols], minlength=self._bins).astype(np.float64) * area]
        if self._texture and window.texture is not None:
            texture = np.bincount(window.texture[rows, cols], minlength=self._labels).astype(np.float64)
            counts.append(texture * area)
        return tuple(counts)

    def _result(self, ev: _Evaluation, iterations: int) -> TrackResult:
        return TrackResult(
            box=self.box,
            state=self.state,
            rho=ev.rho,
            rho_colour=ev.rho_colour,
            rho_texture=ev.rho_texture,
            iterations=iterations,
            frames_lost=self.frames_lost,
        )

    # -- features and histograms ------------------------------------------------------------------------

    def _window(self, frame: ImageU8, centre: FloatArray, extent: FloatArray) -> _Window:
        """Colour bins and LBP labels of the frame within ``extent`` (w, h) around ``centre``, on cells of
        the current kernel's sampling step."""
        import cv2

        factor = self._kernel(self._size).step
        height, width = frame.shape[:2]
        x0 = max(0, math.floor(centre[0] - extent[0] / 2.0))
        y0 = max(0, math.floor(centre[1] - extent[1] / 2.0))
        x1 = min(width, math.ceil(centre[0] + extent[0] / 2.0) + 1)
        y1 = min(height, math.ceil(centre[1] + extent[1] / 2.0) + 1)
        # Whole cells only.
        x1 = x0 + (x1 - x0) // factor * factor
        y1 = y0 + (y1 - y0) // factor * factor
        if x1 <= x0 or y1 <= y0:  # the window left the frame: an empty window, every sample invalid
            return _Window(0, 0, np.zeros((0, 0), np.int32), None)
        patch = frame[y0:y1, x0:x1]
        if factor > 1:
            cells = ((x1 - x0) // factor, (y1 - y0) // factor)
            patch = np.asarray(cv2.resize(patch, cells, interpolation=cv2.INTER_AREA), dtype=np.uint8)
        shift = 8 - round(math.log2(self._levels)) if self._levels & (self._levels - 1) == 0 else 0
        if shift:
            q = (patch >> np.uint8(shift)).astype(np.int32)
        else:
            q = (patch.astype(np.int32) * self._levels) >> 8
        colour = (q[..., 0] * self._levels + q[..., 1]) * self._levels + q[..., 2]
        if self.config.colour_space == ColourSpace.HSV:
            colour = self._hsv_bins(patch)
        texture = None
        if self._texture:
            # The window reaches well past the target, so its edge cells (compared with the edge
            # replicated) are background.
            texture = self._lut[lbp_codes(_grey(patch), self.config.lbp_threshold)]
        return _Window(x0, y0, colour, texture, factor)

    def _hsv_bins(self, patch: ImageU8) -> npt.NDArray[np.int32]:
        import cv2

        levels = self._levels
        hsv = np.asarray(cv2.cvtColor(patch, cv2.COLOR_BGR2HSV), dtype=np.int32)  # H 0..179
        h = hsv[..., 0] * levels // 180
        sat = hsv[..., 1] * levels >> 8
        light = (hsv[..., 2] >= 100).astype(np.int32)
        grey = (hsv[..., 1] < 64) | (hsv[..., 2] < 50)
        out: npt.NDArray[np.int32] = np.where(grey, levels * levels + light, h * levels + sat).astype(
            np.int32
        )
        return out

    def _window_union(
        self, frame: ImageU8, window: _Window, centres: list[FloatArray], size: FloatArray
    ) -> _Window:
        xs = [window.x0, window.end[0]]
        ys = [window.y0, window.end[1]]
        for c in centres:
            xs += [c[0] - size[0], c[0] + size[0]]
            ys += [c[1] - size[1], c[1] + size[1]]
        lo = np.array([min(xs), min(ys)])
        hi = np.array([max(xs), max(ys)])
        return self._window(frame, (lo + hi) / 2.0, hi - lo)

    def _kernel(self, size: FloatArray) -> _Kernel:
        # The half-axes to a quarter pixel, and the kernel built from those, not from the exact size: a
        # cached kernel is then a function of its key alone, whatever size first built it and whenever
        # the cache was last cleared (the full tracker asks for kernels the colour-only one does not, and
        # with b = 0 the two must compute the same).
        hx = max(4, round(max(1.0, size[0] / 2.0) * 4)) / 4.0
        hy = max(4, round(max(1.0, size[1] / 2.0) * 4)) / 4.0
        area = math.pi * hx * hy
        step = max(1, round(math.sqrt(area / self.config.max_pixels)))
        key = (round(hx * 4), round(hy * 4), step)
        kernel = self._kernels.get(key)
        if kernel is None:
            rx, ry = math.ceil(hx), math.ceil(hy)
            gy, gx = np.mgrid[-ry : ry + 1 : step, -rx : rx + 1 : step]
            u, v = gx / hx, gy / hy
            r2 = u * u + v * v
            inside = _silhouette(self.config.silhouette, u, v) & (r2 < 1.0)
            kernel = _Kernel(
                gx[inside].astype(np.intp),
                gy[inside].astype(np.intp),
                (1.0 - r2[inside]).astype(np.float64),
                step,
            )
            if len(self._kernels) > 16:
                self._kernels.clear()
            self._kernels[key] = kernel
        return kernel

    def _evaluate(
        self, window: _Window, centre: FloatArray, size: FloatArray, model: bool = True
    ) -> _Evaluation:
        """Candidate histograms at ``centre`` (eqs. 7, 9), rho against the model (eq. 10) and the weights
        of eq. 12. ``model=False``: the histograms only (building or updating the model)."""
        kernel = self._kernel(size)
        xs = round(centre[0]) + kernel.dx
        ys = round(centre[1]) + kernel.dy
        rows, cols, valid = window.cells(xs, ys)
        cols, rows, k = cols[valid], rows[valid], kernel.k[valid]
        x = xs[valid].astype(np.float64)
        y = ys[valid].astype(np.float64)
        total = float(np.sum(k))
        if len(k) < 8 or total <= 0.0:
            empty = np.zeros(self._bins)
            return _Evaluation(0.0, 0.0, 0.0, empty, None, np.zeros(0), np.zeros(0), np.zeros(0))
        colour_bins = window.colour[rows, cols]
        p_colour = np.bincount(colour_bins, weights=k, minlength=self._bins) / total
        p_texture = None
        texture_labels = None
        if self._texture and window.texture is not None:
            texture_labels = window.texture[rows, cols]
            p_texture = np.bincount(texture_labels, weights=k, minlength=self._labels) / total
        if not model:
            return _Evaluation(0.0, 0.0, 1.0, p_colour, p_texture, np.zeros(0), x, y)
        rho_c = float(np.sum(np.sqrt(p_colour * self._q_colour)))
        ratio_c = np.sqrt(
            np.divide(self._q_colour, p_colour, out=np.zeros_like(p_colour), where=p_colour > 0)
        )
        w_colour = ratio_c[colour_bins]
        if p_texture is None or texture_labels is None:
            return _Evaluation(rho_c, rho_c, 1.0, p_colour, None, w_colour, x, y)
        rho_t = float(np.sum(np.sqrt(p_texture * self._q_texture)))
        ratio_t = np.sqrt(
            np.divide(self._q_texture, p_texture, out=np.zeros_like(p_texture), where=p_texture > 0)
        )
        # eq. 12, the gradient of rho_c * rho_t, generalised to rho_c^a * rho_t^b (the feature weights,
        # 1 and 1 in the paper): a w_c / rho_c + b w_t / rho_t, up to a positive factor.
        a, b = self._exponents
        if b == 0.0:
            # Texture off (feature selection): exactly the colour-only tracker's weights and, for a = 1,
            # its rho (a positive factor on the weights does not move their mean).
            return _Evaluation(rho_c**a, rho_c, rho_t, p_colour, p_texture, w_colour, x, y)
        weights = a * w_colour / max(rho_c, 1e-9) + b * ratio_t[texture_labels] / max(rho_t, 1e-9)
        rho = rho_c**a * rho_t**b
        return _Evaluation(rho, rho_c, rho_t, p_colour, p_texture, weights, x, y)

    def _background(self, window: _Window) -> None:
        """The corrected background-weighted model (Ning et al. 2012) from the ring between the box and
        the box grown to three times its area (as far as ``window`` reaches); and the feature weights.

        Feature weights (``adaptive_weights``): the similarity is ``rho_c^a * rho_t^b`` with each
        exponent the feature's distance from its surroundings, ``1 - BC(q, ring)``, over the larger of
        the two: a feature that tells the target from what is around it no better than the other counts
        less (Jia et al.'s AMF-MS weighs its features adaptively too). Without it, a = b = 1, the
        paper's eq. 10."""
        cfg = self.config
        if cfg.background_weighting or (cfg.adaptive_weights and self._texture):
            grown = self._size * math.sqrt(3.0)
            bg_colour, bg_texture = self._ring(window, self._centre, grown)
            if cfg.adaptive_weights and bg_texture is not None:
                d_c = 1.0 - _bhattacharyya(bg_colour, _normalised(self._q_colour_raw))
                d_t = 1.0 - _bhattacharyya(bg_texture, _normalised(self._q_texture_raw))
                top = max(d_c, d_t)
                a, b = (d_c / top, d_t / top) if top > 1e-6 else (1.0, 1.0)
                if self._select:
                    # Texture on from the ring only where it tells the target from its surroundings
                    # at least as well as colour (b = 1); else exactly off.
                    self._ring_exponents = (max(a, cfg.min_feature_weight), 1.0) if b >= 1.0 else (1.0, 0.0)
                elif self._distractor_weighting:
                    # Unfloored: what the weights relax to while no distractor is near.
                    self._ring_exponents = (max(a, cfg.min_feature_weight), b)
                else:
                    self._exponents = (max(a, cfg.min_feature_weight), max(b, cfg.min_feature_weight))
            if cfg.background_weighting:
                # Colour only: with ten texture labels, "plain" is common in any background, and
                # weighting it down leaves a model of the target's rarest texture, which a busy
                # passer-by matches better than the target (measured on the crossing scene).
                self._colour_factor = _background_factor(bg_colour)
        self._reweight()

    def _weigh_distractors(self, window: _Window, centre: FloatArray, ev: _Evaluation) -> None:
        """The feature exponents from the distractors (``TextureWeighting.DISTRACTOR``), after a tracking
        frame converged at ``centre`` with ``ev``.

        The neighbours are the box moved by ``distractor_offset`` box sizes in the 8 directions, as far as
        ``window`` reaches (at least a quarter of a neighbour's kernel: the tracking window reaches about
        one box size past the box). The one with the highest ``rho_c`` is a distractor when that is at
        least ``distractor_ratio`` times the target's own ``rho_c``: colour alone would take it for the
        target (a look-alike passer-by, the partner walking beside the user). A second ring, the box moved
        by ``distractor_near`` box sizes (overlapping it, inside the window), is a distractor when its
        ``rho_c`` is at least ``distractor_near_ratio`` (1) times the target's: colour has no peak at the
        converged box and does not localise the target (a large, evenly coloured person near the camera,
        whose far neighbours lie past the window; ``track_left_turn`` seed 4). Each feature then counts by
        its distance from the distractor, ``1 - BC(q, p_distractor)``, over the larger of the two, both
        floored at ``min_feature_weight``: while a look-alike is near, texture has at least that say.
        With no distractor the exponents relax, by ``distractor_forget`` a confident frame, toward the
        ring's (``_background``: each feature's distance from the surroundings, texture unfloored),
        which on OTB's people leave texture a small say (b 0.0-0.3) and on the rendered ones more. Frames
        whose match is not confident (``rho`` under ``update_ratio`` times ``rho_ref``: a passer-by over
        the target, whom the neighbours no longer see) change nothing. Possegger, Mauthner, Bischof, "In
        defense of color-based model-free tracking" (CVPR 2015) and Zhu et al.'s DaSiamRPN (ECCV 2018)
        likewise weigh against distractors, not only the background.

        ``TextureWeighting.SELECT`` (feature selection, the default) is the same with texture exactly
        off, exponents (1, 0), wherever it carries no information: a distractor counts only when texture
        tells it from the target where colour does not (``_texture_informative``), the weights relax to
        (1, 0) (snapped there once within 0.02), and the ring turns texture on only where it separates
        the target from its surroundings at least as well as colour. With texture off the tracker
        computes exactly what the colour-only tracker does (``_evaluate``).

        ``rho_ref`` is rescaled to the new exponents (the target's match under them), so a change of
        weights is not taken for an occlusion."""
        texture = window.texture
        if not self._distractor_weighting or texture is None or ev.rho_colour <= 0.0:
            return
        cfg = self.config
        kernel = self._kernel(self._size)
        least = max(8, len(kernel.k) // 4)
        # Colour at each neighbour (bin counts only); the texture of the most alike one that colour
        # would take for the target: on the far ring (distractor_offset) at distractor_ratio of the
        # target's rho_c, on the near ring (distractor_near) at distractor_near_ratio.
        rings = [(cfg.distractor_offset, cfg.distractor_ratio)]
        if cfg.distractor_near > 0.0:
            rings.append((cfg.distractor_near, cfg.distractor_near_ratio))
        best: tuple[float, IntArray, IntArray, FloatArray] | None = None
        for offset, ratio in rings:
            for ox, oy in _NEIGHBOURS:
                at = centre + offset * self._size * np.array([ox, oy])
                rows, cols, valid = window.cells(round(at[0]) + kernel.dx, round(at[1]) + kernel.dy)
                if int(np.count_nonzero(valid)) < least:
                    continue
                rows, cols, k = rows[valid], cols[valid], kernel.k[valid]
                p_colour = np.bincount(window.colour[rows, cols], weights=k, minlength=self._bins).astype(
                    np.float64
                )
                rho_c = _bhattacharyya(p_colour, self._q_colour)
                if rho_c >= ratio * ev.rho_colour and (best is None or rho_c > best[0]):
                    best = (rho_c, rows, cols, k)
        a0, b0 = self._exponents
        confident = ev.rho >= cfg.update_ratio * self._rho_ref
        d_t = 0.0
        if best is not None:
            _, rows, cols, k = best
            p_texture = np.bincount(texture[rows, cols], weights=k, minlength=self._labels).astype(np.float64)
            d_t = 1.0 - _bhattacharyya(p_texture, self._q_texture)
            if self._select and not self._texture_informative(ev, best[0], 1.0 - d_t, kernel.k):
                best = None  # texture does not tell the target from it: as if none were near
        if self._select and confident:
            self._learn_feature_match(ev)
        if best is not None:
            d_c = 1.0 - best[0]
            top = max(d_c, d_t)
            if top <= 1e-6:
                return  # neither feature tells them apart: keep the weights
            a, b = _separation_exponents(d_c, d_t, cfg.min_feature_weight)
            b = max(b, self._ring_exponents[1])
            self._texture_on = self._select
        elif not confident:
            return  # not a confident match (a passer-by over the target?): nothing learnt
        else:
            r = cfg.distractor_forget
            a_r, b_r = self._ring_exponents
            a, b = a0 + r * (a_r - a0), b0 + r * (b_r - b0)
            # Feature selection snaps a texture on its way out to exactly off once its say is small
            # (a 2 % exponent moves rho by well under 1 %).
            snap = 0.02 if self._select else 1e-3
            if abs(a - a_r) + abs(b - b_r) < snap:
                a, b = a_r, b_r
                self._texture_on = False
        if (a, b) == (a0, b0):
            return
        self._exponents = (a, b)
        rho_c, rho_t = max(ev.rho_colour, 1e-9), max(ev.rho_texture, 1e-9)
        self._rho_ref = max(self._rho_ref * rho_c ** (a - a0) * rho_t ** (b - b0), 1e-3)

    def _texture_informative(self, ev: _Evaluation, rho_c: float, rho_t: float, k: FloatArray) -> bool:
        """Feature selection: does texture tell the target (matching the model by ``ev``) from a
        distractor (matching it by ``rho_c``, ``rho_t``) where colour does not? Each feature's margin,
        the target's match less the distractor's, in units of its noise: the running deviation of the
        target's own match on confident frames (for texture at least the mismatch two samples of one
        texture show at the kernel's size, ``(labels - 1) / (4 n)``, ``n`` the kernel's effective sample
        count: a Bhattacharyya coefficient's small-sample bias). Texture is informative when its margin
        is at least ``select_on`` noise levels (``select_off`` while texture is on: hysteresis) and
        larger than colour's."""
        cfg = self.config
        stats = self._feature_match
        if stats[4] < cfg.select_samples:
            return False
        n = float(np.sum(k)) ** 2 / max(float(np.sum(k * k)), 1e-12)
        noise_t = max(math.sqrt(stats[3]), (self._labels - 1) / (4.0 * max(n, 1.0)))
        noise_c = max(math.sqrt(stats[1]), 1e-6)
        z_t = (ev.rho_texture - rho_t) / noise_t
        z_c = (ev.rho_colour - rho_c) / noise_c
        threshold = cfg.select_off if self._texture_on else cfg.select_on
        if not (z_t >= threshold and z_t > z_c):
            return False
        # And texture must be able to decide: at the exponents it would get (on's, a and b, below),
        # its evidence for the target over the distractor, b log(rho_t / rho_t'), at least colour's
        # either way, a |log(rho_c / rho_c')| (while on: half of it, the hysteresis again).
        a, b = _separation_exponents(1.0 - rho_c, 1.0 - rho_t, cfg.min_feature_weight)
        e_t = b * math.log(max(ev.rho_texture, 1e-9) / max(rho_t, 1e-9))
        e_c = a * abs(math.log(max(ev.rho_colour, 1e-9) / max(rho_c, 1e-9)))
        return e_t >= (cfg.select_off / cfg.select_on if self._texture_on else 1.0) * e_c

    def _learn_feature_match(self, ev: _Evaluation) -> None:
        """The target's own colour and texture matches on a confident tracking frame: running means and
        mean square deviations at ``rho_ref_rate`` (the first frame sets the means)."""
        m_c, v_c, m_t, v_t, count = self._feature_match
        x_c, x_t = ev.rho_colour, ev.rho_texture
        if count == 0:
            self._feature_match = (x_c, 0.0, x_t, 0.0, 1)
            return
        r = self.config.rho_ref_rate
        d_c, d_t = x_c - m_c, x_t - m_t
        self._feature_match = (
            m_c + r * d_c,
            (1.0 - r) * (v_c + r * d_c * d_c),
            m_t + r * d_t,
            (1.0 - r) * (v_t + r * d_t * d_t),
            count + 1,
        )

    def _reweight(self) -> None:
        """The models the candidates are compared with: the raw histograms, colour scaled by the last
        background factor."""
        self._q_colour = _normalised(self._q_colour_raw * self._colour_factor)
        self._q_texture = _normalised(self._q_texture_raw)

    def _ring(
        self, window: _Window, centre: FloatArray, grown: FloatArray
    ) -> tuple[FloatArray, FloatArray | None]:
        h, w = window.shape
        gy, gx = np.mgrid[0:h, 0:w]
        f = window.factor
        # Cell centres in frame pixels.
        dx = window.x0 + (gx + 0.5) * f - 0.5 - centre[0]
        dy = window.y0 + (gy + 0.5) * f - 0.5 - centre[1]
        u, v = dx / (self._size[0] / 2.0), dy / (self._size[1] / 2.0)
        outer_u, outer_v = dx / (grown[0] / 2.0), dy / (grown[1] / 2.0)
        ring = (np.maximum(np.abs(u), np.abs(v)) > 1.0) & (
            np.maximum(np.abs(outer_u), np.abs(outer_v)) <= 1.0
        )
        rows, cols = gy[ring], gx[ring]
        colour = np.bincount(window.colour[rows, cols], minlength=self._bins).astype(np.float64)
        texture = None
        if window.texture is not None:
            texture = np.bincount(window.texture[rows, cols], minlength=self._labels).astype(np.float64)
        return colour, texture


_NEIGHBOURS = (
    (-1.0, 0.0),
    (1.0, 0.0),
    (0.0, -1.0),
    (0.0, 1.0),
    (-1.0, -1.0),
    (1.0, -1.0),
    (-1.0, 1.0),
    (1.0, 1.0),
)


def _background_factor(background: FloatArray) -> FloatArray:
    """v_u = min(o* / o_u, 1), o* the smallest non-zero background bin; 1 where the background has none."""
    nonzero = background[background > 0]
    if not len(nonzero):
        return np.ones_like(background)
    smallest = float(np.min(nonzero))
    return np.minimum(
        np.divide(smallest, background, out=np.ones_like(background), where=background > 0), 1.0
    )


def _separation_exponents(d_colour: float, d_texture: float, floor: float) -> tuple[float, float]:
    """The feature exponents (a, b) against a distractor: each feature's distance between the target and
    it, ``1 - BC``, over the larger of the two (the feature that tells them apart better counts whole),
    and never below ``floor``."""
    top = max(d_colour, d_texture, 1e-9)
    return max(d_colour / top, floor), max(d_texture / top, floor)


def _bhattacharyya(counts: FloatArray, q: FloatArray) -> float:
    total = float(np.sum(counts))
    return float(np.sum(np.sqrt(counts / total * q))) if total > 0.0 else 0.0


def _normalised(hist: FloatArray) -> FloatArray:
    total = float(np.sum(hist))
    return hist / total if total > 0.0 else hist


def _grey(bgr: ImageU8) -> ImageU8:
    # ITU-R 601 luma in integers: (29 B + 150 G + 77 R) / 256.
    b, g, r = (bgr[..., i].astype(np.uint16) for i in range(3))
    return ((29 * b + 150 * g + 77 * r) >> 8).astype(np.uint8)


def _check_frame(frame: ImageU8) -> ImageU8:
    if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
        raise ValueError(f"want a BGR uint8 (H, W, 3) frame, got {frame.dtype} {frame.shape}")
    return frame
