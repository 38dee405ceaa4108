"""What a fit rests on, judged once: outlier, coverage, unit and convergence.

``ssm fit`` (one target or a batch) and Blender's *Fit Model* call :func:`judge_fit` on the
same fit and say the same warnings, so a verdict cannot differ between the front ends (a
NaN distance, say, is an outlier in all of them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from ..base.params import FitParams
from .fit import FitResult, Target, outlier_limit

__all__ = ["FREE_SLIDE_MM", "FREE_TURN_DEG", "UNIT_RATIO", "FitVerdict", "calibration", "coverage", "coverage_radius_mm", "is_outlier", "judge_fit", "size_in_unit_range"]

#: A partial target covering less than this share of the model's surface: the completion rests
#: on the model's prior.
LOW_COVERAGE = 0.1
#: A partial target whose fits turned about its long axis fit nearly as well over this many
#: degrees or more: its pose is said to be free.
FREE_TURN_DEG = 30.0
#: … or slid along it over this many mm or more.
FREE_SLIDE_MM = 20.0
#: A target whose size is outside this factor range of the model's is likely in another unit.
UNIT_RATIO = (0.2, 5.0)
#: A rigid fit is said to miss the target's size when the same fit with a similarity pose comes
#: this many times closer to the target (``FitResult.similarity``) …
SIZE_FACTOR = 0.8
#: … and closer by at least this much (mm): a fit already on the surface is not judged.
SIZE_MIN_GAIN_MM = 0.1


def calibration(errors_mm, sd_mm) -> dict:
    """How well posterior SDs follow true errors, where the truth is known (evaluations, tests).

    Parameters
    ----------
    errors_mm, sd_mm : (M,) array_like
        Per point: the distance from its true place and its posterior SD (mm).

    Returns
    -------
    dict
        ``within_2sd``: the share of errors within 2 SD (0.95 for a calibrated Gaussian);
        ``sd_mean_mm``: the mean SD (the sharpness: a share bought with a huge SD says little);
        ``error_mean_mm``; ``correlation``: Pearson's r of per-point SD and error (does the SD
        say *where* the error is?), NaN when either is constant.

    >>> c = calibration([1.0, 2.0, 3.0], [1.0, 1.5, 1.0])
    >>> round(c["within_2sd"], 3), c["sd_mean_mm"] == 3.5 / 3
    (0.667, True)
    """
    err, sd = np.asarray(errors_mm, float).ravel(), np.asarray(sd_mm, float).ravel()
    corr = float(np.corrcoef(err, sd)[0, 1]) if err.size > 1 and err.std() > 0 and sd.std() > 0 else float("nan")
    return {"within_2sd": float(np.mean(err <= 2.0 * sd)), "sd_mean_mm": float(sd.mean()),
            "error_mean_mm": float(err.mean()), "correlation": corr}


def is_outlier(mahalanobis: float, n_modes: int, probability: float = 0.99) -> bool:
    """Whether a fit's Mahalanobis distance is beyond the ``probability`` limit of the chi
    distribution on ``n_modes`` modes (:func:`~ssm_addon.fitting.fit.outlier_limit`); a distance
    that is not finite is an outlier (nothing vouches for the shape).

    >>> is_outlier(2.0, 3), is_outlier(5.0, 3), is_outlier(float("nan"), 3)
    (False, True, True)
    """
    return not math.isfinite(mahalanobis) or mahalanobis > outlier_limit(n_modes, probability)


def size_ratio(points, model) -> float:
    """The extent of ``points`` against the model's mean shape's (largest side of each bounding box)."""
    size_t = float(np.ptp(np.asarray(points, float).reshape(-1, 3), axis=0).max()) if len(points) else 0.0
    size_m = float(np.ptp(np.asarray(model.mean, float), axis=0).max())
    return size_t / size_m if size_m > 0 else math.inf


def size_in_unit_range(points, model) -> bool:
    """Whether ``points`` are of the model's size within :data:`UNIT_RATIO` (else: another unit?)."""
    return UNIT_RATIO[0] < size_ratio(points, model) < UNIT_RATIO[1]


def coverage(result: FitResult, target: Target, within_mm: float) -> float:
    """Share of the fitted shape's points within ``within_mm`` of the target's points: how
    much of the model's surface the target covers (1 for a whole shape)."""
    if not target.has_surface:
        return 0.0
    d, _ = cKDTree(np.asarray(target.samples, float)).query(np.asarray(result.points, float))
    return float(np.mean(d <= within_mm))


def coverage_radius_mm(model, params: FitParams) -> float:
    """The distance (mm) within which a target point covers a model point: twice the model's
    spacing, or three times the fit's noise, the larger."""
    spacing = float((model.params or {}).get("spacing_mm", 1.0))
    return max(2.0 * spacing, 3.0 * params.noise_mm)


