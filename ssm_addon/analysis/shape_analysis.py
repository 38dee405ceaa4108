"""Shape analysis of a built model: group differences, covariate effects, size, the discriminant.

:func:`analyze` takes a :class:`~ssm_addon.model.pca.ShapeModel` (its training shapes in
the model frame) and an attribute table, and returns an :class:`Analysis`: each term's
effect as a shape (mm per unit of a covariate, mm from the reference group to a level),
its permutation tests (globally and per point, :mod:`ssm_addon.analysis.statistics`), the
groups' mean shapes, the normal component of every displacement on the mean surface, and
the linear discriminant of the groups as a shape.

The linear model (one row per instance, points ``x_i`` stacked as 3N coordinates, mm)::

    x_i = β₀ + Σ_levels β_g [group_i = g] + Σ_covariates β_c (c_i − mean c) + ε_i

with treatment coding against the reference group (the first in sorted order unless
given) and covariates centred, so β₀ is the reference group's shape at the mean
covariates and each β is an effect shape: ``mean + t β_c`` is the shape t units of ``c``
away. Without covariates β_g is exactly the difference of the groups' mean shapes.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import eigh

from ..base.errors import InputError
from ..meshutil import vertex_normals
from ..model.joint import relative_poses
from .attributes import Attributes
from .statistics import TermTest, centroid_size, term_test

__all__ = ["CENTROID_SIZE", "MIN_GROUP_SIZE", "Analysis", "Effect", "analyze", "design_matrix"]

#: The covariate name under which each instance's centroid size (mm, world) is available.
CENTROID_SIZE = "centroid_size"
#: Fewest instances a group may have (a group's within-group variation needs two).
MIN_GROUP_SIZE = 2
#: A covariate missing for more than this share of the instances is refused rather than
#: dropping those instances.
MAX_MISSING_SHARE = 0.5


@dataclass(frozen=True)
class Effect:
    """One column of the model: an effect as a shape.

    Attributes
    ----------
    name : str
        ``"group: patient"`` (level vs the reference) or the covariate's name.
    term : str
        The attribute column it belongs to.
    unit : str
        What one unit of the slider is: ``"patient − control"`` or ``"1 year"`` etc.
    displacement : (N, 3) ndarray, mm per unit
        β: the change of every point for one unit (model frame).
    normal : (N,) ndarray, mm per unit
        The displacement's component along the mean surface's outward normal.
    level : str or None
        The category level the effect compares with the reference; None for a covariate.
    """

    name: str
    term: str
    unit: str
    displacement: np.ndarray
    normal: np.ndarray
    level: str | None = None


@dataclass(frozen=True)
class Analysis:
    """The result of :func:`analyze` (model frame, mm).

    Attributes
    ----------
    names : tuple of str
        The instances analysed (rows with every used attribute given).
    excluded : dict name -> reason
        Instances left out and why.
    group : str or None
        The group column; ``levels`` its levels (reference first), ``counts`` per level.
    covariates : tuple of str
    size_removed : bool
        True: every shape was scaled to the mean centroid size first.
    mean : (N, 3) ndarray
        Mean shape of the analysed instances; ``faces`` the template's triangles.
    group_means : dict level -> (N, 3) ndarray
    effects : tuple of Effect
        Intercept excluded; group levels first, then covariates.
    tests : dict term -> TermTest
        Each term against the model without it (the group adjusted for the covariates,
        each covariate for the group and the other covariates).
    pairwise : dict "a vs b" -> TermTest
        Two-group tests between every pair of levels (only with three or more groups;
        without per-point maps).
    discriminant : dict or None
        LDA of the groups on the leading modes: ``displacement`` (N, 3) mm per
        within-group SD of the discriminant score, ``group_scores`` (level -> mean
        score in within-group SD), ``modes`` used, ``loo_accuracy`` (leave-one-out
        classification rate).
    r_squared : float
        Share of the total sum of squares the whole model explains.
    centroid_sizes : (n,) ndarray
        Each analysed instance's centroid size (mm, world).
    attributes : dict column -> list
        The analysed instances' values of the used columns.
    warnings : tuple of str
        What a reader must know (exclusions, unknown names, small groups).
    permutations, seed : int
    relative_pose : dict
        A joint model: per structure pair ``"reference-structure"`` the effect of every term on
        the structure's pose relative to the reference (:func:`relative_pose_effects`).
    """

    names: tuple[str, ...]
    excluded: dict
    group: str | None
    levels: tuple[str, ...]
    counts: dict
    covariates: tuple[str, ...]
    size_removed: bool
    mean: np.ndarray
    faces: np.ndarray
    group_means: dict
    effects: tuple[Effect, ...]
    tests: dict
    pairwise: dict
    discriminant: dict | None
    r_squared: float
    centroid_sizes: np.ndarray
    attributes: dict
    warnings: tuple[str, ...] = ()
    permutations: int = 1000
    seed: int = 0
    units: dict = field(default_factory=dict)
    relative_pose: dict = field(default_factory=dict)

    @property
    def group_test(self) -> TermTest | None:
        return self.tests.get(self.group) if self.group else None

    def effect(self, name: str) -> Effect:
        for e in self.effects:
            if e.name == name:
                return e
        raise KeyError(name)


def _column_values(attrs: Attributes, name: str, sizes: np.ndarray):
    if name == CENTROID_SIZE and name not in attrs.values:
        return "number", sizes.astype(float)
    attrs.require(name)
    return attrs.kinds[name], attrs.column(name)


def _text_covariate(attrs: Attributes, column: str) -> str:
    """A covariate column that is not all numbers: an error naming the cells that are not
    numbers when most are, else the note that it is used as a group (said once)."""
    given = int((~attrs.missing(column)).sum())
    words = attrs.not_numbers(column)
    if len(words) < given / 2:
        shown = ", ".join(f"{v!r} ({n})" for n, v in words[:6]) + (" …" if len(words) > 6 else "")
        raise InputError(f"{attrs.source}: covariate {column!r} has cells that are not numbers: {shown}; write them "
                         "as numbers (a decimal point, or a decimal comma in a semicolon-separated file) or leave "
                         "them empty (missing)")
    return f"covariate {column!r} holds text, not numbers: used as a group (its values are categories)"


def design_matrix(attrs: Attributes, *, group: str | None, covariates=(), sizes=None, reference: str | None = None):
    """The model's design on the rows of ``attrs`` with every used value given.

    Parameters
    ----------
    attrs : Attributes
        Rows in the order of the shapes.
    group : str or None
        Category column (numbers are taken as codes).
    covariates : sequence of str
        Number columns (or categories, dummy-coded), ``"centroid_size"`` included.
    sizes : (n,) array_like, optional
        Centroid sizes for ``"centroid_size"``.
    reference : str, optional
        The group level the others are compared to (default: first in sorted order).

    Returns
    -------
    rows : (m,) int ndarray
        The rows used.
    columns : dict term -> (m, q) ndarray
        Design columns of each term (covariates centred; categories dummy-coded).
    labels : dict term -> list of str
        Each column's name (``"group: b"``).
    levels : dict term -> list of str
        A category's levels, the reference first (covariates have none).
    excluded : dict row -> reason
    """
    n = len(attrs.names)
    sizes = np.full(n, np.nan) if sizes is None else np.asarray(sizes, float)
    terms = ([group] if group else []) + list(covariates)
    if len(set(terms)) != len(terms):
        raise InputError(f"{attrs.source}: a column is used twice ({', '.join(terms)})")
    raw, missing = {}, np.zeros(n, bool)
    reasons: dict[int, list[str]] = {}
    for t in terms:
        kind, col = _column_values(attrs, t, sizes)
        if t == group and kind == "number":
            given = ~np.isnan(col)
            if np.any(given & (col != np.round(col))):
                raise InputError(f"{attrs.source}: group column {t!r} holds non-integer numbers; a group needs "
                                 "categories (use it as a covariate instead)")
            col = np.array([None if np.isnan(v) else str(int(v)) for v in col], dtype=object)
            kind = "category"
        miss = np.isnan(col) if kind == "number" else np.array([v is None for v in col], bool)
        if miss.sum() > MAX_MISSING_SHARE * n:
            raise InputError(f"{attrs.source}: {t!r} is missing for {int(miss.sum())} of {n} instances; an analysis "
                             "with it would leave out most of them")
        for i in np.flatnonzero(miss):
            reasons.setdefault(int(i), []).append(t)
        missing |= miss
        raw[t] = (kind, col)
    rows = np.flatnonzero(~missing)
    columns, labels, levels_of = {}, {}, {}
    for t in terms:
        kind, col = raw[t]
        col = col[rows]
        if kind == "number":
            if np.ptp(col) <= 1e-12 * max(1.0, float(np.max(np.abs(col)))):
                raise InputError(f"{attrs.source}: covariate {t!r} is constant ({col[0]:g} for all {len(rows)} "
                                 "instances analysed): it cannot explain shape")
            columns[t] = (col - col.mean())[:, None]
            labels[t] = [t]
        else:
            levels = sorted(set(col))
            if t == group and reference is not None:
                if reference not in levels:
                    raise InputError(f"{attrs.source}: reference group {reference!r} is not a level of {t!r} "
                                     f"(levels: {', '.join(map(repr, levels))})")
                levels = [reference] + [lv for lv in levels if lv != reference]
            if len(levels) < 2:
                raise InputError(f"{attrs.source}: {t!r} has one value ({levels[0]!r}) for all {len(rows)} instances "
                                 "analysed: nothing to compare")
            counts = {lv: int(np.sum(col == lv)) for lv in levels}
            small = [lv for lv in levels if counts[lv] < MIN_GROUP_SIZE]
            if small:
                raise InputError(f"{attrs.source}: {t} {small[0]!r} has {counts[small[0]]} instance; each group needs "
                                 f"at least {MIN_GROUP_SIZE} (counts: {counts})")
            columns[t] = np.stack([(col == lv).astype(float) for lv in levels[1:]], axis=1)
            labels[t] = [f"{t}: {lv}" for lv in levels[1:]]
            levels_of[t] = levels
    excluded = {i: reasons[i] for i in sorted(reasons)}
    return rows, columns, labels, levels_of, excluded


def _discriminant(scores: np.ndarray, labels: np.ndarray, levels, modes: np.ndarray) -> dict:
    """Fisher's LDA on mode scores ``(m, k)``; the first discriminant as a shape (mm per
    within-group SD of the score) and the leave-one-out classification rate."""
    m, k = scores.shape
    g = len(levels)
    means = np.stack([scores[labels == lv].mean(axis=0) for lv in levels])
    within = sum(((scores[labels == lv] - means[j]).T @ (scores[labels == lv] - means[j]))
                 for j, lv in enumerate(levels)) / (m - g)
    grand = scores.mean(axis=0)
    between = sum(np.sum(labels == lv) * np.outer(means[j] - grand, means[j] - grand) for j, lv in enumerate(levels))
    within_r = within + 1e-9 * np.trace(within) / k * np.eye(k)
    w, vecs = eigh(between, within_r)
    direction = vecs[:, -1] / math.sqrt(float(vecs[:, -1] @ within_r @ vecs[:, -1]))
    s = scores @ direction
    if np.mean(s[labels == levels[-1]]) < np.mean(s[labels == levels[0]]):
        direction = -direction
        s = -s
    shape = np.tensordot(within_r @ direction, modes, axes=1)  # (N, 3): minimal-cost change of +1 score SD
    group_scores = {lv: float(np.mean(s[labels == lv] - s.mean())) for lv in levels}
    # leave-one-out: nearest group mean in the within-group Mahalanobis metric
    inv = np.linalg.inv(within_r)
    correct = 0
    for i in range(m):
        keep = np.arange(m) != i
        mu = np.stack([scores[keep & (labels == lv)].mean(axis=0) for lv in levels])
        d = np.einsum("gk,kl,gl->g", scores[i] - mu, inv, scores[i] - mu)
        correct += levels[int(np.argmin(d))] == labels[i]
    return {"displacement": shape, "group_scores": group_scores, "modes": int(k),
            "loo_accuracy": correct / m, "eigenvalue": float(w[-1])}


def analyze(model, attributes: Attributes, *, group: str | None = None, covariates=(), permutations: int = 1000,
            seed: int = 0, size_removed: bool = False, reference: str | None = None, lda_modes: int = 10,
            progress=None, cancelled=None) -> Analysis:
    """Group differences and covariate effects of a model's training shapes.

    Parameters
    ----------
    model : ShapeModel
        Its ``instance_points`` (model frame, mm) are the shapes; ``instance_points_world``
        give the centroid sizes.
    attributes : Attributes
        Joined to the model's instances by name; names the model lacks are a warning.
    group : str, optional
        Category column whose levels are compared.
    covariates : sequence of str
        Covariates modelled together with the group (``"centroid_size"``, mm, is always
        available).
    permutations : int
        Random permutations of every test (>= 99).
    seed : int
        Seed of the permutations.
    size_removed : bool
        Scale every shape to the mean centroid size before the analysis (shape without
        size; keep ``"centroid_size"`` as a covariate to study allometry).
    reference : str, optional
        The group the others are compared to.
    lda_modes : int
        Leading modes the discriminant uses (fewer when the groups are small).
    progress, cancelled : callables, optional

    Returns
    -------
    Analysis

    Raises
    ------
    InputError
        Unknown columns, a group of one, a constant or mostly missing covariate, no row
        naming an instance, fewer instances than the model has columns.
    """
    if not group and not covariates:
        raise InputError("analysis: give a group column, covariates, or both")
    if int(permutations) < 99:
        raise InputError(f"analysis: permutations must be >= 99 (p-values need the resolution), got {permutations}")
    covariates = tuple(covariates)
    if model.n_instances == 0:
        raise InputError(f"analysis: the model ({model.params.get('source', 'model')}) holds no training shapes, only "
                         "its mean and modes (a statismo file from another tool?); the analysis needs the instances' "
                         "points: use a model.npz from ssm build")
    say = progress or (lambda f, m: None)
    names_all = tuple(str(s) for s in model.instance_names)
    attrs, unknown = attributes.aligned(names_all)
    warnings = []
    if unknown:
        warnings.append(f"{len(unknown)} attribute rows name no instance of the model and were ignored: "
                        f"{', '.join(map(repr, unknown[:8]))}{' …' if len(unknown) > 8 else ''}")
    for c in covariates:
        if c in attrs.values and attrs.kinds[c] == "category":
            warnings.append(_text_covariate(attrs, c))
    sizes_all = centroid_size(np.asarray(model.instance_points_world, float))
    rows, columns, labels, levels_of, excluded_rows = design_matrix(attrs, group=group, covariates=covariates,
                                                                    sizes=sizes_all, reference=reference)
    excluded = {names_all[i]: f"missing {', '.join(t)}" for i, t in excluded_rows.items()}
    if excluded:
        warnings.append(f"{len(excluded)} of {len(names_all)} instances left out for missing attributes: "
                        + "; ".join(f"{k} ({v})" for k, v in list(excluded.items())[:8]))
    m = rows.size
    n_columns = 1 + sum(c.shape[1] for c in columns.values())
    if m < n_columns + 2:
        raise InputError(f"analysis: {m} instances for a model of {n_columns} columns (intercept, "
                         f"{', '.join(columns)}): need at least {n_columns + 2}")
    points = np.asarray(model.instance_points, float)[rows]
    sizes = sizes_all[rows]
    if size_removed:
        c = points.mean(axis=1, keepdims=True)
        points = c + (points - c) * (sizes.mean() / centroid_size(points))[:, None, None]
    faces = np.asarray(model.faces)
    mean = points.mean(axis=0)
    normals = vertex_normals(mean, faces)
    terms = list(columns)
    full = np.concatenate([np.ones((m, 1))] + [columns[t] for t in terms], axis=1)
    # Effects: least squares on all coordinates at once (QR: one factorisation for 3N columns).
    qm, rm = np.linalg.qr(full)
    beta = np.linalg.solve(rm, qm.T @ points.reshape(m, -1))
    fitted = full @ beta
    centred = points.reshape(m, -1) - points.reshape(m, -1).mean(axis=0)
    r_squared = 1.0 - float(np.sum((points.reshape(m, -1) - fitted) ** 2)) / max(float(np.sum(centred**2)), 1e-300)
    effects, col = [], 1
    units = {}
    for t in terms:
        for j, lab in enumerate(labels[t]):
            disp = beta[col].reshape(-1, 3)
            lv = levels_of.get(t)
            if lv is not None:
                unit = f"{lv[j + 1]} − {lv[0]}"
            else:
                unit = "1 mm" if t == CENTROID_SIZE else f"1 unit of {t}"
            units[lab] = unit
            effects.append(Effect(lab, t, unit, disp, np.einsum("nk,nk->n", disp, normals),
                                  level=lv[j + 1] if lv is not None else None))
            col += 1
    tests = {}
    for k, t in enumerate(terms):
        say(k / max(len(terms), 1), f"analysis: testing {t} ({permutations} permutations)")
        tests[t] = term_test(points, _reduced(columns, t, m), columns[t], permutations=permutations, seed=seed,
                             cancelled=cancelled)
    levels, counts, group_means, pairwise, discriminant = (), {}, {}, {}, None
    if group:
        levels = tuple(levels_of[group])
        glab = np.array([levels[0]] * m, dtype=object)
        for j, lv in enumerate(levels[1:]):
            glab[columns[group][:, j] > 0.5] = lv
        counts = {lv: int(np.sum(glab == lv)) for lv in levels}
        labelings = math.factorial(m) // math.prod(math.factorial(c) for c in counts.values())
        if labelings < permutations:
            warnings.append(f"only {labelings} distinct ways to split {m} instances into groups of "
                            f"{', '.join(str(c) for c in counts.values())}: no p-value of the group can be below "
                            f"1/{labelings} = {1 / labelings:.2g}, whatever the shapes")
        group_means = {lv: points[glab == lv].mean(axis=0) for lv in levels}
        if len(levels) > 2:
            others = [columns[o] for o in terms if o != group]
            for a, b in itertools.combinations(levels, 2):
                sel = (glab == a) | (glab == b)
                reduced = np.concatenate([np.ones((int(sel.sum()), 1))] + [o[sel] for o in others], axis=1)
                ind = (glab[sel] == b).astype(float)[:, None]
                pairwise[f"{a} vs {b}"] = term_test(points[sel], reduced, ind, permutations=permutations,
                                                    seed=seed, per_point=False, cancelled=cancelled)
        k = int(min(lda_modes, model.n_modes, m - len(levels) - 1))
        if k >= 1:
            flat = points.reshape(m, -1) - mean.reshape(-1)
            basis = np.asarray(model.modes[:k], float)
            scores = flat @ basis.reshape(k, -1).T
            discriminant = _discriminant(scores, glab, levels, basis)
            discriminant["normal"] = np.einsum("nk,nk->n", discriminant["displacement"], normals)
        else:
            warnings.append("the groups are too small for a discriminant direction (needs more instances than "
                            "groups + 1)")
    pose = relative_pose_effects(model, rows, columns, labels, units, qr=(qm, rm), permutations=permutations,
                                 seed=seed, cancelled=cancelled) if len(model.structure_names) > 1 else {}
    say(1.0, "analysis: done")
    used = ([group] if group else []) + list(covariates)
    attr_out = {}
    for t in used:
        if t == CENTROID_SIZE and t not in attrs.values:
            attr_out[t] = [float(s) for s in sizes]
        else:
            vals = attrs.values[t]
            attr_out[t] = [vals[i] for i in rows]
    return Analysis(names=tuple(names_all[i] for i in rows), excluded=excluded, group=group, levels=levels,
                    counts=counts, covariates=covariates, size_removed=bool(size_removed), mean=mean, faces=faces,
                    group_means=group_means, effects=tuple(effects), tests=tests, pairwise=pairwise,
                    discriminant=discriminant, r_squared=r_squared, centroid_sizes=sizes, attributes=attr_out,
                    warnings=tuple(warnings), permutations=int(permutations), seed=int(seed), units=units,
                    relative_pose=pose)


def _reduced(columns: dict, term: str, m: int) -> np.ndarray:
    """The design without ``term``: the intercept and every other term's columns."""
    return np.concatenate([np.ones((m, 1))] + [c for t, c in columns.items() if t != term], axis=1)


