"""The analysis's files: ``analysis.json``, ``analysis.npz``, ``analysis_scores.csv``, VTK meshes, pictures.

``analysis.json``
    The tests (``group_test.p_value`` is the global group test), effect sizes, groups and
    counts, exclusions and warnings.
``analysis.npz`` (``allow_pickle=False``)
    ``mean`` (N,3), ``faces``; ``effect_names`` (E,), ``effects`` (E,N,3) mm per unit,
    ``effects_normal`` (E,N); ``group_levels`` (G,), ``group_means`` (G,N,3);
    ``displacement`` (N,3) and ``displacement_normal`` (N,): the first group effect (level
    2 − reference); ``t2`` (N,) Hotelling's T², ``pillai``, ``p_point``, ``p_fdr``,
    ``p_fwer`` (N,) of the group term; ``term_names`` (T,) and ``term_pillai``,
    ``term_p_fdr`` (T,N) of every term; ``discriminant`` (N,3) when there are groups.
``analysis_scores.csv``
    One row per analysed instance: its attributes, centroid size and mode scores (SD).
``effects/<effect>.vtp``
    The mean surface with each effect's displacement, normal component, and the term's
    statistic and p-values as point fields.
``analysis_map.png``, ``analysis_scores.png``
    The group displacement's normal component on the mean surface (diverging scale in mm,
    points not significant at FDR 5 % faded towards grey) and score scatter plots coloured by group.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import numpy as np

from ..base.records import jsonable
from ..formats.vtk import write_vtp
from ..model.figures import p_value_text
from ..model.files import write_npz
from .shape_analysis import Analysis, analyze

__all__ = ["FDR_LEVEL", "SHAPE_KEY_PREFIXES", "analysis_arrays", "analysis_document", "analysis_map_picture",
           "analysis_shape_keys", "analysis_summary", "diverging_colours", "run_analysis", "scores_picture",
           "write_analysis"]

#: The FDR level of the maps' significance masks and the counts in analysis.json.
FDR_LEVEL = 0.05
#: How much of its colour a point not significant keeps in the maps (the rest is grey).
GREY_MIX = 0.12
#: The grey a point not significant is drawn in (its colour kept at GREY_MIX).
NOT_SIGNIFICANT_GREY = 0.8


def _term_doc(test, adjusted_for) -> dict:
    doc = {"p_value": test.p_value, "pillai": test.global_pillai, "modes": test.global_modes,
           "p_value_f": test.p_value_f, "f": test.f, "r_squared": test.r_squared, "df": test.df,
           "residual_df": test.residual_df, "permutations": test.permutations, "adjusted_for": list(adjusted_for)}
    if test.p_fdr.size:
        doc.update({"points_significant_fdr": int(np.sum(test.p_fdr <= FDR_LEVEL)),
                    "points_significant_fwer": int(np.sum(test.p_fwer <= FDR_LEVEL)),
                    "points": int(test.p_fdr.size), "fdr_level": FDR_LEVEL,
                    "smallest_p_point": float(test.p_point.min())})
    return doc


def analysis_document(result: Analysis, *, model_path: str | None = None) -> dict:
    """``analysis.json``'s content."""
    terms = list(result.tests)
    effects = []
    for e in result.effects:
        size = np.linalg.norm(e.displacement, axis=1)
        effects.append({"name": e.name, "term": e.term, "unit": e.unit, "max_mm": float(size.max()),
                        "rms_mm": float(np.sqrt(np.mean(size**2))), "normal_min_mm": float(e.normal.min()),
                        "normal_max_mm": float(e.normal.max()), "largest_at_point": int(np.argmax(size))})
    doc = {
        "model": model_path,
        "instances": list(result.names),
        "excluded": result.excluded,
        "n": len(result.names),
        "group": None if not result.group else {
            "column": result.group, "levels": list(result.levels), "reference": result.levels[0],
            "counts": result.counts},
        "covariates": list(result.covariates),
        "size_removed": result.size_removed,
        "permutations": result.permutations,
        "seed": result.seed,
        "r_squared": result.r_squared,
        "tests": {t: _term_doc(result.tests[t], [o for o in terms if o != t]) for t in terms},
        "pairwise": {k: _term_doc(v, list(result.covariates)) for k, v in result.pairwise.items()},
        "effects": effects,
        "centroid_size_mm": {"mean": float(result.centroid_sizes.mean()), "sd": float(result.centroid_sizes.std())},
        "warnings": list(result.warnings),
        "method": {
            "global": "Pillai's trace on the leading residual modes (p_value) and Goodall's pseudo-F on all "
                      "coordinates (p_value_f); Freedman-Lane permutation of the reduced model's residuals",
            "per_point": "Pillai's trace of the term on the point's 3-D residual scatter (two groups: Hotelling "
                         "T^2); permutation p-values, Benjamini-Hochberg FDR and max-statistic FWER across points",
        },
    }
    if result.relative_pose:
        doc["relative_pose"] = result.relative_pose
        doc["method"]["relative_pose"] = (
            "each structure's pose relative to the reference structure (rotation vector in degrees and "
            "translation in mm, in the reference's frame; log scale) regressed on the same design; turn and "
            "shift tested by Pillai's trace of the 3-D vector, scale by F, Freedman-Lane permutations")
    if result.group:
        doc["group_test"] = doc["tests"][result.group]
    if result.discriminant:
        d = result.discriminant
        doc["discriminant"] = {"modes": d["modes"], "group_scores_sd": d["group_scores"],
                               "loo_accuracy": d["loo_accuracy"],
                               "max_mm_per_sd": float(np.linalg.norm(d["displacement"], axis=1).max())}
    return jsonable(doc)


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", name).strip("_") or "effect"