@dataclass(frozen=True)
class FitVerdict:
    """The verdicts on one fit (``fit.json``'s ``outlier``, ``outlier_limit``, ``coverage`` and
    ``warnings``).

    Attributes
    ----------
    outlier : bool
        The Mahalanobis distance is beyond the limit, or not finite.
    outlier_limit : float
        The Mahalanobis distance at ``probability`` (chi distribution on the fit's modes).
    probability : float
    coverage : float
        Share of the fitted shape's points a target point covers (:func:`coverage`).
    warnings : dict kind -> message
        What the fit rests on, said: ``convergence``, ``outlier``, ``coverage`` (a partial
        target covering little), ``pose`` (a partial target whose turn about its long axis is
        free), ``unit`` (a target of another size than the model's: metres
        or centimetres?), ``size`` (a similarity pose fits much closer than the rigid one: the
        target's size lies outside the model's), ``labels`` (a label map fitted with its labels
        merged).
    """

    outlier: bool
    outlier_limit: float
    probability: float
    coverage: float
    warnings: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"outlier": self.outlier,
                "outlier_limit": {"probability": self.probability, "mahalanobis": self.outlier_limit},
                "coverage": self.coverage, "warnings": list(self.warnings.values()),
                "warning_kinds": list(self.warnings)}


def judge_fit(result: FitResult, target: Target, model, *, params: FitParams | None = None, partial: bool = False,
              probability: float = 0.99) -> FitVerdict:
    """The verdicts on ``result``, the fit of ``model`` to ``target`` (world mm).

    Parameters
    ----------
    partial : bool
        The target is part of a shape (completion): its coverage is judged, its size is not.
    probability : float
        The outlier limit's probability (``ssm fit --outlier-probability``).
    """
    params = FitParams() if params is None else params
    limit = outlier_limit(result.n_modes, probability)
    outlier = is_outlier(result.mahalanobis, result.n_modes, probability)
    cover = coverage(result, target, coverage_radius_mm(model, params))
    warnings = {}
    if not result.converged:
        warnings["convergence"] = f"the fit did not converge (stopped at {result.iterations} iterations)"
    if outlier:
        warnings["outlier"] = (f"Mahalanobis distance {result.mahalanobis:.2f} above the {100 * probability:g} % "
                               f"limit {limit:.2f}: an OUTLIER" if math.isfinite(result.mahalanobis) else
                               "the Mahalanobis distance is not finite: an OUTLIER (nothing vouches for the shape)")
    if partial and cover < LOW_COVERAGE:
        warnings["coverage"] = (f"the target covers {100 * cover:.0f} % of the model's surface: the completion rests "
                                "on the model's prior, not on the target")
    if target.has_surface and not partial and not size_in_unit_range(target.samples, model):
        size_m = float(np.ptp(np.asarray(model.mean, float), axis=0).max())
        ratio = size_ratio(target.samples, model)
        warnings["unit"] = (f"the target is {ratio:.3g} times the model's size ({ratio * size_m:.3g} against "
                            f"{size_m:.3g} mm): another unit (m, cm)?")
    similar = result.similarity
    if similar is not None and (similar["mean_distance_mm"] <= SIZE_FACTOR * result.mean_distance_mm
                                and result.mean_distance_mm - similar["mean_distance_mm"] >= SIZE_MIN_GAIN_MM):
        warnings["size"] = (f"a similarity pose fits {similar['mean_distance_mm']:.2f} mm from the target against "
                            f"this rigid fit's {result.mean_distance_mm:.2f} mm (scale {similar['scale']:.3f}, "
                            f"Mahalanobis {similar['mahalanobis']:.2f}): the target's size lies outside the "
                            "model's (a model built with sizes aligned?); fit with scale (--scale) unless its size "
                            "is what you measure")
    free = result.pose_freedom
    if free is not None and (free["width_deg"] >= FREE_TURN_DEG or free.get("width_mm", 0.0) >= FREE_SLIDE_MM):
        lo, hi = free["range_deg"]
        slo, shi = free.get("range_mm", (0.0, 0.0))
        moves = ([f"turned about its long axis from {lo:+.0f}° to {hi:+.0f}°"] if hi > lo else []) + (
            [f"slid along it from {slo:+.0f} to {shi:+.0f} mm"] if shi > slo else [])
        warnings["pose"] = (f"the given part leaves its pose free: {' and '.join(moves)} it fits within "
                            f"{free['tolerance_mm']:.2f} mm of the chosen pose; {free['candidates']} fits that near "
                            f"move the missing part by up to {free['spread_mm']['max']:.1f} mm RMS (included in the "
                            "posterior SD)")
    labels = target.merged_labels
    if len(labels) > 1:
        warnings["labels"] = (f"{target.source} holds {len(labels)} labels ({', '.join(str(x) for x in labels[:6])}"
                              f"{' …' if len(labels) > 6 else ''}) and no --label was given: they were fitted merged")
    return FitVerdict(outlier=outlier, outlier_limit=limit, probability=probability, coverage=cover, warnings=warnings)