def relative_pose_effects(model, rows: np.ndarray, columns: dict, labels: dict, units: dict, *, qr=None,
                          permutations: int = 1000, seed: int = 0, cancelled=None) -> dict:
    """How each term moves a joint model's structures relative to its reference structure.

    The relative pose of every analysed subject (:func:`~ssm_addon.model.joint.relative_poses`:
    the rotation vector in degrees, the translation in mm, both in the reference's frame, and
    the log scale) is regressed on the same design as the shape. Per structure pair and effect:
    the turn (deg per unit, its vector and size), the shift (mm per unit) and the scale change
    (% per unit); per term the Freedman–Lane permutation p-values of the turn and of the shift
    (Pillai's trace of the 3-D vector) and of the log scale.

    ``qr``: the QR factors of the full design (intercept, then the terms' columns), when the
    caller has them.

    Returns ``{"reference-structure": {"effects": {effect: {...}}, "tests": {term: {...}}}}``.
    """
    poses = relative_poses(model)
    reference = model.params.get("reference") or model.structure_names[0]
    m = rows.size
    terms = list(columns)
    qm, rm = qr if qr is not None else np.linalg.qr(
        np.concatenate([np.ones((m, 1))] + [columns[t] for t in terms], axis=1))
    out = {}
    for name, arr in poses.items():
        p = np.asarray(arr, float)[rows]
        turn, shift = np.degrees(p[:, :3]), p[:, 3:6]
        scale = np.c_[p[:, 6], np.zeros((m, 2))]
        beta = np.linalg.solve(rm, qm.T @ np.c_[turn, shift, p[:, 6]])
        effects, col = {}, 1
        for t in terms:
            for lab in labels[t]:
                b = beta[col]
                effects[lab] = {"unit": units.get(lab, ""), "turn_deg": [float(x) for x in b[:3]],
                                "turn_deg_size": float(np.linalg.norm(b[:3])), "shift_mm": [float(x) for x in b[3:6]],
                                "shift_mm_size": float(np.linalg.norm(b[3:6])),
                                "scale_percent": float(100.0 * np.expm1(b[6]))}
                col += 1
        tests = {}
        for t in terms:
            reduced = _reduced(columns, t, m)
            kw = {"permutations": permutations, "seed": seed, "cancelled": cancelled}
            tests[t] = {"turn_p": float(term_test(turn[:, None], reduced, columns[t], **kw).p_point[0]),
                        "shift_p": float(term_test(shift[:, None], reduced, columns[t], **kw).p_point[0]),
                        "scale_p": float(term_test(scale[:, None], reduced, columns[t], per_point=False,
                                                   **kw).p_value_f)}
        out[f"{reference}-{name}"] = {"effects": effects, "tests": tests}
    return out