def analysis_arrays(result: Analysis) -> dict:
    """``analysis.npz``'s arrays."""
    n_points = result.mean.shape[0]
    terms = list(result.tests)
    arrays = {
        "mean": result.mean, "faces": np.asarray(result.faces, np.int64),
        "effect_names": np.asarray([e.name for e in result.effects], dtype=str),
        "effects": np.stack([e.displacement for e in result.effects]) if result.effects else np.zeros((0, n_points, 3)),
        "effects_normal": np.stack([e.normal for e in result.effects]) if result.effects else np.zeros((0, n_points)),
        "term_names": np.asarray(terms),
        "term_pillai": np.stack([result.tests[t].pillai for t in terms]),
        "term_p_fdr": np.stack([result.tests[t].p_fdr for t in terms]),
        "term_p_fwer": np.stack([result.tests[t].p_fwer for t in terms]),
    }
    if result.group:
        test = result.tests[result.group]
        first = next(e for e in result.effects if e.term == result.group)
        arrays.update({
            "group_levels": np.asarray(result.levels),
            "group_means": np.stack([result.group_means[lv] for lv in result.levels]),
            "displacement": first.displacement, "displacement_normal": first.normal,
            "t2": test.hotelling_t2, "pillai": test.pillai, "p_point": test.p_point, "p_fdr": test.p_fdr,
            "p_fwer": test.p_fwer,
        })
        if result.discriminant:
            arrays["discriminant"] = result.discriminant["displacement"]
    return arrays


def _mesh_view(points: np.ndarray):
    """Two views of the mean (screen x, y, depth rows): along its thinnest axis and across."""
    depth = int(np.argmin(np.ptp(points, axis=0)))
    rest = [a for a in range(3) if a != depth]
    return [np.eye(3)[[rest[0], rest[1], depth]], np.eye(3)[[rest[0], depth, rest[1]]]]


