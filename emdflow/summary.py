"""Global flow summary: what the autopilot flies on.

The detector's output is sparse, quantised to the channels' speeds, and each axis measures
how fast an edge *crosses that axis*, not a flow component (``docs/spec/template-model.md`` §6):
a per-axis mean is 40–100 % off. The summary works on the detection histogram
``hist[axis, code, orientation]`` that the backends compute next to the detector, so its
cost does not depend on the frame size.

Method
------
1. **Intersection of constraints (IoC), the initial guess** (spec §6). Each detection is
   a constraint on the global flow ``F = (U, V)`` along the gradient direction
   ``n = (cos φ, sin φ)`` of its orientation bin: a horizontal detection of channel speed
   ``r`` says ``n · F = r · cos φ``, a vertical one ``n · F = r · sin φ``. ``F`` is the
   Huber IRLS solution. The right-hand side is quantised to the channel speeds (scale
   ``k`` fires for crossing speeds of about ``k/2 … 1.5k`` and the fastest channel wins),
   so the quantisation errors only cancel for motion along the axes or diagonals; off
   those directions the fit snaps towards the axes (21 % / 11° median error at +0.3 rad).
2. **Calibrated maximum likelihood, the answer.** Each histogram row (axis ``a``,
   orientation bin) is treated as a sample of the *mixture of winning codes* the detector
   produces when an edge crosses axis ``a`` at the signed speed ``c = (n · F) / n_a``. The
   table ``P(code | c, ψ, β)`` — ``ψ`` the angle between the edge normal and the axis,
   ``β = |sin|`` of the angle between the flow and the edge normal — is measured on
   camera flights with known flow (``emdflow/tools/calibrate_summary.py``, stored in
   ``summary_calibration.npz`` next to this module) and mixed with a uniform outlier
   probability. ``F`` maximises ``Σ_rows w_row Σ_codes count · log P(code | c(F), ψ, β(F))``
   with the tempered row weight ``w_row = n_row ** (row_exponent − 1)`` (a row of ``n``
   detections counts like ``√n`` independent ones: neighbouring detections are not
   independent, and a texture's few strong edge orientations would otherwise dominate),
   searched coarse-to-fine on a polar grid (log speed × direction) around the IoC guess:
   7×7 candidates over ±0.45 in log speed and ±24° (re-centred on the best candidate while
   it is in the fastest row or the outermost directions, at most ``search_climbs`` = 2
   times: the guess under-reads fast flow off the axes, see ``_SEARCH_LEVELS``), then 7×7
   over ±0.12 and ±4.5°, then the vertex of a parabola through the best candidate and its
   neighbours. Each row's β is taken at the centre direction of a level, which pulls a
   level's answer towards its centre; so the fine level runs a second time, centred on
   the first one's answer with β from there (that pass alone takes the extended model
   from 2.37° to 2.22° median direction error on random directions, and the paper's from
   2.42° to 2.37°; evaluating β at every candidate instead measured worse, 2.64°, as did
   a table without the β dimension, 2.74°). Directions are multiples of 0.25° and every
   row's geometry (|c| per unit speed, its sign, the β node) is tabulated once per
   direction; the per-row likelihood curves are computed once per frame (one batched
   matrix product), so a level costs one (candidates × rows) interpolation. Rows whose
   normal is more than ``max_axis_angle`` (60°) from their axis are left out: their
   crossing speed ``c = n·F / n_a`` is huge and the detections there are dominated by
   texture details rather than edges. The table carries the band overlap and
   the highest-speed priority, the orientation error of the gradient, and the
   texture-detail ("point") responses that appear when the flow slides along an edge.
3. **Quality (0..255) tells the expected error.** It multiplies a texture factor (share
   of pixels with enough contrast), an evidence factor (detections), a geometry factor
   (gradient directions constraining both axes, the aperture problem) and an *accuracy*
   factor computed from the curvature of the log-likelihood around its maximum (the
   predicted relative error of ``F``, inflated by a calibrated over-dispersion because
   neighbouring detections are not independent), the disagreement between the IoC guess
   and the likelihood fit, the top of the speed range (above ~11 px/frame with the
   paper's channels only the 13 px scale fires and speed is poorly resolved; ~12.7 with
   the extended model's scale 15), and the **misfit**: how much worse the table explains
   the frame's code mixtures than the calibration flights' are explained. The measure is
   the likelihood-ratio deviance per (tempered) detection between the table at the answer
   and each row's own observed mixture (:attr:`FlowSummary.deviance`), minus the median
   deviance of calibration frames at the same speed (stored with the table by
   ``calibrate_summary fit``; ``misfit_weight`` × the excess joins the expected error in
   quadrature). The likelihood fit's own precision cannot see a texture whose mixtures
   the table does not know — brick's aligned, periodic edges read 0.5–1 px/frame 15–16 %
   off with the best qualities of the set — its deviance can: on the held-out evaluation
   flights the rank correlation of quality with the error rises from 0.36 to 0.52
   (paper's model, random directions) and 0.37 to 0.48 (extended), and the top quality
   band's 90th-percentile error falls from 23 % to 12.5 % and 15 % to 11 %. On
   calibration frames the deviance adds little (leaving one calibration texture out of
   the paper's table: rank correlation 0.648 → 0.643): it flags scenes *unlike* the
   calibration's. ``misfit_weight = 0.3`` was chosen on the evaluation flights (0.2–0.5
   all help there). The weights of the three terms were re-chosen later on flights over
   the *calibration* textures (``overdispersion`` 0.7 → 2.0, ``disagreement_weight`` 0.5
   → 0.1): the disagreement with the IoC guess, which for the extended model's classes
   is a crude start, was the largest term and the worst predictor; with the likelihood's
   own precision leading, the rank correlation on the held-out evaluation flights rose
   from 0.22–0.42 to 0.34–0.59 (extended model, four sets) and from 0.50–0.53 to
   0.54–0.56 (paper's, random and +0.3 rad directions; at multiples of 45° 0.49 → 0.46).
   See :class:`SummaryOptions`.

Blank, saturated or texture-less frames give flow 0 with quality 0, and so do the three
frames (more with uncompensated delays) whose templates contain a global brightness step (an auto-exposure jump; see
:attr:`FlowField.exposure_step`). A *static* textured
scene — texture present, almost no receptor changes at scale 1 (or only sensor noise's),
so the image moves less
than the detector's floor of about 0.5 px/frame — is a valid measurement: flow 0 with a
quality set by the texture.

Calibration tables are per channel set: ``summary_calibration.npz`` for the paper's
channels (scales 1, 3, …, 13, delay 1) and ``summary_calibration_<model>.npz`` for others,
each naming its channels and threshold mode (:func:`calibration_for` picks the table of
exactly ``field.params.channels``, preferring one made with the same threshold mode). The
extended model's table (``delays=(1, 2, 4)`` at scale 1, adaptive threshold: channel
speeds 0.25, 0.5, 1, 3, …, 13) has three scene-contrast classes, chosen per frame from
the frame's mean gradient ``g`` (edges at g = 3.75 gray levels, where the adaptive
θ = 0.4 g leaves its floor of 1.5, and at 12, rough ground at full contrast): at the floor
noise weighs more and the code mixture for a given crossing speed shifts; one table for
all contrasts was biased by +13 % at 1 px/frame on full-contrast flights, and without
the top class (and its calibration flights over rough 1/f textures) gravel and grass read
0.25 px/frame 20–25 % slow. Inside each contrast class the extended table has one
distribution per **gradient-strength class** of the detections (the histogram's bins
``class · 64 + orientation``, ``emdflow.params.GRADIENT_CLASS_STEPS``): how strong the
local gradient is against the threshold says which delays and scales *can* fire at a
given speed, so a class's code mixture depends much less on the texture. The classes of
one row share its geometry, so their log-likelihood curves are added before the search;
a frame gathers only the table rows of its nonzero counts. The paper's table has no
classes (they gained little there, see ``calibrate_summary.GRADIENT_CLASS_TABLES``) and
the summary sums the histogram's classes for it. For a channel set
without a table the summary falls back to step 1 alone.

**Diagonal evidence** (``EngineParams.diagonal_evidence``, the default): the histogram has
two more axes, the detectors along the diagonals ``B = A + k·(1, 1)`` (axis 2) and
``B = A + k·(1, −1)`` (axis 3). Their rows enter the likelihood of step 2 with their own
geometry — the crossing speed in diagonal steps, ``c = n·F / (n_x ± n_y)``, and ψ against
the diagonal — and their own distributions (``prob_diagonal`` in the table, measured on
the same calibration flights; the table files are ``…_diagonal.npz``, and a table serves
only estimators with the same setting). Step 1 (the IoC guess) and the quality's
detection count read the horizontal and vertical axes alone. Over granular ground a
fast oblique flow blinds the vertical detectors (the ground slides sideways under their
receptors), and the diagonal nearest the flow still sees it: the paper's model on random
flights, 8.9 % / 2.37° → 6.3 % / 1.96° median error (README, "Diagonal evidence"; both
with the former search, ``search_climbs=0``).

**Line ground.** Thin lines (mortar joints, paving, tiles) fire only the scale of their
speed where an edge also fires the larger ones, so the edge table reads them slow (brick
at 7–13 px/frame: 0.66–0.80×). The extended model's channels have a second table,
measured over turned grids of thin bright lines (``summary_calibration_extended_lines.npz``,
``calibrate_summary fit --ground lines``). Each frame is fitted with both, from the same
IoC guess, and the line table's answer is kept when its log-likelihood beats the edge
table's by more than ``SummaryOptions.line_ground_margin`` (:attr:`FlowSummary.line_ground`
says which). The gradient-strength classes are what make the two tell apart: a thin line
has a strong gradient for the speed its codes say. The paper's channels have no line
table: one fitted by the same recipe won in only a third of the frames over turned line
grids and a fifth over step edges, and read the +0.3 rad set's directions worse (README,
"Thin lines read slow").

Measured accuracy
-----------------
(With the former search, ``search_climbs=0``, which reads 9–13 px/frame off the axes
lower; README, "The search's reach", has both.) OpenCL backend (bit-identical to numpy),
320×240, noise σ = 2, 9 speeds (1, 2, 3, 4, 5, 7, 9, 11, 13 px/frame) × 4 evaluation
textures (gravel, brick, grass, camera — the calibration never saw them) × 8 directions ×
6 frames = 1728 frames per set; quality-0 frames count as 100 % error (none occurred:
coverage 100 %) (``python -m emdflow.tools.calibrate_summary evaluate --offset 0`` /
``--offset 0.3`` / ``--random``). Median relative error, median direction error:

============================  ==============  ==============
directions                    previous ML     this summary
============================  ==============  ==============
multiples of 45°              8.7 %, 1.01°    9.3 %, 1.35°
multiples of 45° + 0.3 rad    9.4 %, 2.68°    9.0 %, 2.58°
random (seeded)               9.5 %, 2.56°    8.9 %, 2.37°
============================  ==============  ==============

("previous ML": the former 4-level search with untempered rows and β nodes
0/.25/.5/.7/.85/1, fitted on the same flights; the IoC guess alone is 21 % / 11° off-axis.
Tempering trades ~0.3° along the axes for better off-axis estimates; ``row_exponent=1``
restores the untempered likelihood; with one fine pass instead of two: 9.1 %, 1.33° /
9.1 %, 2.69° / 9.2 %, 2.42°.) 1–7 px/frame are within 5–12 % and 1–3°; at 9–13 px/frame
only the top scales fire: 8–18 % and 2–7°, and 13 px/frame 25–40 %. Brick (few, aligned,
periodic edges) is the hardest texture. The quality says so: quality bands (random set)
192–255 → 5.9 % median error (90th percentile 12.5 %), 128–191 → 10.5 %, 64–127 →
12.6 %, 1–63 → 24 % (without the misfit term 7.0 % (23 %), 10.6 %, 12.1 %, 32 %: brick's
biased frames sat in the top band). Cost ≈ 0.29–0.31 ms per call on the 2-core host, plus
~0.015 ms for the deviance (IoC guess ~0.03 ms, per-frame curves ~0.04 ms, search
~0.16 ms, of which the second fine pass ~0.055 ms); the former 4-level search took
~0.8 ms. At 640×480 (``evaluate --size 640x480``; the engine samples about as many
detections as at 320×240, over four times the ground) the three sets give 8.1 %, 1.06° /
8.5 %, 2.32° / 8.1 %, 1.91°. The error is mostly each flight's, not each frame's
(``evaluate`` prints both parts): over the same ground it does not average out.

Extended model (``scales=(1, 3, …, 13, 15)``, ``delays=(1, 2, 4)``, ``delay_scales=(1,)``,
adaptive threshold, brightness compensation; its own table with gradient-strength
classes): 10 speeds (0.25, 0.5, 1, 2, 3, 5, 7, 9, 11, 13 px/frame) × the same 4
evaluation textures × 8 directions × 6 frames = 1920 frames per set, coverage 100 % in
every set (``evaluate --model extended --random`` etc.; see ``calibrate_summary``), read
with its edge and line-ground tables. Median relative error, median direction error:

==========================================  ==============  ================  ====================
set                                         all speeds      0.25 px/frame     edge table alone
==========================================  ==============  ================  ====================
random directions                           6.3 %, 1.92°    6.6 %, 1.86°      7.0 %, 1.80°; 6.6 %
multiples of 45° + 0.3 rad                  6.2 %, 1.92°    6.3 %, 1.91°      7.0 %, 1.84°; 6.2 %
random, contrast × 0.25                     7.7 %, 2.05°    9.0 %, 2.54°      8.2 %, 2.09°; 10.5 %
random, exposure drift +20 % per flight     6.6 %, 2.02°    7.0 %, 1.77°      7.3 %, 1.92°; 6.9 %
random, exposure drift −20 % per flight     6.6 %, 1.95°    9.2 %, 1.82°      7.2 %, 1.92°; 9.2 %
==========================================  ==============  ================  ====================

(With the line-ground table, "Line ground" above; the last column is the edge table alone,
``SummaryOptions(ground="edges")``, all speeds and 0.25 px/frame. The rest of this note
was measured with the edge table alone. IoC alone: 16.9 % / 5.8°, 20.3 % / 9.5°,
19.9 % / 5.2°, 17.0 % / 5.9°, 17.6 % / 5.7°.
Measured with the compensation's threshold at 256 T + 128 (see
:meth:`emdflow.EngineParams.compensated_threshold`), the gradient-strength classes taken
at the brightness of the frame (the channel's exposure gain applied to the gradient of
``t − D``, :func:`emdflow.reference.summary_statistics`) and the table collected through
both. With the classes taken at the gradient's own brightness the five sets gave
7.0 % / 1.81°, 7.0 % / 1.82°, 8.5 % / 2.12°, 7.3 % / 1.93°, 7.2 % / 1.96° and 0.25
px/frame 6.5 %, 6.2 %, 10.7 %, 6.4 %, **10.4 %**: a darkening flight put the slow
channel's detections in too strong classes, and gravel and grass read 0.25 px/frame
0.88–0.89× (now 0.90–0.93×). The former threshold 256 T and its table gave 7.1 % / 1.91°,
7.2 % / 1.85°, 8.8 % / 2.22°, 7.0 % / 1.85°, 7.0 % / 1.93°, and 0.25 px/frame 9.6 %,
9.1 %, 15.8 %, 5.4 %, 8.1 %: its drifting calibration flights carried too many fast codes
at slow speeds, and steady flights read slow motion slow. README, "The summary".) 0.5–3
px/frame are within 4.1–5.4 % and 0.9–1.5°; 5–7 px/frame 8.0–9.3 % / 1.5–2.6°, 9–11
px/frame 10–11 % / 3.4–3.7°, 13 px/frame 15 % / 5.3° (without the scale-15 channel, as
for the paper's model: 29–40 % / 7–10°). Above 7 px/frame the error is brick's: its thin
mortar lines read 7–13 px/frame 0.66–0.80× (with the line-ground table 5–9 px/frame
0.96–0.99×, 11–13 px/frame 0.78–0.84×) while gravel, grass and camera read within
0.92–1.01×. Quality bands (random set): 192–255 → 5.5 % (90th percentile
11.2 %), 128–191 → 6.8 %, 64–127 → 11.8 %, 1–63 → 21 %; rank correlation of quality with
the error 0.41–0.45 across the five sets (without the misfit term 6.1 % (14.8 %), 6.7 %,
15 %, 31 % and 0.32 on the random set). Cost on the Intel Xeon host of the earlier
sessions, with the edge table alone ≈ 0.55–0.6 ms per call back to back at 640×480 (plus
~0.025 ms for the deviance) and 0.8–1.2 ms right after each frame's update, when the
engine has evicted the table from the caches (``emdflow bench --stages --model
extended``; on the AMD EPYC host of the README's "Speed", with both tables, 2.3 ms at
640×480 and 2.2–2.4 ms in ``emdflowd --demo`` at 320×240); the line-ground table's second fit, which reuses the
first one's gathering of the counts, makes it 1.6–1.7× (0.85–0.90 against 0.52 ms back to
back at 320×240 and 640×480, ``calibrate_summary evaluate --data F --ground auto|edges``;
1.05 ms after each update, measured on an Intel Xeon host where the figures above were on
an AMD EPYC one): the
curves of up to four classes per row, ~2 000 nonzero counts, each a 240-entry table row,
summed by one compiled sparse product (numpy's padded batched product took ~0.85 ms back
to back). Without the classes
(``EngineParams.gradient_classes=False``, which reads the table's all-classes distribution:
8.8 % / 2.10°, 0.25 px/frame 9.8 %) it costs about as much as the paper model's summary.

References
----------
Quelin, Bouzerdoum & Phung, "Fast digital optical flow estimation based on EMD",
EUVIP 2010; ``docs/spec/template-model.md`` §6 (facts the summary is built on).
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import json
import math
import warnings
from pathlib import Path

import numpy as np

from .field import FlowField
from .params import GRADIENT_CLASS_STEPS, HISTOGRAM_BINS, MODELS, ORIENTATION_BINS, EngineParams, _is_real, _is_whole
from .reference import STAT_CONTRAST, STAT_FIRST_CHANGED

__all__ = ["FlowSummary", "summarize", "SummaryOptions", "calibration_for", "calibration_mismatch", "CalibrationWarning",
           "warn_if_uncalibrated", "prepare"]


def _compiled_csr_product():
    """SciPy's compiled CSR × dense kernel ``csr_matvecs(rows, cols, vecs, indptr, indices,
    data, X, Y)`` (Y += A · X; SciPy comes with scikit-image), or None. It is a private
    function, so it is checked on a small product once: a SciPy that renamed or changed
    it leaves the summary on the numpy path, which gives the same sums, slower."""
    try:
        from scipy.sparse._sparsetools import csr_matvecs

        table = np.arange(12, dtype=np.float32).reshape(4, 3)
        out = np.zeros((2, 3), np.float32)
        csr_matvecs(2, 4, 3, np.array([0, 1, 3]), np.array([3, 0, 2]),
                    np.array([1.0, 2.0, 0.5], np.float32), table.ravel(), out.ravel())
        expected = np.stack([table[3], 2.0 * table[0] + 0.5 * table[2]])
        return csr_matvecs if np.array_equal(out, expected) else None
    except Exception:  # noqa: BLE001 - any failure of a private API means "use numpy"
        return None


_CSR_MATVECS = _compiled_csr_product()

#: Calibration table of the paper's model, written by
#: ``python -m emdflow.tools.calibrate_summary fit --write``.
CALIBRATION_FILE = Path(__file__).with_name("summary_calibration.npz")
#: Tables of other channel sets sit next to it as ``summary_calibration_<model>.npz``
#: (``fit --model <model> --write``), each naming its channels and threshold mode, and
#: line-ground tables as ``summary_calibration[_<model>]_lines.npz`` (``fit --ground
#: lines``), each naming its ground.
CALIBRATION_GLOB = "summary_calibration*.npz"
#: Values of :attr:`SummaryOptions.ground`; a table's own ``ground`` (``"edges"`` when
#: it names none) is one of the last two.
GROUNDS = ("auto", "edges", "lines")


@dataclasses.dataclass(frozen=True)
class FlowSummary:
    """Global image flow of one frame.

    Attributes
    ----------
    flow_x, flow_y : float
        Global image flow, px/frame, image axes (x right, y down) — not MAVLink axes.
    quality : int
        0 (no information) … 255 (best). It falls as the expected error grows (see
        :class:`SummaryOptions` and the README's quality table).
    detections : int
        Detections that entered the fit.
    static : bool
        True when the scene is textured but does not move measurably (< ~0.5 px/frame);
        the flow is then 0 by definition.
    inlier_fraction : float
        Share of detection weight the robust IoC fit kept (1 = all agree).
    expected_error : float
        Predicted relative error of the flow (0.1 = 10 % of its magnitude); ``inf`` when
        nothing was estimated, 0 for a static scene.
    deviance : float
        How far the detections' code mixtures are from what the calibrated model predicts
        at the answer: the likelihood-ratio deviance per (tempered) detection against each
        histogram row's own mixture; 0 without a likelihood fit. Calibration flights show
        ~0.1–0.6 (paper table) or ~0.25–1.2 (extended), rising with speed; more means a scene
        unlike the calibration's, and lowers the quality (``SummaryOptions.misfit_weight``).
    line_ground : bool
        True when the answer is the line-ground table's: with ``SummaryOptions.ground``
        ``"auto"`` the frame's detections are better explained by thin lines (mortar,
        paving joints, tiles) than by edges; with ``"lines"`` the table was forced.
    """

    flow_x: float = 0.0
    flow_y: float = 0.0
    quality: int = 0
    detections: int = 0
    static: bool = False
    inlier_fraction: float = 0.0
    expected_error: float = math.inf
    deviance: float = 0.0
    line_ground: bool = False

    @property
    def speed(self) -> float:
        """Magnitude of the global flow, px/frame."""
        return math.hypot(self.flow_x, self.flow_y)


@dataclasses.dataclass(frozen=True)
class SummaryOptions:
    """Tuning of :func:`summarize` (defaults measured on texture flights, see README).

    Attributes
    ----------
    min_textured : float
        Textured share of pixels below which a frame is blank (quality 0).
    full_textured : float
        Textured share at which the texture factor of the quality reaches 1.
    max_saturated : float
        Saturated share of pixels above which a frame is unusable (quality 0).
    min_detections : int
        Fewer detections than this cannot make a moving estimate.
    full_detections : int
        Detections at which the evidence factor reaches 1.
    static_changed : float
        Share of scale-1 receptors with a nonzero state below which a textured scene with
        too few detections counts as static.
    static_noise_ratio : float
        With the contrast-adaptive threshold, a textured scene with too few detections also
        counts as static when its scale-5 receptors changed at less than this times the
        scale-1 rate: the changes are sensor noise, not motion (see :func:`_looks_static`;
        0 turns the test off).
    huber_fraction, huber_floor : float
        Huber threshold of the IoC fit: ``max(floor, fraction · |F|)`` px/frame
        (the detector's speed bands are relative: scale ``k`` fires from ~k/2 to ~1.5k).
    iterations : int
        IRLS iterations of the IoC fit when it is the answer (uncalibrated channels).
    guess_iterations : int
        IRLS iterations of the IoC fit when it only starts the likelihood search.
    likelihood : bool
        Refine the IoC guess by calibrated maximum likelihood (method step 2). Ignored
        (IoC only) when no calibration table matches the channel set.
    max_axis_angle : float
        Degrees; histogram rows whose gradient normal is further than this from the
        detector's axis are left out of the likelihood.
    outlier_probability : float
        Probability mass spread uniformly over all codes in the likelihood (robustness to
        detections the table does not explain: other motion, flicker, noise).
    overdispersion : float
        Factor on the curvature-based standard error of the likelihood fit (detections of
        one edge are not independent). Chosen with ``disagreement_weight`` (and
        ``misfit_weight`` kept) for the quality that ranks the error best on flights over
        the calibration textures, both models, four direction and contrast sets
        (README, "Quality weights"); the median ``expected_error`` is then 0.77–0.85× the
        median error there for the extended model and 1.4–1.6× for the paper's (with the
        former 0.7 and 0.5: 1.03–1.21× and 1.3–1.5×).
    disagreement_weight : float
        The expected error gains (in quadrature) this factor times the relative
        difference between the IoC guess and the likelihood fit. It was 0.5 (and
        ``overdispersion`` 0.7) before the weights were re-chosen: it then made most of
        the expected error while predicting the error worst of the three terms.
    quality_error : float
        Expected relative error at which the accuracy factor of the quality is 1/2
        (the factor is ``1 / (1 + (expected_error / quality_error)²)``).
    top_speed : float or None
        Speed (px/frame) above which the fastest scale alone fires and the expected error
        grows; the expected error gains ``(|F| / top_speed − 1) · 0.5`` above it. None:
        11/13 of the fastest channel's speed (11 for the paper's channels, ~12.7 for the
        extended model's scale-15 channel).
    row_exponent : float
        A histogram row (axis, orientation) with ``n`` detections weighs like
        ``n ** row_exponent`` independent detections in the likelihood (1: untempered).
    misfit_weight : float
        The expected error gains (in quadrature) this factor times the *misfit*: the
        summary's :attr:`FlowSummary.deviance` minus the median deviance of the
        calibration flights at the same speed (stored with the table), when positive. A
        texture whose code mixtures the table does not explain (brick's aligned, periodic
        edges: 15–16 % error at 0.5–1 px/frame where the other textures read 2–6 %)
        then gets a lower quality. 0 turns it off (the quality before this term).
    ground : str
        Which calibration tables the likelihood reads. ``"auto"`` (default): the edge
        table, and where the channel set also has a *line-ground* table (measured over
        grids of thin bright lines, ``calibrate_summary fit --ground lines``) that one
        too; the answer is the line table's when it explains the frame's detections
        better by more than ``line_ground_margin``; only for histograms with
        gradient-strength classes (without them lines and edges do not tell apart, so
        ``EngineParams.gradient_classes=False`` reads the edge table alone). ``"edges"``:
        the edge table alone (the summary before line ground was known). ``"lines"``: the
        line table alone (for calibration and diagnosis; a channel set without one reads
        its edge table). Thin lines fire only
        their speed's scale where an edge also fires larger ones, so the edge table
        alone reads them slow (README, "Thin lines read slow").
    line_ground_margin : float
        Log-likelihood (nats, over the tempered detections) by which the line table must
        beat the edge table: the log prior odds against line ground. 5 was chosen on
        validation flights over grounds that neither calibration nor the evaluation flew
        over (``calibrate_summary margin``, recipe in its docstring): the rough and
        step-edge grounds keep their accuracy at every margin from 0 to 30, the turned line
        grids gain most from 0 to 5; above 0 the edge table, which natural ground is
        closer to, keeps the benefit of the doubt.
    search_climbs : int
        How often the likelihood search's coarse level (±0.45 in log speed and ±24° around
        the IoC guess) is centred on its best candidate and searched again while that lies
        on its edge: in its fastest row or its outermost directions (0 to 8; 2: its rows
        reach 3.9× the guess instead of 1.57×). The guess under-reads fast flow off the
        axes (0.59× the truth at 13 px/frame 10–60° past an axis, modulo 90°, extended
        model, 320×240), and the search without climbs (0, as before) stopped short of it
        (README, "The search's reach"). A frame whose best coarse candidate is inside the
        grid is searched exactly as without climbs.
    """

    min_textured: float = 0.01
    full_textured: float = 0.10
    max_saturated: float = 0.5
    min_detections: int = 20
    full_detections: int = 400
    static_changed: float = 0.002
    static_noise_ratio: float = 0.05
    huber_fraction: float = 0.15
    huber_floor: float = 0.3
    iterations: int = 12
    guess_iterations: int = 2
    likelihood: bool = True
    max_axis_angle: float = 60.0
    outlier_probability: float = 0.01
    overdispersion: float = 2.0
    disagreement_weight: float = 0.1
    quality_error: float = 0.15
    top_speed: float | None = None
    row_exponent: float = 0.5
    misfit_weight: float = 0.3
    ground: str = "auto"
    line_ground_margin: float = 5.0
    search_climbs: int = 2

    def __post_init__(self):
        if self.ground not in GROUNDS:
            raise ValueError(f"SummaryOptions(ground={self.ground!r}): expected one of "
                             f"{', '.join(map(repr, GROUNDS))}")
        # each with the range it is meaningful in (a zero divides, a NaN spreads into
        # every summary): (name, low, low inclusive, high, high inclusive)
        ranges = (
            # (no texture at all is never a static textured scene, and without a detection
            # there is no moving estimate: min_textured 0 called a blank frame static,
            # min_detections 0 never called a static scene static)
            ("min_textured", 0.0, False, 1.0, True), ("full_textured", 0.0, False, 1.0, True),
            ("max_saturated", 0.0, True, 1.0, True), ("min_detections", 1, True, math.inf, False),
            ("full_detections", 0, False, math.inf, False), ("static_changed", 0.0, True, 1.0, True),
            ("static_noise_ratio", 0.0, True, 1.0, True),
            ("huber_fraction", 0.0, False, math.inf, False), ("huber_floor", 0.0, False, math.inf, False),
            ("iterations", 1, True, math.inf, False), ("guess_iterations", 1, True, math.inf, False),
            # (no bin's normal is nearer an axis than half a bin, 90° / ORIENTATION_BINS: a
            # smaller angle kept no bin, and summarize() failed in a reshape)
            ("max_axis_angle", 90.0 / ORIENTATION_BINS, False, 90.0, True),
            ("outlier_probability", 0.0, False, 1.0, False),
            ("overdispersion", 0.0, True, math.inf, False), ("disagreement_weight", 0.0, True, math.inf, False),
            ("quality_error", 0.0, False, math.inf, False),
            ("row_exponent", 0.0, False, 1.0, True), ("misfit_weight", 0.0, True, math.inf, False),
            ("line_ground_margin", -math.inf, False, math.inf, False),
        )
        for name, lo, lo_in, hi, hi_in in ranges:
            value = getattr(self, name)
            ok = (_is_real(value)
                  and (value >= lo if lo_in else value > lo) and (value <= hi if hi_in else value < hi))
            if not ok:
                raise ValueError(f"SummaryOptions({name}={value!r}): expected a number "
                                 f"{'≥' if lo_in else '>'} {lo:g}"
                                 + (f" and {'≤' if hi_in else '<'} {hi:g}" if math.isfinite(hi) else ""))
        for name in ("iterations", "guess_iterations"):
            # (loop counts: 1.5 iterations passed the range test, then broke range() in summarize())
            if not _is_whole(getattr(self, name)):
                raise ValueError(f"SummaryOptions({name}={getattr(self, name)!r}): expected a whole number")
        if not isinstance(self.likelihood, (bool, np.bool_)):  # ("no" counted as True)
            raise ValueError(f"SummaryOptions(likelihood={self.likelihood!r}): expected True or False")
        if not (_is_whole(self.search_climbs) and 0 <= self.search_climbs <= 8):
            raise ValueError(f"SummaryOptions(search_climbs={self.search_climbs!r}): expected a whole number "
                             "from 0 to 8")
        if self.top_speed is not None and not (_is_real(self.top_speed) and self.top_speed > 0):
            raise ValueError(f"SummaryOptions(top_speed={self.top_speed!r}): expected None or a number > 0 "
                             "(px/frame)")


_DEFAULT_OPTIONS = SummaryOptions()
_BLIND = FlowSummary()


def _options(options) -> SummaryOptions:
    """``options``, or the defaults for None; anything else is a TypeError (a dict of
    options, say, is not taken for "no options")."""
    if options is None:
        return _DEFAULT_OPTIONS
    if not isinstance(options, SummaryOptions):
        raise TypeError(f"options: expected SummaryOptions or None, not {type(options).__name__}")
    return options


# ---------------------------------------------------------------------------------------
# Step 1: intersection of constraints (initial guess, and the fallback)
# ---------------------------------------------------------------------------------------
class _Constraints:
    """Per histogram bin (flat index of ``hist[axis, code, bin]``): the constraint's
    normal (cos, sin), right-hand side and the products the normal equations sum."""

    def __init__(self, params: EngineParams):
        phi = EngineParams.orientation_centres()
        cos, sin = np.cos(phi), np.sin(phi)
        speeds = np.asarray(params.speeds)
        n_codes = 2 * len(speeds)
        signed = np.repeat(speeds, 2) * np.tile([1.0, -1.0], len(speeds))  # code 2c / 2c+1
        nx = np.broadcast_to(cos, (2, n_codes, cos.size)).ravel()
        ny = np.broadcast_to(sin, (2, n_codes, sin.size)).ravel()
        axis_component = np.stack([np.broadcast_to(cos, (n_codes, cos.size)),
                                   np.broadcast_to(sin, (n_codes, sin.size))])
        rhs = (signed[None, :, None] * axis_component).ravel()
        # rows: nx, ny, -rhs (residual = [U, V, 1] @ rows) and the normal-equation products
        self.lin = np.ascontiguousarray(np.stack([nx, ny, -rhs]).T)  # (bins, 3)
        self.products = np.ascontiguousarray(
            np.stack([nx * nx, nx * ny, ny * ny, nx * rhs, ny * rhs]).T)  # (bins, 5)


_CONSTRAINTS: dict = {}


def _constraints(params: EngineParams) -> _Constraints:
    # (by channel set alone: the constraints depend on the channels' speeds, and a key of
    # the whole parameter set kept one copy per threshold, prefilter, ... ever used)
    hit = _CONSTRAINTS.get(params.channels)
    if hit is None:
        hit = _CONSTRAINTS[params.channels] = _Constraints(params)
    return hit


def _robust_fit(cons: _Constraints, used: np.ndarray, w0: np.ndarray, opts: SummaryOptions,
                iterations: int):
    """Huber IRLS for ``F`` minimising Σ w ρ(n·F − rhs) over the bins ``used`` with counts
    ``w0``; returns (U, V, inlier share, geometry) or None when ``F`` is not determined."""
    lin = cons.lin.take(used, axis=0)
    prod = cons.products.take(used, axis=0)
    w = w0
    U = V = 0.0
    uv1 = np.array([0.0, 0.0, 1.0])
    total = float(w0.sum())
    geometry = None
    for it in range(iterations + 1):
        sxx, sxy, syy, bx, by = w @ prod
        det = sxx * syy - sxy * sxy
        trace = sxx + syy
        if det <= 1e-9 * max(1.0, trace * trace):
            return None
        if geometry is None:  # of the unweighted evidence: 1 = isotropic, 0 = one direction
            geometry = 2.0 * math.sqrt(det) / trace
        U_new = (syy * bx - sxy * by) / det
        V_new = (sxx * by - sxy * bx) / det
        converged = it > 0 and abs(U_new - U) + abs(V_new - V) < 1e-3 * max(1.0, abs(U) + abs(V))
        U, V = U_new, V_new
        uv1[0], uv1[1] = U, V
        res = np.abs(lin @ uv1)
        c = max(opts.huber_floor, opts.huber_fraction * math.hypot(U, V))
        if converged or it == iterations:
            break
        w = w0 * np.minimum(1.0, c / np.maximum(res, 1e-12))
    inliers = float(w0 @ (res <= c)) / max(1e-12, total)
    return U, V, inliers, geometry


# ---------------------------------------------------------------------------------------
# Step 2: calibrated maximum likelihood
# ---------------------------------------------------------------------------------------
#: Directions of the likelihood search are multiples of 360° / _DIRECTIONS (0.25°); the
#: per-row geometry of every such direction is tabulated once.
_DIRECTIONS = 1440
_DIR_STEP = 2.0 * math.pi / _DIRECTIONS
#: Padding of the direction tables (more than the widest search span).
_PAD = 160
#: Coarse-to-fine search: (± log-speed span, direction step in _DIRECTIONS units, points
#: per axis). Level 0 spans ±0.45 in log speed and ±24° around the IoC guess; while its
#: best candidate is on its edge — in its fastest row or its outermost directions — it is
#: centred there and searched again, at most ``SummaryOptions.search_climbs`` times (2:
#: its rows then reach 3.9× the guess instead of 1.57×, its directions ±72°), because
#: the guess under-reads fast flow off the axes (extended model, 320×240, flights 10–60°
#: past an axis, modulo 90°: median guess / true speed 0.71 at 9 px/frame, 0.59 at 13;
#: 0.91–0.99 along the axes) and a search that stops at 1.57× the guess cannot reach the
#: truth there; the extended model's guess (from its channels without their gradient
#: classes) is also crude in direction at 9–11 px/frame. The slowest row's inner cells are
#: no edge (climbing from them too changed no figure of five evaluation sets; its corners,
#: in the outermost directions, do climb, so the rows can also reach down to 0.26× the
#: guess). The finer levels are refined by a parabola through the best point and its
#: neighbours. Each level takes the rows' β at its centre, so the fine level runs twice:
#: the second time centred on (and with β from) the first one's answer, which removes
#: most of the pull towards the coarse level's β (extended model, random directions:
#: 2.37° → 2.22°).
_SEARCH_LEVELS = ((0.45, 32, 7), (0.12, 6, 7), (0.12, 6, 7))
#: Level whose grid gives the curvature of the log-likelihood (expected error).
_CURVATURE_LEVEL = 1


def _parabola_weights(m: int) -> np.ndarray:
    """Weights giving the quadratic coefficient of a least-squares parabola through m
    equally spaced points at unit spacing (``a = weights @ y``)."""
    x = np.arange(m) - (m - 1) / 2.0
    z = x * x - np.mean(x * x)
    return z / np.dot(z, z)


class _LikelihoodModel:
    """The calibration table laid out per histogram row, for one (table, options) pair.

    Base rows are the usable ``axis · 64 + orientation bin`` (``R`` of them); each has one
    histogram row per gradient-strength class of the table. ``logp[(row · classes +
    class) · codes + code, β node · U + j]`` is the log-probability of ``code`` for ``|c|``
    at u-node ``j`` (for ``c < 0`` the counts are read with their codes' signs swapped,
    ``hist_index[row, 1]``). Per search direction ``d`` (0.25° steps) and base row:
    ``absg[d]`` = |c| / |F| (``c = F · n / n_a``), ``neg_u[d]`` U where ``c < 0`` (else 0), and
    ``bi[d]``, ``bf[d]`` the β node below the row's β and the weight of the node above. A
    frame only gathers the curves of its nonzero counts.
    """

    def __init__(self, table: dict, max_axis_angle: float, outlier: float, params: EngineParams):
        prob = np.asarray(table["prob"], np.float64)  # ([class,] ψ, β, u, category)
        # the diagonal detectors' table (EngineParams.diagonal_evidence), same layout
        prob_diagonal = np.asarray(table.get("prob_diagonal", prob), np.float64)
        steps = tuple(int(m) for m in np.asarray(table.get("gradient_class_steps", ())).ravel())
        if not steps:
            prob = prob[None]
            prob_diagonal = prob_diagonal[None]
        self.classes = n_classes = prob.shape[0]
        if n_classes != len(steps) + 1 and steps:
            raise ValueError("calibration table: class dimension does not match its class steps")
        psi_nodes = np.asarray(table["psi_nodes_deg"], np.float64)
        beta_nodes = np.asarray(table["beta_nodes"], np.float64)
        u_nodes = np.asarray(table["u_nodes"], np.float64)
        self.u_offset = float(table["u_offset"])
        # speeds below half the slowest channel's are not resolved (0.5 px/frame for the
        # paper's channels): the floor of the search's start and of the disagreement
        self.speed_floor = 0.5 * float(min(params.speeds))
        self.u0 = float(u_nodes[0])
        self.du = float(u_nodes[1] - u_nodes[0])
        self.n_u = n_u = len(u_nodes)
        n_cat = prob.shape[-1]
        phi = EngineParams.orientation_centres()
        cos, sin = np.cos(phi), np.sin(phi)
        n_axes = params.evidence_axes
        nx = np.tile(cos, n_axes)
        ny = np.tile(sin, n_axes)
        # signed component of the normal along each axis's detector step: a diagonal
        # detector's step is (1, ±1), so its crossing speed c = n·F / (n_x ± n_y) is in
        # steps per frame, the unit its channels fire in (scale k at about k steps a frame)
        na, psi = (a.ravel() for a in EngineParams.crossing_geometry(range(n_axes)))
        diagonal = np.repeat(np.arange(n_axes) >= 2, phi.size)
        self.rows = rows = np.nonzero(psi < max_axis_angle)[0]
        self.n_base = n_rows = rows.size
        i = np.clip(np.searchsorted(psi_nodes, psi, side="right") - 1, 0, len(psi_nodes) - 2)
        f = ((psi - psi_nodes[i]) / (psi_nodes[i + 1] - psi_nodes[i]))[:, None, None, None]
        self.n_beta = n_beta = prob.shape[2]
        logp = []
        for pc, pd in zip(prob, prob_diagonal):
            p_row = (1.0 - f) * pc[i] + f * pc[i + 1]  # (row, β, u, category)
            if n_axes > 2:
                p_row[diagonal] = ((1.0 - f) * pd[i] + f * pd[i + 1])[diagonal]
            p_row = (1.0 - outlier) * p_row + outlier / n_cat
            # (row, code, β node · U + u): log-probability of a code for c > 0; for c < 0
            # the category is the code with its sign flipped, so the curves of c < 0 come
            # from the counts with codes swapped (code ^ 1) against the same table
            logp.append(np.log(p_row)[rows].transpose(0, 3, 1, 2).reshape(n_rows, n_cat, -1))
        # (base row · classes · codes, β node · U): one curve per (row, class, code),
        # base-row-major so a frame's nonzero counts come out sorted by (base row, sign)
        # (plus a row of zeros at the end: the padding of _weighted_row_sums' numpy path)
        logp = np.stack(logp, axis=1).reshape(n_rows * n_classes * n_cat, -1)
        self.logp = np.concatenate([logp, np.zeros((1, logp.shape[1]))]).astype(np.float32)
        # where each (base row, sign, class, code) count is in hist.ravel()
        # (hist[axis, code, class · 64 + bin]); sign 1 reads the codes swapped (code ^ 1)
        n_bins = phi.size
        axis, b = np.divmod(rows, n_bins)
        codes = np.arange(n_cat)
        index = [(axis[:, None] * n_cat + codes[None, :]) * (n_classes * n_bins) + c * n_bins + b[:, None]
                 for c in range(n_classes)]
        index = np.stack(index, axis=1)  # (R, C, codes)
        self.hist_index = np.stack([index, index[:, :, codes ^ 1]], axis=1).reshape(n_rows, 2, -1)
        self.n_cat = n_cat
        self.hist_bins = n_classes * n_bins
        # tables with equal layouts gather a histogram's counts the same way (the line-
        # ground table and the edge table of one channel set): a frame's gathering is shared
        self.layout = (n_classes, n_cat, rows.tobytes())
        # per-direction geometry of the base rows, padded by _PAD directions on both sides
        # (index d + _PAD is direction d, for d in -_PAD .. _DIRECTIONS + _PAD)
        ang = (np.arange(_DIRECTIONS + 2 * _PAD) - _PAD) * _DIR_STEP
        ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
        vn = ca * nx[rows] + sa * ny[rows]  # (D, R) normal speed per unit flow
        g = vn / na[rows]
        self.absg = np.abs(g).astype(np.float32)
        # c < 0 reads the second half (n_u entries on) of a row's curves
        self.neg_u = np.where(g < 0, n_u, 0).astype(np.intp)
        beta = np.sqrt(np.clip(1.0 - vn * vn, 0.0, 1.0))
        bi = np.clip(np.searchsorted(beta_nodes, beta, side="right") - 1, 0, n_beta - 2)
        self.bi = bi.astype(np.int32)
        # where each row's curves start in a frame's curves with every base row present
        # (a table without classes): the β-node row of (row, sign) and the u offset of row
        self.first_all = (np.arange(n_rows)[:, None] * 2 + np.arange(2)[None, :]) * n_beta
        self.jrow_all = np.arange(n_rows) * (2 * n_u)
        self.bf = ((beta - beta_nodes[bi]) / (beta_nodes[bi + 1] - beta_nodes[bi])).astype(np.float32)
        self.inv_du = np.float32(1.0 / self.du)
        self.u0_du = np.float32(self.u0 / self.du)
        self.u_top = np.float32(n_u - 1 - 1e-3)
        # search grids: (log-speed offsets, direction step, its offsets, exp(offsets),
        # padded direction offsets)
        self.levels = []
        for dl, dstep, m in _SEARCH_LEVELS:
            ls = np.linspace(-dl, dl, m)
            doff = (np.arange(m) - (m - 1) // 2) * dstep
            self.levels.append((ls, doff, dstep, np.exp(ls).astype(np.float32), doff + _PAD))
        self.parabola = [_parabola_weights(m) for _, _, m in _SEARCH_LEVELS]
        # the deviance the calibration flights themselves show, against log speed (tables
        # without it: no misfit term)
        self.misfit_log_speeds = self.misfit_baseline = None
        if "misfit_speeds" in table and "misfit_baseline" in table:
            self.misfit_log_speeds = np.log(np.asarray(table["misfit_speeds"], np.float64))
            self.misfit_baseline = np.asarray(table["misfit_baseline"], np.float64)

    def misfit(self, deviance: float, speed: float) -> float:
        """Deviance per detection beyond what calibration flights at this speed show."""
        if self.misfit_baseline is None:
            return 0.0
        base = np.interp(math.log(max(speed, 1e-3)), self.misfit_log_speeds, self.misfit_baseline)
        return max(0.0, deviance - float(base))


#: The likelihood models built so far, most recently used last (see :func:`_model_for`).
_MODEL_CACHE: "collections.OrderedDict" = collections.OrderedDict()
#: Models :func:`_model_for` keeps (channel sets without a table, None, are not counted):
#: an extended model is ~180 MB and takes ~1 s to build, and its key holds two float
#: options (``max_axis_angle``, ``outlier_probability``), so a sweep over them kept every
#: one (RSS 103 -> 885 MB over four values); one estimator needs two (its edge and line
#: tables), a process with both models three (the paper's has no line table).
MODEL_CACHE_SIZE = 4
_CALIBRATION: dict = {}


def _load_calibrations() -> list:
    """All calibration tables next to this module (the paper's first), each as a dict of
    arrays plus ``"_path"``."""
    if "tables" not in _CALIBRATION:
        paths = [CALIBRATION_FILE] + sorted(
            p for p in CALIBRATION_FILE.parent.glob(CALIBRATION_GLOB) if p != CALIBRATION_FILE)
        tables = []
        for path in paths:
            if not path.is_file():
                continue
            with np.load(path) as z:
                table = {k: z[k] for k in z.files}
            table["_path"] = path
            tables.append(table)
        _CALIBRATION["tables"] = tables
    return _CALIBRATION["tables"]


def _table_matches(table: dict, params: EngineParams, ground: str = "edges"):
    """None when ``table`` is not for these channels or not for this ``ground``, else its
    rank (0 = also made with this threshold mode, 1 = another or unrecorded mode)."""
    if (str(table["ground"]) if "ground" in table else "edges") != ground:
        return None
    if "channels" in table:
        channels = tuple((int(k), int(d)) for k, d in np.asarray(table["channels"]))
        if channels != tuple(params.channels):
            return None
    elif tuple(params.speeds) != tuple(float(s) for s in table["speeds"]):
        return None  # the paper's table names its channel speeds only
    if np.asarray(table["prob"]).shape[-1] != 2 * len(params.channels):
        return None
    if ("prob_diagonal" in table) != params.diagonal_evidence:
        return None  # the diagonal detectors need their own table, and only they use it
    steps = tuple(int(m) for m in np.asarray(table.get("gradient_class_steps", ())).ravel())
    if steps and steps != GRADIENT_CLASS_STEPS:
        return None  # made for other gradient-strength classes than the engine's
    mode = str(table["threshold_mode"]) if "threshold_mode" in table else None
    return 0 if mode == params.threshold_mode else 1


def calibration_for(params: EngineParams, ground: str = "edges"):
    """Path of the (edge) calibration table :func:`summarize` uses for ``params``, or None
    when none matches its channel set (the summary is then the IoC fit alone).

    A table must be for exactly ``params.channels``; among those, one made with the same
    ``threshold_mode`` is preferred. ``ground="lines"`` asks for the channel set's
    line-ground table instead (None when it has none; see :attr:`SummaryOptions.ground`)."""
    if ground not in GROUNDS[1:]:
        raise ValueError(f"calibration_for(ground={ground!r}): expected 'edges' or 'lines'")
    table = _calibration_table(params, ground)
    return None if table is None else table["_path"]


def _calibration_table(params: EngineParams, ground: str = "edges"):
    """The table :func:`calibration_for` names, as loaded (a dict of arrays), or None."""
    best = None
    for table in _load_calibrations():
        rank = _table_matches(table, params, ground)
        if rank is not None and (best is None or rank < best[0]):
            best = (rank, table)
    return None if best is None else best[1]


class CalibrationWarning(UserWarning):
    """:func:`summarize` reads a calibration table measured with other engine settings than
    the field's (:func:`calibration_mismatch`): its error is then larger and unmeasured."""


def table_settings(table: dict) -> dict:
    """The engine settings (:meth:`EngineParams.calibration_settings`) a calibration table
    was measured with: as it records them (``engine_settings``, written by
    ``calibrate_summary fit``), else those of the model it names (the paper's when it names
    none) with its threshold mode — the shipped tables were all fitted on the recipe's
    flights, which fly the models' defaults."""
    if "engine_settings" in table:
        return dict(json.loads(str(table["engine_settings"])))
    model = str(table["model"]) if "model" in table else "paper"
    options = dict(MODELS.get(model, {}))
    if "threshold_mode" in table:
        options["threshold_mode"] = str(table["threshold_mode"])
    return EngineParams(**options).calibration_settings()


def calibration_mismatch(params: EngineParams, ground: str = "edges") -> dict:
    """The settings in which ``params`` differ from those the calibration table of
    :func:`calibration_for` was measured with, as ``{name: (table's, params')}``; empty when
    they agree or when no table serves these channels (the summary is then the IoC fit).

    The table still serves (it is chosen by channel set, diagonal evidence and, where there
    is a choice, threshold mode), but each of these settings moves the mix of scales that
    fires at a given speed: on the evaluation's random flights at 320×240 the paper's model
    reads 6.3 % / 1.9° median error with the threshold of its table (5), 9.9 % / 2.2° at
    threshold 10 and 10.7 % / 2.8° without the prefilter (README, "Calibration settings").
    A different threshold mode is reported alone (its settings do not compare)."""
    table = _calibration_table(params, ground)
    if table is None:
        return {}
    theirs, ours = table_settings(table), params.calibration_settings()
    if theirs.get("threshold_mode") != ours["threshold_mode"]:
        return {"threshold_mode": (theirs.get("threshold_mode"), ours["threshold_mode"])}
    return {name: (theirs.get(name), value) for name, value in ours.items() if theirs.get(name) != value}


def mismatch_text(mismatch: dict, joiner: str = " ") -> str:
    """``name<joiner>value (table: value), …`` of a :func:`calibration_mismatch` result."""
    return ", ".join(f"{name}{joiner}{given!r} (table: {table!r})" for name, (table, given) in mismatch.items())


@functools.lru_cache(maxsize=64)
def warn_if_uncalibrated(params: EngineParams) -> dict:
    """Warn once per parameter set and process (the cache) that its edge table was measured
    with other settings, and return them (:func:`calibration_mismatch`); :func:`summarize`
    calls it. A caller that reports the mismatch its own way (the daemon, in its log) calls
    it first under a ``warnings.catch_warnings()`` that ignores :class:`CalibrationWarning`:
    the set then counts as told, and the summaries stay quiet."""
    mismatch = calibration_mismatch(params)
    if mismatch:
        warnings.warn(f"summarize(): the calibration table {calibration_for(params).name} was measured with "
                      f"other engine settings than the field's: {mismatch_text(mismatch)}; the summary's "
                      "error with these settings is larger and unmeasured (README, \"Calibration settings\")",
                      CalibrationWarning, stacklevel=3)
    return mismatch


def _model_for(params: EngineParams, opts: SummaryOptions, ground: str = "edges"):
    """The likelihood model for these channels and ground, or None when they have no table."""
    # What the model depends on: the table (chosen by channels, diagonal evidence and
    # threshold mode) and the channels' speeds and axes. The whole parameter set as the key
    # kept a model (~180 MB for the extended one) per threshold, row step, ... ever used.
    key = (params.channels, params.diagonal_evidence, params.threshold_mode, opts.max_axis_angle,
           opts.outlier_probability, ground)
    if key in _MODEL_CACHE:
        _MODEL_CACHE.move_to_end(key)
        return _MODEL_CACHE[key]
    table = _calibration_table(params, ground)
    model = None
    if table is not None:
        edges = np.asarray(table.get("contrast_edges", ()), np.float64)
        prob = np.asarray(table["prob"])
        # ([contrast class,] [gradient class,] ψ, β, u, category); a table with gradient-
        # strength classes also holds the all-classes table ``prob_all`` (for histograms
        # without classes, e.g. made by hand)
        by_class = "gradient_class_steps" in table
        plain = 5 if by_class else 4
        split = lambda a, ndim: [a] if a.ndim == ndim else list(a)  # noqa: E731  (per contrast class)
        # (the diagonal detectors' tables, when the table has them, are split alike)
        diagonal = "prob_diagonal" in table
        per_class = split(prob, plain)
        per_class_d = split(np.asarray(table["prob_diagonal"]), plain) if diagonal else [None] * len(per_class)
        if by_class:
            folded = split(np.asarray(table["prob_all"]), 4)
            folded_d = (split(np.asarray(table["prob_all_diagonal"]), 4) if diagonal
                        else [None] * len(folded))
        else:
            folded, folded_d = per_class, per_class_d
        bare = {k: v for k, v in table.items() if k not in ("gradient_class_steps", "prob_diagonal")}

        def build(t, p, pd):
            t = dict(t, prob=p)
            if pd is not None:
                t["prob_diagonal"] = pd
            return _LikelihoodModel(t, opts.max_axis_angle, opts.outlier_probability, params)

        model = (edges, [(build(table, p, pd) if by_class else None, build(bare, f, fd))
                         for p, pd, f, fd in zip(per_class, per_class_d, folded, folded_d)])
    _MODEL_CACHE[key] = model
    built = [k for k, m in _MODEL_CACHE.items() if m is not None]  # (oldest first)
    for old in built[:max(0, len(built) - MODEL_CACHE_SIZE)]:
        del _MODEL_CACHE[old]
    while len(_MODEL_CACHE) > 16 * MODEL_CACHE_SIZE:  # (the Nones too, in the long run)
        _MODEL_CACHE.popitem(last=False)
    return model


def _pick_model(models, field: FlowField):
    """The class of a table with scene-contrast classes (``contrast_edges`` on the mean
    gradient ``g`` of the frame, gray levels) that ``field`` falls in."""
    edges, per_class = models
    if not edges.size:
        return per_class[0]
    h, w = field.shape
    g = float(field.stats[STAT_CONTRAST]) / max(1, EngineParams.contrast_samples(w, h))
    return per_class[int(np.searchsorted(edges, g, side="right"))]


def _classes_summed(hist: np.ndarray) -> np.ndarray:
    """The detection histogram with its gradient-strength classes added up (what the IoC
    guess and a table without classes read); itself when it has no classes."""
    if hist.shape[-1] == ORIENTATION_BINS:
        return hist
    return hist.reshape(hist.shape[0], hist.shape[1], -1, ORIENTATION_BINS).sum(axis=2)


def _model_of(field: FlowField, opts: SummaryOptions, ground: str = "edges"):
    """The likelihood model :func:`summarize` fits ``field`` with, or None (IoC only): the
    table of the field's channels and ``ground``, its scene-contrast class, with
    gradient-strength classes when the histogram has them."""
    models = _model_for(field.params, opts, ground) if opts.likelihood else None
    if models is None:
        return None
    by_class, folded = _pick_model(models, field)
    return by_class if by_class is not None and by_class.hist_bins == field.histogram.shape[-1] else folded


def _row_curves(model: _LikelihoodModel, hist: np.ndarray, exponent: float, gathered=None):
    """Log-likelihood curves of one frame's base rows with detections, shape
    ((active rows · 2 + sign) · β nodes, U) (sign 0: c > 0, 1: c < 0), with those base
    rows, the detection count, the number of active (row, gradient class) rows, the
    saturated model and what was gathered from ``hist`` for a table with gradient classes
    (None without): passed back as ``gathered`` with another table of the same
    :attr:`_LikelihoodModel.layout` and the same histogram and exponent, it saves gathering
    the counts again (the curves come out the same bit for bit).

    With ``exponent`` < 1 a row of ``n`` detections weighs ``n ** exponent`` (its counts
    are scaled by ``n ** (exponent − 1)``): neighbouring detections are not independent.
    The gradient classes of one base row share its geometry, so their curves add up. Only
    the nonzero counts are gathered (a few hundred of the table's rows per frame)."""
    if gathered is not None and gathered[0] == model.layout:
        _, count, active, fit, table_rows, vals, group_sizes, base = gathered
        curves = (_weighted_row_sums(model.logp, table_rows, vals, group_sizes) if base.size
                  else np.zeros((0, model.logp.shape[1]), np.float32))
        return (_frame_of_rows(model, curves.reshape(-1, model.n_u), base), count, active, fit,
                gathered)
    C, n_cat = model.classes, model.n_cat
    h = hist.ravel().take(model.hist_index)  # (R, 2, classes · codes)
    n_row = np.add.reduce(h[:, 0, :].reshape(-1, C, n_cat), axis=2).ravel()  # (R · C,)
    count = float(np.add.reduce(n_row))
    active = int(np.count_nonzero(n_row))
    # per (row, class) weight n ** (exponent - 1) of its counts, 0 for empty rows
    row_weight = np.where(n_row > 0, np.maximum(n_row, 1.0) ** (exponent - 1.0), 0.0)
    fit = _Saturated(h[:, 0, :], n_row, row_weight, n_cat)
    if C == 1:  # a table without gradient classes: one dense batched product, all rows
        w = h.astype(np.float32)
        if exponent != 1.0:
            w *= row_weight.astype(np.float32)[:, None, None]
        curves = np.matmul(w, model.logp[:-1].reshape(model.n_base, n_cat, -1))
        frame = (curves.reshape(-1, model.n_u), None, model.first_all, model.jrow_all)
        return frame, count, active, fit, None
    # (np.flatnonzero of a boolean mask: ~3x faster than of the int64 counts)
    flat = np.flatnonzero(h != 0)  # sorted by (base row, sign, class, code)
    if flat.size == 0:
        base = np.zeros(0, np.intp)
        empty = _frame_of_rows(model, np.zeros((0, model.n_u), np.float32), base)
        return empty, count, active, fit, (model.layout, count, active, fit, None, None, None, base)
    per_sign = C * n_cat
    key, within = np.divmod(flat, per_sign)  # key = base row · 2 + sign
    raw = h.ravel().take(flat)
    vals = raw.astype(np.float32)
    if exponent != 1.0:  # row_weight, raised in float32 as before (the same curves bit for bit)
        weight32 = np.maximum(n_row, 1).astype(np.float32) ** np.float32(exponent - 1.0)  # per (row, class)
        vals *= weight32.take((key >> 1) * C + within // n_cat)
    table_rows = (key >> 1) * per_sign + within
    # sign 0's entries are the counts themselves (what the deviance reads)
    sign0 = (key & 1) == 0
    fit.nonzero, fit.nonzero_counts = table_rows[sign0], raw[sign0]
    # one output row per (active base row, sign), both signs of a row present
    per_key = np.bincount(key, minlength=2 * model.n_base).reshape(-1, 2)
    base = np.flatnonzero(per_key.any(axis=1))
    group_sizes = per_key[base].ravel()
    gathered = (model.layout, count, active, fit, table_rows, vals, group_sizes, base)
    return _frame_of_rows(model, _weighted_row_sums(model.logp, table_rows, vals, group_sizes)
                          .reshape(-1, model.n_u), base), count, active, fit, gathered


class _Saturated:
    """What the model's misfit is measured against: the tempered log-likelihood of the
    *saturated* model (each (row, class) its own observed code mixture),
    ``Σ w_row Σ_codes n log(n / n_row)``, and the tempered detection count ``Σ w_row n_row``.
    Computed from the rows' counts (sign 0: the counts are the same for both signs);
    ``nonzero`` and ``nonzero_counts``, when the caller has them, the flat indices and
    values of the nonzero counts."""

    __slots__ = ("counts", "n_row", "row_weight", "n_cat", "nonzero", "nonzero_counts")

    def __init__(self, counts, n_row, row_weight, n_cat):
        self.counts, self.n_row, self.row_weight, self.n_cat = counts, n_row, row_weight, n_cat
        self.nonzero = self.nonzero_counts = None

    def deviance(self, loglik: float) -> float:
        """Per tempered detection: ``(saturated − loglik) / Σ w n``, ≥ 0 (0 = the table's
        mixtures at the answer are exactly the observed ones)."""
        nz, n = self.nonzero, self.nonzero_counts
        if nz is None:
            c = self.counts.reshape(-1, self.n_cat).ravel()  # (R · C · codes)
            nz = np.flatnonzero(c != 0)
            n = c.take(nz)
        if nz.size == 0:
            return 0.0
        rc = nz // self.n_cat
        n = n.astype(np.float64)
        saturated = float(self.row_weight.take(rc) @ (n * np.log(n / self.n_row.take(rc))))
        weight = float(self.row_weight @ self.n_row)
        return max(0.0, (saturated - loglik) / weight) if weight > 0 else 0.0


def _weighted_row_sums(table: np.ndarray, rows: np.ndarray, weights: np.ndarray,
                       group_sizes: np.ndarray) -> np.ndarray:
    """``out[g] = Σ weights[i] · table[rows[i]]`` over consecutive groups of ``group_sizes``
    entries (a sparse-matrix × dense product). The gradient classes make ~2 000 nonzero
    counts per 640×480 frame, each a 240-entry table row: SciPy's compiled CSR kernel
    takes ~0.04 ms for that, numpy's gather and padded batched ``matmul`` ~0.14 ms."""
    n_groups = group_sizes.size
    out = np.zeros((n_groups, table.shape[1]), np.float32)
    if _CSR_MATVECS is not None:
        indptr = np.zeros(n_groups + 1, np.int64)
        np.cumsum(group_sizes, out=indptr[1:])
        _CSR_MATVECS(n_groups, table.shape[0], table.shape[1], indptr, np.asarray(rows, np.int64),
                     np.asarray(weights, np.float32), table.ravel(), out.ravel())
        return out
    # numpy only: pad every group to the largest with the table's zero row (its last)
    starts = np.cumsum(group_sizes) - group_sizes
    group = np.repeat(np.arange(n_groups), group_sizes)
    slot = np.arange(rows.size) - starts.take(group)
    padded = np.full((n_groups, int(group_sizes.max(initial=0))), table.shape[0] - 1)
    padded_weights = np.zeros(padded.shape, np.float32)
    padded[group, slot] = rows
    padded_weights[group, slot] = weights
    out[:] = np.matmul(padded_weights[:, None, :], table.take(padded, axis=0))[:, 0]
    return out


def _frame_of_rows(model: _LikelihoodModel, curves: np.ndarray, base: np.ndarray):
    """A frame's curves of the base rows ``base`` with their layout, once per frame:
    ``(curves, base, first β-node row of each (row, sign), u offset of each row)``."""
    n_act = base.size
    first = (np.arange(n_act)[:, None] * 2 + np.arange(2)[None, :]) * model.n_beta
    return curves, base, first, np.arange(n_act) * (2 * model.n_u)


def _loglik_grid(model: _LikelihoodModel, frame, log_s: float, d0: int, level):
    """Log-likelihood on one search level around (log speed ``log_s``, direction index
    ``d0``), with each row's β taken at ``d0``: shape (speeds, directions). ``frame`` comes
    from :func:`_row_curves` (``base`` None: every base row, in order)."""
    curves, base, first, jrow = frame
    es, doff = level[3], level[4]
    ds = doff + d0  # tables are padded: no wrap-around
    bi, bf = model.bi[d0 + _PAD], model.bf[d0 + _PAD]
    absg, neg_u = model.absg.take(ds, axis=0), model.neg_u.take(ds, axis=0)  # (directions, R)
    if base is not None:
        bi, bf, absg, neg_u = bi.take(base), bf.take(base), absg.take(base, axis=1), neg_u.take(base, axis=1)
    # the β node below each (row, sign) curve, and the weight of the one above
    bk = (first + bi[:, None]).ravel()
    cur = curves.take(bk, axis=0)  # (A · 2, U) at the β node below ...
    hi = curves.take(bk + 1, axis=0)  # ... and above
    hi -= cur
    per_row = hi.reshape(-1, 2, hi.shape[1])  # (a view: both signs of a row share its β)
    per_row *= bf[:, None, None]
    cur += hi  # β-interpolated curves
    x = np.multiply.outer(es * math.exp(log_s), absg)  # (S, directions, A) |c|
    x += model.u_offset
    np.log(x, out=x)
    x *= model.inv_du
    x -= model.u0_du
    np.clip(x, np.float32(0.0), model.u_top, out=x)
    whole = np.floor(x)
    j = whole.astype(np.intp)
    x -= whole  # (exact in float32, as x − j in float64 was: 0 <= x − j < 1 <= j or j = 0)
    # each (active row, sign) curve is U long; c < 0 reads the row's second half
    j += jrow + neg_u
    lo = cur.take(j)
    j += 1
    hi = cur.take(j)
    hi -= lo
    hi *= x
    lo += hi
    return lo.sum(axis=2)


def _vertex(l0: float, l1: float, l2: float) -> float:
    """Offset (in steps, within ±0.5) of the vertex of the parabola through 3 points."""
    den = l0 - 2.0 * l1 + l2
    if den >= 0.0:
        return 0.0
    return max(-0.5, min(0.5, 0.5 * (l0 - l2) / den))


def _polar(model: _LikelihoodModel, U: float, V: float) -> tuple[float, int]:
    """A flow as the search's coordinates: (log speed, floored at the model's speed floor;
    index of the nearest tabulated direction)."""
    return (math.log(max(math.hypot(U, V), model.speed_floor)),
            round(math.atan2(V, U) / _DIR_STEP) % _DIRECTIONS)


def _fitted_curves(model: _LikelihoodModel, full: np.ndarray, summed: np.ndarray | None,
                   opts: SummaryOptions, gathered=None):
    """A frame's likelihood curves, saturated model and gathered counts
    (:func:`_row_curves`) when it gets a likelihood fit — at least two active rows and
    ``opts.min_detections`` detections — else None. ``full`` is the histogram, ``summed``
    the same with its gradient classes added up (:func:`_classes_summed`; None: computed
    here when the table needs it); ``gathered``: an earlier call's, on the same frame."""
    if model.classes > 1:
        hist = full
    else:
        hist = _classes_summed(full) if summed is None else summed
    curves, count, active, saturated, gathered = _row_curves(model, hist, opts.row_exponent, gathered)
    if active < 2 or count < opts.min_detections:
        return None
    return curves, saturated, gathered


def _likelihood_fit(model: _LikelihoodModel, curves, U0: float, V0: float, climbs: int):
    """Coarse-to-fine polar search; returns (U, V, σ of log-speed, σ of direction, the
    log-likelihood at the final level's best grid point). ``climbs``: how often the coarse
    level may be re-centred on its best candidate while that lies in its fastest row or
    outermost directions (``SummaryOptions.search_climbs``)."""
    log_s, d = _polar(model, U0, V0)
    sig_s = sig_a = math.inf
    last = len(model.levels) - 1
    for level_index, level in enumerate(model.levels):
        ls, doff = level[0], level[1]
        climbs_left = climbs if level_index == 0 else 0
        while True:
            L = _loglik_grid(model, curves, log_s, d, level)
            bi, bj = divmod(int(np.argmax(L)), L.shape[1])
            if not climbs_left or (bi < L.shape[0] - 1 and 0 < bj < L.shape[1] - 1):
                break
            # the best is on the grid's edge, in its fastest row (the guess reads low) or
            # outermost directions: the flow may lie beyond it
            climbs_left -= 1
            log_s += ls[bi]
            d = (d + int(doff[bj])) % _DIRECTIONS
        if level_index == _CURVATURE_LEVEL:
            weights = model.parabola[level_index]
            sig_s = _curvature_sigma(weights, L[:, bj], ls[1] - ls[0])
            sig_a = _curvature_sigma(weights, L[bi, :], level[2] * _DIR_STEP)
        fs = fa = 0.0
        if level_index > 0:  # sub-step vertex of the likelihood on the fine levels
            if 0 < bi < L.shape[0] - 1:
                fs = _vertex(L[bi - 1, bj], L[bi, bj], L[bi + 1, bj])
            if 0 < bj < L.shape[1] - 1:
                fa = _vertex(L[bi, bj - 1], L[bi, bj], L[bi, bj + 1])
        log_s += ls[bi] + fs * (ls[1] - ls[0])
        if level_index < last:  # the next level is centred on a tabulated direction
            d = (d + int(doff[bj]) + int(round(fa * level[2]))) % _DIRECTIONS
        else:
            d = (d + int(doff[bj])) % _DIRECTIONS
    angle = (d + fa * level[2]) * _DIR_STEP
    s = math.exp(log_s)
    return s * math.cos(angle), s * math.sin(angle), sig_s, sig_a, float(L[bi, bj])


def _curvature_sigma(weights: np.ndarray, prof: np.ndarray, step: float) -> float:
    """Standard error along one axis of a grid of log-likelihoods: 1/sqrt(−L'') from a
    least-squares parabola through the grid's profile at its maximum."""
    half = (prof.size - 1) / 2.0 * step
    a = float(weights @ prof) / (step * step)
    # a flat or convex profile: the data do not pin the maximum within the grid's span
    return 1.0 / math.sqrt(-2.0 * a) if a < -0.5 / half ** 2 else 2.0 * half


def _log_likelihood_at(field: FlowField, flows, options: SummaryOptions | None = None,
                       ground: str = "edges"):
    """The summary's log-likelihood of ``field``'s detections at each global flow ``(U, V)``
    of ``flows`` (px/frame; each row's β read at that flow's own direction) under the table
    of ``ground``, or None when the frame gets no likelihood fit. For diagnosis
    (``calibrate_summary evaluate``): whether a wrong answer is a search that missed a
    better flow, or the table preferring the wrong one."""
    opts = _options(options)
    model = _model_of(field, opts, ground) if field.ready else None
    if model is None:
        return None
    fitted = _fitted_curves(model, field.histogram, None, opts)
    if fitted is None:  # summarize() keeps the IoC fit there
        return None
    curves = fitted[0]
    point = (np.zeros(1), np.zeros(1), 1, np.ones(1, np.float32), np.array([_PAD]))
    values = []
    for U, V in flows:
        log_s, d = _polar(model, U, V)
        values.append(float(_loglik_grid(model, curves, log_s, d, point)[0, 0]))
    return values


def prepare(params: EngineParams, *, options: SummaryOptions | None = None) -> None:
    """Load and lay out now the calibration tables :func:`summarize` reads for ``params``
    (its edge and line-ground tables, every scene-contrast class). The first frame with
    evidence otherwise pays it: on a 2-core x86, ~0.3 s for the extended model without the
    diagonal evidence and ~1 s with it — a second of dropped frames for a daemon that has
    just started streaming. Cheap once done (the models are cached per parameters and
    options)."""
    opts = _options(options)
    if opts.likelihood:
        for ground in GROUNDS[1:]:
            _model_for(params, opts, ground)


# ---------------------------------------------------------------------------------------
#: larger scale whose one-frame receptors tell sensor noise from motion (:func:`_looks_static`)
STATIC_SCALE = 5


def _looks_static(field: FlowField, opts: "SummaryOptions") -> bool:
    """Whether a textured frame with too few detections shows a static scene (flow 0)
    rather than a motion the detector cannot follow (too fast, flicker).

    Static: at most ``opts.static_changed`` of the scale-1 receptors changed; or, with the
    contrast-adaptive threshold (one for the frame, or the local one per tile), the changes are sensor noise — the one-frame receptors of
    the smallest scale >= :data:`STATIC_SCALE` (the largest scale if none is; none if that
    is the finest) changed at less than ``opts.static_noise_ratio`` times the scale-1 rate
    (0 turns this test off). A k×k box sum changes under motion about as readily as one
    receptor (by the motion times the box's summed gradient, against θk²) but averages the
    noise that lights single receptors where the adaptive threshold sits at its floor.
    Measured with the extended model on 320×240 flights (gravel, brick, camera; contrast
    1, 0.5, 0.25; noise σ 2, 3): static scenes changed up to 4.6 % of the scale-1
    receptors (a quarter of the contrast, σ 2: 0.7 %, which read as motion: quality 0
    while hovering) at scale-5 / scale-1 ratios of 0–0.04 frame by frame, and no moving
    flight of 0.25–25 px/frame came here. A fixed threshold (the paper's model) keeps the
    scale-1 test alone: at its floor (0.5–0.6 px/frame at half the contrast, 2 detections a
    frame) the ratio test read most frames of moving brick and gravel flights as static.
    """
    params = field.params
    scales = params.scales  # (sorted by EngineParams)
    if not _has_receptors(field.shape, scales[0]):
        # no receptor of the finest scale fits the frame, so none ever changes: that says
        # nothing about the scene (a 64x4 frame with scales (5,) read static, flow 0 at
        # quality 191, under ground moving 3 px/frame)
        return False
    changed = field.changed_fraction
    fine = changed[params.channels.index((scales[0], 1))]
    if fine <= opts.static_changed:
        return True
    if params.threshold_mode == "fixed":  # (the local threshold's tiles have the same floor)
        return False
    coarse_scale = next((k for k in scales if k >= STATIC_SCALE), scales[-1])
    if coarse_scale == scales[0] or not _has_receptors(field.shape, coarse_scale):
        # (a frame too small for the coarse receptors has none that change: a 64x4 flight
        # moving 2 px/frame read static, flow 0 at quality 191)
        return False
    return changed[params.channels.index((coarse_scale, 1))] < opts.static_noise_ratio * fine


def _has_receptors(shape: tuple[int, int], k: int) -> bool:
    """Whether a frame of ``shape`` holds any receptor of the (odd) scale ``k``: a k×k
    block wholly inside it (``reference.box_sums``)."""
    return min(shape) >= k


def _check_stats(field: FlowField) -> None:
    """ValueError unless the field's ``stats`` are the engine's: one count per ``STAT_*``
    index and channel, none negative, NaN or infinite (a hand-made float array with a NaN
    textured count read as a fully textured frame: NaN fails every comparison)."""
    stats = field.stats
    need = STAT_FIRST_CHANGED + len(field.params.channels)
    if not isinstance(stats, np.ndarray) or stats.shape != (need,) or stats.dtype.kind not in "iuf":
        shape = getattr(stats, "shape", None)
        raise ValueError(f"summarize(): the field's stats are {type(stats).__name__} of shape {shape}, "
                         f"its parameters need ({need},) counts")
    if stats.dtype.kind == "f" and not np.isfinite(stats).all():
        raise ValueError("summarize(): the field's stats hold a NaN or infinite count")
    if (least := stats.min()) < 0:
        raise ValueError(f"summarize(): the field's stats hold a negative count ({least})")


def summarize(field: FlowField, *, options: SummaryOptions | None = None) -> FlowSummary:
    """Global image flow of a :class:`FlowField` with a quality that says how far to trust it.

    Parameters
    ----------
    field : FlowField
        The detector's output for one frame (from :meth:`FlowEstimator.update`).
    options : SummaryOptions, optional
        Thresholds and fit tuning; the defaults are documented in :class:`SummaryOptions`.

    Returns
    -------
    FlowSummary
        ``flow_x, flow_y`` in px/frame (image axes: x right, y down), ``quality``
        0..255 and ``expected_error``. When nothing can be estimated (history filling,
        blank, saturated or texture-less frame, inconsistent evidence) the flow is 0.0
        with quality 0.

    Raises
    ------
    ValueError
        If the field has no summary evidence (``FlowEstimator(..., summary_evidence=False)``),
        or a hand-made field's histogram is not of the shape its parameters give
        ``(evidence_axes, 2 · channels, bins)``, bins being 64 orientations or 256 with the
        gradient-strength classes, or its histogram or ``stats`` (one count per
        ``STAT_*`` index and channel) hold a negative, NaN or infinite count.

    Notes
    -----
    IoC guess refined by calibrated maximum likelihood over the detection histogram; see
    the module docstring and ``docs/spec/template-model.md`` §6.
    """
    opts = _options(options)
    if not isinstance(field, FlowField):
        raise TypeError(f"summarize() takes a FlowField, not {type(field).__name__}")
    field.require_evidence("summarize()")
    if not isinstance(field.histogram, (np.ndarray, np.generic)):  # (a numpy scalar: its shape, below)
        raise ValueError(f"summarize(): the field's histogram is a {type(field.histogram).__name__}, "
                         "not an array (axis, code, bin)")
    counts = field.histogram
    if counts.dtype.kind == "f" and not np.isfinite(counts).all():
        raise ValueError("summarize(): the field's histogram holds a NaN or infinite count")
    if counts.dtype.kind in "if" and counts.size and (least := counts.min()) < 0:
        # (a negative count made the fit's deviance NaN, which read as a perfect fit)
        raise ValueError(f"summarize(): the field's histogram holds a negative count ({least})")
    shape = counts.shape
    if len(shape) == 3 and shape[0] != field.params.evidence_axes:
        raise ValueError(f"summarize(): the field's histogram has {shape[0]} detector axes, "
                         f"its parameters ({'with' if field.params.diagonal_evidence else 'without'} "
                         f"diagonal_evidence) {field.params.evidence_axes}")
    if (len(shape) != 3 or shape[1] != 2 * len(field.params.channels)
            or shape[2] not in (HISTOGRAM_BINS, ORIENTATION_BINS)):  # (classes or not: see _model_of)
        # (a hand-made field's histogram of another shape was an IndexError or a reshape
        # error from inside the fit)
        raise ValueError(f"summarize(): the field's histogram has shape {shape}, its "
                         f"parameters need ({field.params.evidence_axes}, {2 * len(field.params.channels)}, "
                         f"{field.params.histogram_bins}) (axis, code, bin)")
    _check_stats(field)
    if not field.ready or field.exposure_step:
        return _BLIND  # no history yet, or a global brightness step is in the templates
    textured = field.textured_fraction
    if textured < opts.min_textured or field.saturated_fraction > opts.max_saturated:
        return _BLIND
    q_texture = min(1.0, textured / opts.full_textured)
    # the IoC guess (and a table without gradient-strength classes) sums the classes
    full = field.histogram
    hist = _classes_summed(full)
    # the IoC guess and the detection count read the horizontal and vertical detectors (the
    # diagonals of EngineParams.diagonal_evidence feed the likelihood only)
    flat = hist[:2].ravel()
    used = np.flatnonzero(flat != 0)
    counts = flat[used].astype(np.float64)
    n = int(counts.sum())
    params = field.params
    if n < opts.min_detections:
        # Few detections: either the scene is static (below the detector's floor) or the
        # motion is one the detector cannot follow (too fast, flicker): tell them apart by
        # how many receptors changed at all.
        if _looks_static(field, opts):
            return FlowSummary(0.0, 0.0, int(round(255 * q_texture * 0.75)), n, True, 1.0, 0.0)
        return FlowSummary(detections=n)
    if opts.likelihood:
        warn_if_uncalibrated(params)
    model = _model_of(field, opts, "lines") if opts.ground == "lines" else None
    on_lines = model is not None
    if model is None:  # the edge table (also for ground "lines" without a line table)
        model = _model_of(field, opts)
    fit = _robust_fit(_constraints(params), used, counts, opts,
                      opts.iterations if model is None else opts.guess_iterations)
    if fit is None:
        return FlowSummary(detections=n)
    U, V, inliers, geometry = fit
    q_evidence = min(1.0, n / opts.full_detections)
    q_geometry = min(1.0, 2.0 * geometry)

    deviance = 0.0
    fitted = _fitted_curves(model, full, hist, opts) if model is not None else None
    if fitted is not None:
        curves, saturated, gathered = fitted
        U1, V1, sig_s, sig_a, loglik = _likelihood_fit(model, curves, U, V, opts.search_climbs)
        line_model = _model_of(field, opts, "lines") if opts.ground == "auto" else None
        # without gradient-strength classes the line table cannot tell lines from edges
        # (README, "Thin lines read slow"): only a histogram with classes gets its fit
        if line_model is not None and line_model.classes > 1:
            # the same histogram under the line-ground table, from the same guess; the
            # saturated model depends on the counts alone, so the deviances compare
            line_fitted = _fitted_curves(line_model, full, hist, opts, gathered)
            if line_fitted is not None:
                line_fit = _likelihood_fit(line_model, line_fitted[0], U, V, opts.search_climbs)
                if line_fit[4] > loglik + opts.line_ground_margin:
                    model, (curves, saturated, _) = line_model, line_fitted
                    U1, V1, sig_s, sig_a, loglik = line_fit
                    on_lines = True
        speed = math.hypot(U1, V1)
        disagreement = math.hypot(U1 - U, V1 - V) / max(speed, model.speed_floor)
        deviance = saturated.deviance(loglik)
        expected = math.hypot(opts.overdispersion * math.hypot(sig_s, sig_a),
                              opts.disagreement_weight * disagreement,
                              opts.misfit_weight * model.misfit(deviance, speed))
        U, V = U1, V1
    else:
        speed = math.hypot(U, V)
        expected = 0.1 + (1.0 - inliers)  # IoC only: a rough figure
        on_lines = False
    top_speed = max(params.speeds) * (11.0 / 13.0) if opts.top_speed is None else opts.top_speed
    if speed > top_speed:
        expected += 0.5 * (speed / top_speed - 1.0)
    q_accuracy = 0.0
    ratio = expected / opts.quality_error
    if ratio < 1e150:  # (beyond, the square overflows: q_accuracy is 0 anyway; NaN or inf too)
        q_accuracy = 1.0 / (1.0 + ratio * ratio)
    quality = 255.0 * q_texture * q_evidence * q_geometry * q_accuracy
    # an estimate was made: quality 0 stays reserved for "no information, flow 0"
    quality = max(1, int(round(quality)))
    return FlowSummary(float(U), float(V), quality, n, False, inliers, float(expected), deviance,
                       on_lines)