def analysis_map_picture(result: Analysis, path, *, effect: str | None = None) -> Path:
    """The normal component of an effect on the mean surface (mm, diverging blue–red scale with
    its legend, clipped at the 99th percentile: the colour bar's arrows and its label say so,
    with the extremes); points not significant at FDR 5 % of the effect's term are drawn in
    flat grey without shading of their colour (when any point is significant), with a legend
    patch."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.figure import Figure

    e = result.effect(effect) if effect else result.effects[0]
    test = result.tests[e.term]
    value = e.normal
    lim = max(float(np.percentile(np.abs(value), 99)), 1e-6)  # a few extreme points do not wash out the rest
    norm = TwoSlopeNorm(vcenter=0.0, vmin=-lim, vmax=lim)
    fig = Figure(figsize=(9.0, 4.4), dpi=100)
    FigureCanvasAgg(fig)
    import matplotlib

    cmap = matplotlib.colormaps["RdBu_r"]
    faces = np.asarray(result.faces)
    pts = result.mean - result.mean.mean(axis=0)
    significant = test.p_fdr <= FDR_LEVEL
    for j, view in enumerate(_mesh_view(pts)):
        ax = fig.add_axes([0.02 + 0.42 * j, 0.12, 0.4, 0.78])
        p = pts @ view.T
        tri = p[faces]
        order = np.argsort(tri[:, :, 2].mean(axis=1))
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        light = 0.45 + 0.55 * np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-12)
        rgba = cmap(norm(value[faces].mean(axis=1)))
        if significant.any():  # with none significant, fading everything would hide where the estimate lies
            grey = significant[faces].sum(axis=1) < 2
            rgba[grey, :3] = GREY_MIX * rgba[grey, :3] + (1 - GREY_MIX) * NOT_SIGNIFICANT_GREY
        rgba[:, :3] *= light[:, None]
        ax.add_collection(PolyCollection(tri[order, :, :2], facecolors=rgba[order], edgecolors="none"))
        half = 0.55 * float(np.max(np.ptp(p[:, :2], axis=0)))
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(["view along the mean's thinnest axis", "view across it"][j], fontsize=9)
        ax.plot([-0.9 * half, -0.9 * half + 10.0], [-0.92 * half] * 2, color="k", lw=2)
        ax.text(-0.9 * half, -0.88 * half, "10 mm", fontsize=8)
    cax = fig.add_axes([0.88, 0.15, 0.025, 0.7])
    from matplotlib.cm import ScalarMappable

    low, high = float(value.min()), float(value.max())
    extend = {(False, False): "neither", (True, False): "min", (False, True): "max", (True, True): "both"}[
        (low < -lim, high > lim)]
    label = f"normal displacement, {e.unit} (mm)"
    if extend != "neither":
        label += f"\nclipped at ±{lim:.2g} (99th pct.); extremes {low:.2f} to {high:.2f}"
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, label=label, extend=extend)
    t = test
    where = (f"{int(significant.sum())} of {len(significant)} points significant at FDR {FDR_LEVEL:g}"
             if significant.any() else f"no point significant at FDR {FDR_LEVEL:g} (colours: the estimate)")
    if significant.any():
        from matplotlib.patches import Patch

        fig.legend(handles=[Patch(facecolor=str(GREY_MIX * 0.5 + (1 - GREY_MIX) * NOT_SIGNIFICANT_GREY),
                                  edgecolor="0.5", label=f"grey: not significant (FDR {FDR_LEVEL:g})")],
                   loc="lower center", ncol=1, fontsize=9, frameon=False)
    fig.suptitle(f"{e.name} ({e.unit}): global p = {t.p_value:.3g}; {where}", fontsize=10)
    path = Path(path)
    fig.savefig(path)
    return path


def _scores_sd(result: Analysis, model) -> np.ndarray:
    """(analysed instances, K) mode weights in SD (:meth:`ShapeModel.scores` / √λ), rows in ``result.names``."""
    row = {str(n): i for i, n in enumerate(model.instance_names)}
    return model.scores()[[row[n] for n in result.names]] / model.standard_deviations


def scores_picture(result: Analysis, model, path, *, modes: int = 3) -> Path:
    """Score scatter plots of the first modes (SD), coloured by group."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    k = min(modes, model.n_modes)
    z = _scores_sd(result, model)[:, :k]
    pairs = [(0, 1), (0, 2), (1, 2)][: max(1, k * (k - 1) // 2)] if k >= 2 else []
    fig = Figure(figsize=(4.0 * max(1, len(pairs)), 3.8), dpi=100)
    FigureCanvasAgg(fig)
    labels = np.asarray(result.attributes[result.group], dtype=object) if result.group else np.array(
        ["all"] * len(z), dtype=object)
    levels = list(result.levels) if result.group else ["all"]
    colours = ["#4477aa", "#ee6677", "#228833", "#ccbb44", "#66ccee", "#aa3377", "#bbbbbb"]
    for j, (a, b) in enumerate(pairs):
        ax = fig.add_subplot(1, len(pairs), j + 1)
        for c, lv in enumerate(levels):
            sel = labels == lv
            ax.scatter(z[sel, a], z[sel, b], s=18, color=colours[c % len(colours)], label=f"{lv} ({int(sel.sum())})")
        ax.set_xlabel(f"mode {a + 1} (SD)")
        ax.set_ylabel(f"mode {b + 1} (SD)")
        ax.axhline(0, color="#cccccc", lw=0.5)
        ax.axvline(0, color="#cccccc", lw=0.5)
        if j == 0:
            ax.legend(fontsize="small", title=result.group or None)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    return path


def write_analysis(result: Analysis, out_dir, *, model=None, model_path: str | None = None,
                   pictures: bool = True, doc: dict | None = None) -> dict:
    """Write the analysis's files into ``out_dir`` (created); returns ``{file: path}``.

    ``doc``: ``analysis.json``'s content when the caller has it (:func:`analysis_document`).

    ``model`` (the analysed ShapeModel) adds the score table and plot.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    doc = analysis_document(result, model_path=model_path) if doc is None else doc
    written["analysis.json"] = out / "analysis.json"
    written["analysis.json"].write_text(json.dumps(doc, indent=1, sort_keys=False))
    written["analysis.npz"] = write_npz(out / "analysis.npz", analysis_arrays(result))
    effects_dir = out / "effects"
    effects_dir.mkdir(exist_ok=True)
    for e in result.effects:
        t = result.tests[e.term]
        fields = {"displacement_mm": e.displacement, "normal_mm": e.normal, "pillai": t.pillai,
                  "p_point": t.p_point, "p_fdr": t.p_fdr, "p_fwer": t.p_fwer}
        path = effects_dir / f"{_safe(e.name)}.vtp"
        written[f"effects/{path.name}"] = write_vtp(path, result.mean, result.faces, fields)
    if result.group:
        for lv in result.levels:
            path = effects_dir / f"mean_{_safe(lv)}.vtp"
            written[f"effects/{path.name}"] = write_vtp(path, result.group_means[lv], result.faces)
        if result.discriminant:
            d = result.discriminant
            path = effects_dir / "discriminant.vtp"
            written["effects/discriminant.vtp"] = write_vtp(path, result.mean, result.faces,
                                                            {"displacement_mm": d["displacement"],
                                                             "normal_mm": d["normal"]})
    if model is not None:
        z = _scores_sd(result, model)
        cols = list(result.attributes)
        path = out / "analysis_scores.csv"
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["name", *cols, *([] if "centroid_size" in cols else ["centroid_size"]),
                        *[f"mode_{k + 1}_sd" for k in range(model.n_modes)]])
            for i, name in enumerate(result.names):
                vals = ["" if v is None else v for v in (result.attributes[c][i] for c in cols)]
                extra = [] if "centroid_size" in cols else [f"{result.centroid_sizes[i]:.6g}"]
                w.writerow([name, *vals, *extra, *[f"{v:.6g}" for v in z[i]]])
        written["analysis_scores.csv"] = path
    if pictures:
        try:
            written["analysis_map.png"] = analysis_map_picture(result, out / "analysis_map.png")
            if model is not None:
                written["analysis_scores.png"] = scores_picture(result, model, out / "analysis_scores.png")
        except ImportError:  # pragma: no cover - matplotlib is a dependency
            pass
    return written


def run_analysis(model, attributes, params, out_dir=None, *, model_path: str | None = None, progress=None,
                 cancelled=None, pictures: bool = True) -> tuple[Analysis, dict, dict]:
    """:func:`~ssm_addon.analysis.shape_analysis.analyze` with an ``[analysis]`` parameter object,
    its files written into ``out_dir`` (none when None): returns (the analysis, ``analysis.json``'s
    content, the files written). The one route of ``ssm analyze``, the build's ``[analysis]`` and
    Blender."""
    result = analyze(model, attributes, group=params.group or None, covariates=params.covariates,
                     permutations=params.permutations, seed=params.seed, size_removed=params.size_removed,
                     reference=params.reference or None, lda_modes=params.lda_modes, progress=progress,
                     cancelled=cancelled)
    doc = analysis_document(result, model_path=model_path)
    written = {} if out_dir is None else write_analysis(result, out_dir, model=model, model_path=model_path,
                                                        pictures=pictures, doc=doc)
    return result, doc, written


def analysis_summary(result: Analysis) -> list[str]:
    """One line per test and the warnings, for the command line and the Blender status."""
    lines = []
    for term, t in result.tests.items():
        where = (f"; {int(np.sum(t.p_fdr <= FDR_LEVEL))} of {t.p_fdr.size} points significant at FDR {FDR_LEVEL:g}"
                 if t.p_fdr.size else "")
        adj = [o for o in result.tests if o != term]
        lines.append(f"{term}: {p_value_text(t.p_value)} (Pillai {t.global_pillai:.3f} on {t.global_modes} modes; "
                     f"Goodall F = {t.f:.3g}, {p_value_text(t.p_value_f)}; partial R² = {t.r_squared:.3f}; "
                     f"{t.permutations} permutations{', adjusted for ' + ', '.join(adj) if adj else ''}){where}")
        if (t.p_value <= 0.05) != (t.p_value_f <= 0.05):
            lines.append(f"  the two tests of {term} disagree: Pillai's trace (the verdict, its p first) tests the "
                         f"change in the {t.global_modes} leading residual modes; Goodall's F spreads it over all "
                         "coordinates, where a change confined to a few modes is diluted by the rest"
                         if t.p_value <= 0.05 else
                         f"  the two tests of {term} disagree: Goodall's F sees a change spread over many coordinates "
                         f"that the {t.global_modes} leading residual modes of Pillai's trace (the verdict) miss")
    for pair, t in result.pairwise.items():
        lines.append(f"  {pair}: {p_value_text(t.p_value)}")
    for e in result.effects:
        lines.append(f"  effect {e.name} ({e.unit}): largest {np.linalg.norm(e.displacement, axis=1).max():.3g} mm, "
                     f"normal {e.normal.min():.3g} to {e.normal.max():.3g} mm")
    for pair, figures in result.relative_pose.items():
        for term, t in figures["tests"].items():
            lines.append(f"relative pose {pair}, {term}: turn p = {t['turn_p']:.3g}, shift p = {t['shift_p']:.3g}, "
                         f"scale p = {t['scale_p']:.3g}")
        for name, e in figures["effects"].items():
            lines.append(f"  {pair} effect {name} ({e['unit']}): turn {e['turn_deg_size']:.3g}°, shift "
                         f"{e['shift_mm_size']:.3g} mm, scale {e['scale_percent']:+.3g} %")
    return lines


#: Name prefixes of the shape keys an analysis puts on the model's mean mesh.
SHAPE_KEY_PREFIXES = ("Effect: ", "Group mean: ", "Discriminant")


def analysis_shape_keys(result: Analysis, base) -> dict:
    """Shape keys for the model's mean mesh: ``{key name: (positions (N, 3) mm, slider min, slider max)}``.

    ``base`` (N, 3) is the mesh's basis (the model's mean, model frame). A group level's
    key is ``base + β`` (slider 1 = the level against the reference group, range −1…2). A
    covariate's key is ``base + s β`` for ``s`` units of the covariate, ``s`` the power of ten
    that keeps ±3 SD of the covariate within Blender's slider range of ±10 (``"per 10 of
    age"``: slider value 1 = 10 years). The discriminant's key moves one within-group SD of
    the discriminant score (slider ±3); a group mean's key is that mean (0…1).
    """
    base = np.asarray(base, dtype=float)
    keys = {}
    for e in result.effects:
        if e.level is not None:  # a category level against the reference
            keys[f"Effect: {e.name} ({e.unit})"] = (base + e.displacement, -1.0, 2.0)
            continue
        values = np.asarray(result.attributes[e.term], dtype=float)
        span = max(3.0 * float(np.std(values)), 1e-12)
        scale = 10.0 ** math.ceil(math.log10(span / 10.0)) if span > 10.0 else 1.0
        keys[f"Effect: {e.name} (per {scale:g} of {e.term})"] = (base + scale * e.displacement, -span / scale,
                                                                 span / scale)
    if result.discriminant:
        keys["Discriminant (per within-group SD)"] = (base + result.discriminant["displacement"], -3.0, 3.0)
    for lv in result.levels:
        keys[f"Group mean: {lv}"] = (result.group_means[lv], 0.0, 1.0)
    return keys


def diverging_colours(values, *, limit: float | None = None, mask=None) -> np.ndarray:
    """RGBA (n, 4) of a blue–white–red scale, ±``limit`` (default: the largest |value|); points where
    ``mask`` is False are faded towards grey (not significant)."""
    import matplotlib

    v = np.asarray(values, dtype=float)
    lim = float(np.max(np.abs(v))) if limit is None else float(limit)
    rgba = matplotlib.colormaps["RdBu_r"](0.5 + 0.5 * v / max(lim, 1e-12))
    if mask is not None:
        off = ~np.asarray(mask, bool)
        rgba[off, :3] = GREY_MIX * rgba[off, :3] + (1 - GREY_MIX) * 0.78
    return rgba
