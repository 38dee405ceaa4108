"""The build's report: one type with its sections (``report.json``), and ``report.html``, the page a
person reads (images embedded, works offline).

:class:`Report` holds every section a reader relies on (project, parameters, model, template,
correspondence, quality, metrics, instances, timings); a section is either there or
explicitly :class:`Absent` with the reason, so no writer drops one silently and the page never
says "passed" of a section it was not given. :func:`study_report` assembles it from a study:
the headless build and Blender's *Save Model* call it on the same kind of study.

The page shows what ``report.json`` holds, for a reader: the warnings first, then the
project and its parameters, the model (variance per mode, paper fig. 9), the mode picture
(fig. 10) when the Blender step drew it, compactness / generalization / specificity, and
a quality table with a small picture of every coated instance (coloured by its place on
the template, so corresponding regions share a colour) and its fit figures, failed gates
highlighted. A short script checks that every picture decodes and says so on the page.
"""

from __future__ import annotations

import base64
import dataclasses
import html
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..base.records import jsonable
from ..correspondence.rounds import evenly_spaced
from ..meshutil import genus
from ..model.metrics import aggregate_fit, model_summary
from ..model.pca import procrustes_fit
from .sides import given_sides, model_side
from .study import Study, carried_landmarks, input_coordinates, landmark_distances, study_parameters

__all__ = ["MAX_THUMBNAILS", "SECTIONS", "Absent", "Report", "instance_thumbnails", "joint_report", "model_alignment",
           "model_report", "study_report", "thumbnail_names", "write_html_report", "write_report_html"]


@dataclass(frozen=True)
class Absent:
    """A report section that is not there, and why (``report.json``: ``{"absent": reason}``)."""

    reason: str

    def to_dict(self) -> dict:
        return {"absent": self.reason}


#: The sections every report has, each present or :class:`Absent` with its reason.
SECTIONS = ("project", "parameters", "model", "template", "correspondence", "quality", "metrics", "instances",
            "timings_s")


def correspondence_used(study) -> str:
    """What anchored a study's correspondence, whatever ``[correspondence] method`` says:
    ``"no landmarks"`` (the template's start registered from the object frames' rotations,
    :mod:`~ssm_addon.correspondence.frames`), ``"model"`` (the model method: rounds, or landmarks on
    some instances only) or ``"landmarks"`` (the paper's single pass)."""
    names = list(study.names)
    given = [n for n in names if study.landmarks(n) is not None]
    if not given:
        return "no landmarks"
    if study.params.correspondence.method == "model" or len(given) < len(names) or study.correspondence_rounds:
        return "model"
    return "landmarks"

def sides_record(study, model) -> dict:
    """``correspondence.sides`` of report.json: the template's side (given, or ``""``), the instances
    mirrored into it (the model's record) and how each side was decided (given, landmarks, surface or
    undecided, with both fits in mm; where this study decided them)."""
    decided = {n: d.to_dict() for n, d in given_sides(study).items()}
    decided.update({n: d.to_dict() for n, d in study.sides.items()})
    return {"template": model_side(study),
            "mirrored": list((model.params or {}).get("mirrored") or ()), "instances": decided}


def _section(value):
    return value.to_dict() if isinstance(value, Absent) else value


@dataclass(frozen=True)
class Report:
    """The content of ``report.json``: every section required, present or :class:`Absent`.

    Attributes
    ----------
    project : str or Absent
        The project file the study came from.
    parameters : dict or Absent
        Every parameter, as ``model.npz`` records them (:func:`~ssm_addon.pipeline.study.study_parameters`).
    model : dict
        Sizes and spectrum of the model (paper 5, eq. 8).
    template : dict or Absent
        The template's instance, points, triangles and genus (paper 3).
    correspondence : dict or Absent
        How the coatings came about: method, starts, rounds, the self-check.
    quality : dict or Absent
        The quality gates' parameters, their findings and the outlier scores.
    metrics : dict or Absent
        Compactness, generalization, specificity.
    instances : dict
        Each instance's coating figures (mm).
    timings_s : dict or Absent
        Wall time per step (s); ``timings_unknown`` names steps whose time is not known.
    fit_summary : dict
        The instances' figures summarised.
    timings_unknown : dict
        Step -> why its time is not known (e.g. run in another Blender session).
    extra : dict
        Further entries (files, compute, peak memory, analysis, the Blender model object).
    """

    project: str | Absent
    parameters: dict | Absent
    model: dict
    template: dict | Absent
    correspondence: dict | Absent
    quality: dict | Absent
    metrics: dict | Absent
    instances: dict
    timings_s: dict | Absent
    fit_summary: dict = field(default_factory=dict)
    timings_unknown: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def section(self, name: str) -> dict | str | None:
        """A section's content, or None when it is absent."""
        value = getattr(self, name)
        return None if isinstance(value, Absent) else value

    def absent(self, name: str) -> str:
        """Why a section is absent ("" when it is there)."""
        value = getattr(self, name)
        return value.reason if isinstance(value, Absent) else ""

    def to_dict(self) -> dict:
        """The JSON document (``report.json``); an absent section is ``{"absent": reason}``."""
        doc = {name: _section(getattr(self, name)) for name in SECTIONS}
        doc["fit_summary"] = self.fit_summary
        if self.timings_unknown:
            doc["timings_unknown"] = dict(self.timings_unknown)
        doc.update(self.extra)
        return jsonable(doc)

    @classmethod
    def from_dict(cls, doc: dict) -> Report:
        """A report read back from ``report.json``; a section the document lacks (an older
        writer) is absent with that reason."""
        def get(name):
            value = doc.get(name)
            if isinstance(value, dict) and set(value) == {"absent"}:
                return Absent(str(value["absent"]))
            if value is None or (name != "project" and not value and not isinstance(value, dict)):
                return Absent("not in this report (written without it)")
            return value

        known = set(SECTIONS) | {"fit_summary", "timings_unknown"}
        values = {name: get(name) for name in SECTIONS}
        for name in ("model", "instances"):
            if isinstance(values[name], Absent):
                values[name] = {}
        return cls(**values, fit_summary=doc.get("fit_summary") or {}, timings_unknown=doc.get("timings_unknown") or {},
                   extra={k: v for k, v in doc.items() if k not in known})

    def replace(self, **changes) -> Report:
        return dataclasses.replace(self, **changes)


def model_report(model, *, metrics=None, per_instance: dict | None = None, why: str, extra: dict | None = None,
                 project: str | Absent | None = None) -> Report:
    """The report of a model without its study (a model file opened on its own): the model,
    its instances' figures and metrics; every study section absent because ``why``."""
    per = {str(k): (dataclasses.asdict(v) if dataclasses.is_dataclass(v) else dict(v))
           for k, v in (per_instance or {}).items()}
    return Report(project=project if project is not None else Absent(why), parameters=Absent(why),
                  model=model_summary(model), template=Absent(why), correspondence=Absent(why), quality=Absent(why),
                  metrics=metrics.to_dict() if metrics is not None else Absent("not computed"), instances=per,
                  timings_s=Absent(why), fit_summary=aggregate_fit(per), extra=dict(extra or {}))


def model_alignment(study: Study) -> dict[str, dict]:
    """Per instance, what the model's alignment (``[model] alignment``) did to its coating in its
    object frame: the turn (degrees), the shift (mm) and the scale onto the model frame. A turn
    near 180° is an object frame the correspondence put right (a flip the paper's object-frame
    alignment would model as shape). Empty for ``alignment = "none"``."""
    model = study.model
    if study.params.model.alignment == "none" or model is None or not model.n_instances:
        return {}
    names = [str(n) for n in model.instance_names]
    if any(n not in study.coatings for n in names):
        return {}
    src = np.stack([study.coatings[n].points_object for n in names])
    dst = np.asarray(model.instance_points, float)
    out = {}
    for i, n in enumerate(names):
        s, rot, t = procrustes_fit(src[i][None], dst[i], scale=True)
        turn = float(np.degrees(np.arccos(np.clip((np.trace(rot[0]) - 1.0) / 2.0, -1.0, 1.0))))
        shift = float(np.linalg.norm(dst[i].mean(axis=0) - src[i].mean(axis=0)))
        out[n] = {"turn_deg": turn, "shift_mm": shift, "scale": float(s[0])}
    return out


def study_report(study: Study, *, project: str | Absent, timings_unknown: dict | None = None,
                 metrics_absent: str = "not computed", extra: dict | None = None) -> Report:
    """The report of a built study: what the headless build and Blender's *Save Model* write.

    Parameters
    ----------
    study : Study
        With its template, coatings and model; its findings, correspondence records,
        outlier scores, metrics and timings as the stages left them.
    project : str or Absent
        The project file (or why there is none).
    timings_unknown : dict step -> reason
        Steps whose wall time is not known.
    metrics_absent : str
        Why the metrics section is absent when the study has no metrics.
    extra : dict
        Further entries (compute, peak memory, files, the Blender model object).
    """
    model, tpl = study.model, study.template
    names = list(model.instance_names)
    # one source for how each coating started: the study's record (a round's coating says
    # "landmark warp" of its own warp, the study how the instance's correspondence began)
    per_instance = {n: dataclasses.asdict(dataclasses.replace(
        study.coatings[n].fit, start=study.coating_start.get(n, study.coatings[n].fit.start))) for n in names}
    for n in names:  # instances given as meshes: the coating against the user's own mesh, both ways
        if n in study.input_distances:
            per_instance[n]["input_surface_mm"] = study.input_distances[n]
    for n, moved in model_alignment(study).items():  # what the model's alignment did to each object frame
        per_instance[n]["alignment"] = moved
    check = study.correspondence_check
    correspondence = {
        "method": study.params.correspondence.method,
        "used": correspondence_used(study),
        "template_instance": study.template_instance,
        "template_choice": jsonable(study.template_choice),
        "start": {n: study.coating_start.get(n, study.coatings[n].fit.start) for n in names},
        "rounds": [r.to_dict() for r in study.correspondence_rounds],
        "stop": check.stop if check is not None else "",
        "self_check": check.to_dict() if check is not None else None,
        "carried_landmark_distance_mm": landmark_distances(study, carried_landmarks(study)),
        "optimisation": study.optimisation.to_dict() if study.optimisation is not None else None,
        "sides": sides_record(study, model),
    }
    return Report(
        project=project,
        parameters=study_parameters(study, model.params.get("landmarks", ())),
        model=model_summary(model),
        template={"instance": study.template_instance, "points": int(len(tpl.points_object)),
                  "triangles": int(len(tpl.faces)), "genus": int(genus(len(tpl.points_object), tpl.faces)),
                  **({"max_distance_mm": study.params.template.max_distance_mm,
                      **{k: tpl.params[k] for k in ("largest_distance_mm", "mean_distance_mm", "tolerance_rounds")
                         if k in (tpl.params or {})}}
                     if study.params.template.max_distance_mm is not None else {}),
                  **{k: tpl.params[k] for k in ("surface_largest_distance_mm", "refined_at") if k in (tpl.params or {})}},
        correspondence=correspondence,
        quality={"parameters": dataclasses.asdict(study.params.quality),
                 "findings": [f.to_dict() for f in study.findings], "outlier_scores": study.outlier_scores},
        metrics=study.metrics.to_dict() if study.metrics is not None else Absent(metrics_absent),
        instances=per_instance,
        timings_s=dict(study.timings_s),
        fit_summary=aggregate_fit(per_instance),
        timings_unknown=dict(timings_unknown or {}),
        extra={"inputs": input_coordinates(study), **dict(extra or {})})

THUMB_PX = 256
#: Width (px) of one thumbnail view on the page.
THUMB_SHOWN_PX = 128
#: Instances drawn in ``report.html`` at most: every flagged one, the rest evenly spaced in study
#: order (:func:`thumbnail_names`); a biobank's page stays small and quick to write.
MAX_THUMBNAILS = 200


def thumbnail_names(names, flagged=()) -> list[str]:
    """The instances ``report.html`` draws: all of them up to :data:`MAX_THUMBNAILS`; above, every
    ``flagged`` instance and the others evenly spaced in their order up to that many (the same
    choice on every library version).

    >>> thumbnail_names([f"s{i}" for i in range(1000)], ["s7"])[:3], len(thumbnail_names([f"s{i}" for i in range(1000)]))
    (['s0', 's5', 's7'], 200)
    """
    names = [str(n) for n in names]
    if len(names) <= MAX_THUMBNAILS:
        return names
    flagged = set(map(str, flagged)) & set(names)
    rest = [n for n in names if n not in flagged]
    chosen = flagged | set(evenly_spaced(rest, max(MAX_THUMBNAILS - len(flagged), 0)))
    return [n for n in names if n in chosen]


def _shade(points: np.ndarray, faces: np.ndarray, colours: np.ndarray, view: np.ndarray):
    """Triangles seen along ``view`` (3 × 3 rows: screen x, screen y, depth), back to front,
    Lambert-shaded: (polygons (F, 3, 2), RGBA (F, 4))."""
    p = points @ view.T
    tri = p[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1)
    facing = n[:, 2] / np.maximum(ln, 1e-12)
    order = np.argsort(tri[:, :, 2].mean(axis=1))
    light = 0.35 + 0.65 * np.abs(facing)
    rgba = np.ones((len(faces), 4))
    rgba[:, :3] = colours[faces].mean(axis=1)[:, :3] * light[:, None]
    return tri[order, :, :2], rgba[order]


def instance_thumbnails(points: np.ndarray, faces: np.ndarray, names, *, size_px: int = THUMB_PX) -> dict[str, bytes]:
    """A small PNG of every shape, two views side by side: ``{name: png bytes}`` (Pillow, painter's
    algorithm; ``2 size_px`` × ``size_px`` pixels).

    Parameters
    ----------
    points : (n, N, 3) float, mm
        The coated instances in the model frame; all seen along the axis in which the
        mean shape is thinnest (its largest silhouette) and across it, at one scale,
        coloured by their place on the mean shape (corresponding regions share a colour),
        Lambert-shaded.
    faces : (F, 3) int
    names : n names
    """
    from PIL import Image, ImageDraw

    pts = np.asarray(points, float)
    faces = np.asarray(faces)
    if len(pts) == 0 or not len(faces):
        return {}
    mean = pts.mean(axis=0)
    depth = int(np.argmin(np.ptp(mean, axis=0)))
    sx, sy = [a for a in range(3) if a != depth]
    # two views: along the thinnest axis (the largest silhouette) and along the first axis across it
    views = [np.eye(3)[[sx, sy, depth]], np.eye(3)[[depth, sy, sx]]]
    lo, hi = mean.min(axis=0), mean.max(axis=0)
    colours = np.ones((len(mean), 4))
    colours[:, :3] = 0.15 + 0.8 * (mean - lo) / np.where(hi > lo, hi - lo, 1.0)
    half = 0.55 * float(np.max(np.ptp(pts.reshape(-1, 3), axis=0)))
    ss = 2  # supersampling, for smooth edges
    size = size_px * ss
    out = {}
    for i, name in enumerate(names):
        img = Image.new("RGB", (2 * size, size), (255, 255, 255))
        draw = ImageDraw.Draw(img)
        for j, view in enumerate(views):
            polys, rgba = _shade(pts[i] - pts[i].mean(axis=0), faces, colours, view)
            xy = (polys / (2 * half) + 0.5) * size
            xy[:, :, 0] += j * size
            xy[:, :, 1] = size - xy[:, :, 1]  # screen y runs down
            fill = (np.clip(rgba[:, :3], 0, 1) * 255).astype(np.uint8)
            for tri, col in zip(xy.reshape(len(xy), -1).tolist(), map(tuple, fill.tolist())):
                draw.polygon(tri, fill=col)  # a flat [x0, y0, x1, y1, x2, y2]
        buf = io.BytesIO()
        # the supersampled picture averaged over ss × ss pixels; a quick PNG compression level
        img.reduce(ss).save(buf, format="PNG", compress_level=3)
        out[str(name)] = buf.getvalue()
    return out


def _img(data: bytes, alt: str, width: int | None = None) -> str:
    w = f' width="{width}"' if width else ""
    return (f'<img alt="{html.escape(alt)}"{w} src="data:image/png;base64,'
            f'{base64.b64encode(data).decode("ascii")}">')


def _num(v, digits=2) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:,.{digits}f}"
    return html.escape(str(v))


def _table(rows, header) -> str:
    """An HTML table; a row given as a dict may carry a ``note`` (HTML): a row of its own below
    it, across every column (an instance's warnings, readable at any width)."""
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for row in rows:
        cls = row.get("_class", "") if isinstance(row, dict) else ""
        cells = row["cells"] if isinstance(row, dict) else row
        out.append(f'<tr class="{cls}">' + "".join(f"<td>{c}</td>" for c in cells) + "</tr>")
        if isinstance(row, dict) and row.get("note"):
            out.append(f'<tr class="{cls} note"><td colspan="{len(header)}">{row["note"]}</td></tr>')
    out.append("</table>")
    return "\n".join(out)


CSS = """
body{font:15px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:2em auto;max-width:1240px;color:#222;
padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;margin-top:1.8em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;margin:.6em 0;font-size:.88em}td,th{border:1px solid #ddd;padding:.25em .45em;
text-align:right;vertical-align:middle}th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
tr.warn td{background:#fff1e6}tr.note td{text-align:left;font-size:.95em;border-top:none}th{white-space:normal}.warnings{background:#fff1e6;border:1px solid #f0a060;padding:.6em 1em;border-radius:4px}
.ok{background:#eef8ee;border:1px solid #8c8;padding:.6em 1em;border-radius:4px}
.figs img{max-width:100%;border:1px solid #eee;margin:.3em}.muted{color:#777}code{background:#f6f6f6;padding:0 .2em}
#broken{display:none;background:#fdd;border:1px solid #c44;padding:.6em 1em}
"""

SCRIPT = """
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) ok++; }
  document.body.setAttribute('data-images', imgs.length);
  var tables = document.getElementsByTagName('table'), wide = 0;
  for (var t = 0; t < tables.length; t++) { if (tables[t].getBoundingClientRect().right > window.innerWidth + 1) wide++; }
  document.body.setAttribute('data-tables-past-the-window', wide);
  document.body.setAttribute('data-images-decoded', ok);
  if (ok < imgs.length) {
    var b = document.getElementById('broken');
    b.textContent = (imgs.length - ok) + ' of ' + imgs.length + ' pictures could not be shown.';
    b.style.display = 'block';
  }
});
"""


def _analysis_section(a: dict, images: dict[str, bytes]) -> list[str]:
    """The Analysis section: groups, the tests, the effects, the maps and the score plots."""
    if not a:
        return []
    parts = ["<h2>Analysis: groups and covariates</h2>"]
    if a.get("error"):
        return parts + [f'<div class="warnings"><b>The analysis did not run:</b> {html.escape(a["error"])}</div>']
    g = a.get("group") or {}
    counts = ", ".join(f"{html.escape(str(k))} {v}" for k, v in (g.get("counts") or {}).items())
    parts.append(f"<p>{_num(a.get('n'))} instances"
                 + (f"; groups by <code>{html.escape(g['column'])}</code>: {counts} (reference "
                    f"{html.escape(str(g['reference']))})" if g else "")
                 + (f"; covariates {', '.join(html.escape(c) for c in a.get('covariates', []))}"
                    if a.get("covariates") else "")
                 + ("; shapes scaled to the mean centroid size" if a.get("size_removed") else "")
                 + f"; {_num(a.get('permutations'))} permutations. Model R² {_num(a.get('r_squared'), 3)}.</p>")
    if a.get("warnings"):
        items = "".join(f"<li>{html.escape(w)}</li>" for w in a["warnings"])
        parts.append(f'<div class="warnings"><b>Analysis warnings</b><ul>{items}</ul></div>')
    rows = []
    for term, t in (a.get("tests") or {}).items():
        sig = t.get("points_significant_fdr")
        rows.append({"_class": "warn" if t["p_value"] <= 0.05 else "", "cells": [
            f"<b>{html.escape(term)}</b>", html.escape(", ".join(t.get("adjusted_for") or []) or "–"), _num(t["df"]),
            _num(t["p_value"], 3), f"{_num(t['f'], 3)} (p {_num(t['p_value_f'], 3)})", _num(t["r_squared"], 3),
            f"{sig} of {t.get('points')}" if sig is not None else "–"]})
    for pair, t in (a.get("pairwise") or {}).items():
        rows.append([html.escape(pair), html.escape(", ".join(t.get("adjusted_for") or []) or "–"), _num(t["df"]),
                     _num(t["p_value"], 3), f"{_num(t['f'], 3)} (p {_num(t['p_value_f'], 3)})",
                     _num(t["r_squared"], 3), "–"])
    parts.append(_table(rows, ["term", "adjusted for", "df", "p (Pillai, leading modes)", "Goodall F (p)",
                               "partial R²", "points significant (FDR 5 %)"]))
    parts.append(_table([[html.escape(e["name"]), html.escape(e["unit"]), _num(e["max_mm"], 3), _num(e["rms_mm"], 3),
                          _num(e["normal_min_mm"], 3), _num(e["normal_max_mm"], 3)] for e in a.get("effects", [])],
                        ["effect", "per", "largest (mm)", "RMS (mm)", "normal min (mm)", "normal max (mm)"]))
    pose_rows = []
    for pair, figures in (a.get("relative_pose") or {}).items():
        tests = figures.get("tests") or {}
        for name, e in (figures.get("effects") or {}).items():
            term = next((t for t in tests if name == t or name.startswith(f"{t}: ")), None)
            t = tests.get(term, {})
            small = min(t.get("turn_p", 1.0), t.get("shift_p", 1.0), t.get("scale_p", 1.0)) <= 0.05
            pose_rows.append({"_class": "warn" if small else "", "cells": [
                html.escape(pair), html.escape(name), html.escape(e["unit"]),
                f"{_num(e['turn_deg_size'], 3)} (p {_num(t.get('turn_p'), 3)})",
                f"{_num(e['shift_mm_size'], 3)} (p {_num(t.get('shift_p'), 3)})",
                f"{_num(e['scale_percent'], 3)} (p {_num(t.get('scale_p'), 3)})"]})
    if pose_rows:
        parts.append("<p>Relative pose: how each effect turns, shifts and scales a structure on the reference "
                     "structure (in the reference's frame; p: permutation tests of the term).</p>")
        parts.append(_table(pose_rows, ["structures", "effect", "per", "turn (°)", "shift (mm)", "scale (%)"]))
    d = a.get("discriminant")
    if d:
        scores = ", ".join(f"{html.escape(str(k))} {v:+.2f}" for k, v in d["group_scores_sd"].items())
        parts.append(f"<p>Discriminant (LDA on {d['modes']} modes): group means at {scores} within-group SD; "
                     f"leave-one-out classification {100 * d['loo_accuracy']:.0f} %.</p>")
    if images:
        parts.append('<div class="figs">')
        for caption, data in images.items():
            parts.append(f"<figure>{_img(data, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("</div>")
    return parts


def _head_section(report: Report, title: str, findings: list) -> list[str]:
    """The title, the project, the quality gates' warnings (or that they passed, or are not known) and
    the sections the report does not have."""
    parts = [f"<h1>{html.escape(title)}</h1>"]
    project = report.section("project") or ""
    if project:
        parts.append(f'<p class="muted">Project <code>{html.escape(str(project))}</code></p>')
    elif report.absent("project"):
        parts.append(f'<p class="muted">No project file: {html.escape(report.absent("project"))}</p>')
    parts.append('<div id="broken"></div>')
    if report.absent("quality"):
        parts.append(f'<div class="warnings"><b>Quality gates: not known</b> — {html.escape(report.absent("quality"))}. '
                     "Nothing here says the instances passed them.</div>")
    elif findings:
        items = "".join(f"<li><b>{html.escape(f.get('instance') or 'study')}</b> [{html.escape(f['gate'])}]: "
                        f"{html.escape(f['message'])}</li>" for f in findings)
        parts.append(f'<div class="warnings"><b>Warnings ({len(findings)})</b> — thresholds in the '
                     f"<code>[quality]</code> table<ul>{items}</ul></div>")
    else:
        parts.append('<div class="ok">Every quality gate passed.</div>')
    missing = [(name, report.absent(name)) for name in ("parameters", "template", "correspondence", "metrics",
                                                         "timings_s") if report.absent(name)]
    if missing:
        parts.append('<p class="muted">Not in this report: ' + "; ".join(
            f"{html.escape(name.removesuffix('_s'))} ({html.escape(why)})" for name, why in missing) + ".</p>")
    return parts


def _model_section(report: Report, images: dict) -> list[str]:
    """The model's size and variance, the template, the modes' table and the figures."""
    model = report.model
    n, npts, k = model.get("n_instances"), model.get("n_points"), model.get("n_modes")
    parts = ["<h2>Model</h2>"]
    parts.append(f"<p>{_num(n)} instances, {_num(npts)} points, {_num(model.get('n_faces'))} triangles, {_num(k)} "
                 f"modes; total variance {_num(model.get('total_variance_mm2'))} mm².</p>")
    tpl = report.section("template") or {}
    if isinstance(tpl, dict) and tpl.get("points"):
        if tpl.get("max_distance_mm") is not None:
            density = (f"its triangles within {_num(tpl.get('largest_distance_mm'), 2)} mm of the instance's surface "
                       f"(mean {_num(tpl.get('mean_distance_mm'), 2)} mm; tolerance {_num(tpl['max_distance_mm'])} "
                       f"mm, <code>[template] max_distance_mm</code>)")
        else:
            density = "its density from the radii of eq. 1 (<code>[template] max_distance_mm = \"off\"</code>)"
        if tpl.get("surface_largest_distance_mm") is not None:
            density += (f"; the instance's surface within {_num(tpl['surface_largest_distance_mm'], 2)} mm of its "
                        "triangles")
        refined = tpl.get("refined_at")
        if isinstance(refined, dict):
            density += (f"; built again denser where the coatings of {len(refined.get('instances') or {})} "
                        f"instance(s) cut off parts of their meshes ({_num(refined.get('points_before'))} points "
                        f"before; <code>[template] refine_where_cut_off</code>)")
        parts.append(f"<p>Template: {_num(tpl['points'])} points from <b>{html.escape(str(tpl.get('instance')))}</b>, "
                     f"{density}.</p>")
    var = model.get("variances_mm2", [])[:12]
    conc = model.get("concentration_eigen", [])[:12]
    per_point = max(int(npts or 1), 1)
    parts.append(_table([[str(i + 1), _num(float(v), 3), _num(float(np.sqrt(max(v, 0))), 3),
                          _num(float(np.sqrt(max(v, 0) / per_point)), 3), f"{100 * float(c):.1f} %"]
                         for i, (v, c) in enumerate(zip(var, conc))],
                        ["mode", "variance λ (mm²)", "σ = √λ, whole shape (mm)", "RMS per point at 1σ (mm)",
                         "cumulative (eq. 8)"]))
    parts.append(f'<p class="muted">σ = √λ is the length of the whole shape\'s displacement at one standard '
                 f'deviation, over all {_num(npts)} × 3 coordinates (the mode is a unit vector of them); a point '
                 f'moves √(λ/N) on average (root mean square), the column beside it.</p>')
    app = report.to_dict().get("appearance") or {}
    if app.get("images"):  # the appearance stage's record
        inside, outside = (list(app.get("boundary_inside_outside") or []) + [None, None])[:2]
        parts.append(f"<p>Appearance: boundary profiles learned from the images of {len(app['images'])} instance(s) "
                     f"({html.escape(', '.join(map(str, app['images'][:5])))}{'…' if len(app['images']) > 5 else ''}), "
                     f"{_num(app.get('training_voxel_mm'), 2)} mm voxels, levels "
                     f"{html.escape(', '.join(f'{float(x):g}' for x in app.get('levels_sigma_mm') or []))} mm; grey "
                     f"values inside {_num(inside, 0)}, outside {_num(outside, 0)} (what <code>ssm segment</code> "
                     "expects of a new image).</p>")
    if images:
        parts.append('<h2>Figures</h2><div class="figs">')
        for caption, data in images.items():
            parts.append(f"<figure>{_img(data, caption)}<figcaption>{html.escape(caption)}</figcaption></figure>")
        parts.append("</div>")
    return parts


def _metrics_section(report: Report) -> list[str]:
    """Compactness, generalization and specificity by number of modes (paper fig. 9)."""
    metrics = report.section("metrics") or {}
    if not metrics:
        return []
    parts = ["<h2>Compactness, generalization, specificity</h2>"]
    comp = metrics.get("compactness", {})
    gen = metrics.get("generalization", {})
    spe = metrics.get("specificity", {})
    ks = list(gen.get("k", []) or spe.get("k", []))[:10]
    rows = []
    for j, kk in enumerate(ks):
        c = comp.get("cumulative", [])
        rows.append([str(kk), f"{100 * c[kk - 1]:.1f} %" if len(c) >= kk else "–",
                     _num(gen.get("mean_mm", [None] * len(ks))[j], 3) if j < len(gen.get("mean_mm", [])) else "–",
                     _num(spe.get("mean_mm", [None] * len(ks))[j], 3) if j < len(spe.get("mean_mm", [])) else "–"])
    parts.append(_table(rows, ["modes k", "compactness", "generalization (mm)", "specificity (mm)"]))
    if gen.get("method"):
        parts.append(f'<p class="muted">Generalization by {html.escape(str(gen["method"]))}.</p>')
    return parts


def _template_choice_lines(choice: dict) -> list[str]:
    """Which instance the template came from, and why (the model method's medoid routes)."""
    if choice.get("medoid") and choice.get("by") == "landmarks":
        used = choice["medoid"] if choice.get("kept") else choice.get("given")
        return [f"<p>Template from <b>{html.escape(str(used))}</b>: the instance whose given landmarks are "
                f"nearest their mean is {html.escape(str(choice['medoid']))}, chosen before the first "
                "coating" + ("; its coatings confirm it as the instance nearest the mean shape"
                             if choice.get("confirmed") else "") + ".</p>"]
    if choice.get("medoid") and choice.get("by") == "coatings":  # without landmarks
        used = choice["medoid"] if choice.get("kept") else choice.get("given")
        rms = choice.get("rms_from_mean_mm") or {}
        return [f"<p>Template from <b>{html.escape(str(used))}</b>: without landmarks, the instance whose first "
                f"coating is nearest the mean shape is {html.escape(str(choice['medoid']))} "
                f"({_num(rms.get(choice['medoid']), 2)} mm RMS; the given template's instance "
                f"{html.escape(str(choice.get('given')))} {_num(rms.get(choice.get('given')), 2)} mm); "
                + ("every instance was coated again from its template." if choice.get("kept") else
                   "the given template kept" + (f" ({html.escape(str(choice['failed']))})." if choice.get("failed")
                                                else " (the medoid's own coatings did not put it nearer the mean)."
                                                if choice.get("confirmed") is False
                                                else f" (it is the medoid, or within {_num(choice.get('tie'), 2)}x its distance)."))
                + "</p>"]
    if choice.get("medoid"):
        used = choice["medoid"] if choice.get("kept") else choice.get("given")
        return [f"<p>Template from <b>{html.escape(str(used))}</b>: the population's medoid is "
                f"{html.escape(str(choice['medoid']))} (the instance nearest the mean shape); "
                + (f"the landmark transfer error with the given template {html.escape(str(choice.get('given')))} "
                   f"{_num(choice.get('transfer_given_mm'), 3)} mm, with the medoid's "
                   f"{_num(choice.get('transfer_medoid_mm'), 3)} mm; "
                   f"{'the medoid' if choice.get('kept') else 'the given'} template kept."
                   if choice.get("medoid") != choice.get("given") else "it gave the template already.")
                + "</p>"]
    return []


def _correspondence_section(corr: dict) -> list[str]:
    """How the coatings came about: the method and its stop, the self-check, the template's instance,
    the model method's rounds and the correspondence optimisation."""
    if not corr:
        return []
    check = corr.get("self_check") or {}
    transfer = check.get("instance_mm") or {}
    parts = ["<h2>Correspondence</h2>"]
    stop = {"converged": "the rounds converged (the mean shape moved less than the tolerance)",
            "criterion": "the rounds stopped when one did not lower the landmark transfer error (it was dropped)",
            "limit": "the rounds stopped at their limit without settling",
            "failed": "the rounds failed and the start's coatings were kept (see the warnings)",
            }.get(corr.get("stop", ""), "the paper's single pass")
    kept = check.get("kept_round", 0)
    parts.append(f"<p>Method <code>{html.escape(str(corr.get('method', '')))}</code>: {html.escape(stop)}; "
                 + (f"round {kept}'s coatings kept." if kept else "the start's coatings kept.")
                 + (f" Self-check: landmark transfer error {_num(check.get('study_mm'), 2)} mm (each "
                    "instance's given landmarks predicted by the model of the others fitted to its surface)."
                    if transfer else "") + "</p>")
    parts += _template_choice_lines(corr.get("template_choice") or {})
    rounds = corr.get("rounds") or []
    if rounds:
        parts.append(_table([{"_class": "" if r.get("kept", True) else "warn", "cells": [
            str(r["round"]), _num(r.get("mean_change_mm"), 3),
            _num(max((r.get("instance_change_mm") or {}).values(), default=None), 2),
            _num((r.get("landmark_noise") or {}).get("click_mm"), 2),
            _num((r.get("landmark_noise") or {}).get("model_mm"), 2),
            _num(100 * (r.get("landmark_noise") or {}).get("shrink", 0.0), 0),
            _num(r.get("transfer_before_mm"), 3), _num(r.get("transfer_after_mm"), 3),
            "kept" if r.get("kept", True) else "dropped", _num(sum((r.get("folds") or {}).values())),
            _num(r.get("seconds"), 1)]} for r in rounds],
            ["round", "mean shape moved (mm)", "instances moved ≤ (mm)", "landmark error (mm/axis)",
             "model's prediction error (mm/axis)", "landmarks moved (%)", "transfer before (mm)",
             "transfer after (mm)", "kept", "folds", "seconds"]))
    opt = corr.get("optimisation") or {}
    if opt.get("steps"):
        first, last = opt["steps"][0], opt["steps"][-1]
        moved = opt.get("instance_movement_mm") or {}
        most = max(moved, key=moved.get) if moved else ""
        stop = {"converged": "it converged (the points moved less than the tolerance)",
                "limit": "it stopped at its iteration limit", "cancelled": "it was cancelled (the last complete "
                "iteration kept)"}.get(opt.get("stop", ""), str(opt.get("stop", "")))
        parts.append(f"<p>Correspondence optimisation: {int(opt.get('iterations', 0))} iteration(s), "
                     f"{html.escape(stop)}; objective {_num(first.get('objective'), 4)} → "
                     f"{_num(last.get('objective'), 4)}, population entropy {_num(first.get('entropy_nats'), 2)} → "
                     f"{_num(last.get('entropy_nats'), 2)} nats"
                     + (f"; the points of <b>{html.escape(str(most))}</b> moved most, "
                        f"{_num(moved[most], 3)} mm RMS" if most else "") + ".</p>")
    return parts


def _instances_section(report: Report, thumbnails: dict, by_instance: dict, outliers: dict, corr: dict) -> list[str]:
    """A row per instance: its picture, its coating's figures and start, its outlier scores, and its
    findings beneath it; the meshes' cavities."""
    inst = report.instances
    if not inst:
        return []
    transfer = (corr.get("self_check") or {}).get("instance_mm") or {}
    parts = ["<h2>Instances</h2>"]
    if thumbnails and len(thumbnails) < len(inst):
        parts.append(f'<p class="muted">Pictures of {len(thumbnails)} of the {len(inst)} instances: every '
                     "flagged one, the others evenly spaced in study order (at most "
                     f"{MAX_THUMBNAILS}).</p>")
    rows = []
    for name, fit in inst.items():
        res = fit.get("landmark_residuals_mm") or []
        o = outliers.get(name, {})
        flags = by_instance.get(name, [])
        # drawn at 256 px per view, shown at 128 (the page's zoom shows the rest) so the table fits 1,300 px
        thumb = _img(thumbnails[name], name, THUMB_SHOWN_PX * 2) if name in thumbnails else ""
        rows.append({"_class": "warn" if flags else "", "cells": [
            f"<b>{html.escape(name)}</b>", thumb, _num(fit.get("mean_distance_mm"), 3),
            _num(fit.get("max_distance_mm"), 3),
            _num(((fit.get("input_surface_mm") or {}).get("from_input") or {}).get("max_mm"), 2),
            _num((fit.get("alignment") or {}).get("turn_deg"), 0),
            _num(fit.get("folded_after")),
            _num(max(res) if res else None, 1), _num(transfer.get(name), 2), _num(fit.get("converged")),
            html.escape(str((corr.get("start") or {}).get(name, fit.get("start", "")))),
            _num(o.get("mahalanobis"), 2), _num(o.get("p_value"), 2), _num(o.get("loo_error_mm"), 2)],
            "note": "<br>".join(f"&#9888; {html.escape(name)}: [{html.escape(f['gate'])}] "
                                f"{html.escape(f['message'])}" for f in flags)})
    parts.append(_table(rows, ["instance", "coated", "mean dist. (mm)", "max dist. (mm)",
                               "input mesh to coating, max (mm)", "alignment turn (°)", "folds",
                               "max landmark residual (mm)", "landmark transfer (mm)", "converged", "start",
                               "Mahalanobis (LOO)", "p",
                               "LOO error (mm)"]))
    hollow = {n: (fit.get("input_surface_mm") or {}).get("cavities") for n, fit in inst.items()}
    hollow = {n: c for n, c in hollow.items() if c}
    if hollow:
        parts.append(f'<p class="muted">The meshes of {len(hollow)} instance(s) hold internal cavities, closed '
                     "surfaces inside the object (" + ", ".join(
                         f"{html.escape(n)}: {c['components']}, {c['vertices']:,} vertices" for n, c in hollow.items())
                     + "); the template fills cavities, so the input mesh's distance to its coating is that of "
                     "its outer surface.</p>")
    return parts


def _inputs_section(doc: dict) -> list[str]:
    """Each instance's file and the coordinates it was read in."""
    inputs = doc.get("inputs") or {}
    if not inputs:
        return []
    return ["<h2>Inputs</h2><p class=\"muted\">World coordinates are RAS mm; each file is read in the "
            "convention it states (3D Slicer's SPACE=LPS, a NIfTI's qform or sform), else the one given.</p>",
            _table([[f"<b>{html.escape(n)}</b>", html.escape(Path(d.get("source") or "").name),
                     html.escape(d.get("coordinates", "")), html.escape(Path(d.get("landmarks") or "").name),
                     html.escape(d.get("landmark_coordinates", ""))] for n, d in inputs.items()],
                   ["instance", "file", "coordinates", "landmarks", "landmark coordinates"])]


def _parameters_and_timings_section(report: Report) -> list[str]:
    """The template's, coating's and model's parameters, and each stage's time (or why it is not known)."""
    parts = []
    params = report.section("parameters") or {}
    if params:
        parts.append("<h2>Parameters</h2>")
        for section in ("template", "coating", "model"):
            table = params.get(section)
            if isinstance(table, dict):
                parts.append(f"<h3>[{section}]</h3>")
                parts.append(_table([[html.escape(str(k)), html.escape(json.dumps(v))] for k, v in table.items()],
                                    ["key", "value"]))
    timings = report.section("timings_s") or {}
    if timings or report.timings_unknown:
        parts.append("<h2>Timings</h2>")
        parts.append(_table([[html.escape(k), f"{float(v):.2f} s"] for k, v in timings.items()]
                            + [[html.escape(k), f"not known: {html.escape(why)}"] for k, why in report.timings_unknown.items()],
                            ["stage", "time"]))
    return parts


def write_html_report(path, report: Report | dict, *, images: dict[str, bytes] | None = None,
                      thumbnails: dict[str, bytes] | None = None, title: str = "SSM Builder model report",
                      analysis_images: dict[str, bytes] | None = None) -> Path:
    """Write ``report.html`` from a :class:`Report` (or a ``report.json`` document) and the pictures (PNG bytes).

    A section the report does not have is said to be absent, with its reason: an absent
    quality section is "not known", never "passed". Each section has its renderer (the head
    with the warnings, the model, the metrics, the correspondence, the instances, the inputs, a
    joint model's, the analysis, the parameters and timings), each a list of HTML fragments.

    Parameters
    ----------
    report : Report or dict
        The report (a dict is read as ``report.json``: :meth:`Report.from_dict`).
    images : dict caption -> PNG bytes
        Figures shown in order (fig. 9 plots, metrics, fig. 10).
    thumbnails : dict instance -> PNG bytes
    """
    report = report if isinstance(report, Report) else Report.from_dict(report)
    doc = report.to_dict()
    quality = report.section("quality") or {}
    findings = quality.get("findings", [])
    by_instance: dict[str, list] = {}
    for f in findings:
        by_instance.setdefault(f.get("instance", ""), []).append(f)
    corr = report.section("correspondence") or {}
    parts = (_head_section(report, title, findings) + _model_section(report, images or {})
             + _metrics_section(report) + _correspondence_section(corr)
             + _instances_section(report, thumbnails or {}, by_instance, quality.get("outlier_scores", {}), corr)
             + _inputs_section(doc) + _joint_section(doc) + _analysis_section(doc.get("analysis") or {},
                                                                               analysis_images or {})
             + _parameters_and_timings_section(report))
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{html.escape(title)}</title>"
            f"<style>{CSS}</style></head><body>\n" + "\n".join(parts) + f"\n<script>{SCRIPT}</script>\n</body></html>\n")
    path = Path(path)
    path.write_text(page, encoding="utf-8")
    return path


FIGURES = (("variability.png", "Eigenvalue spectrum and concentration of variability (paper fig. 9)"),
           ("modes.png", "Mean shape and the first modes (paper fig. 10)"),
           ("metrics.png", "Compactness, generalization and specificity by number of modes"),
           ("optimisation.png", "Correspondence optimisation: the objective by iteration, and where on the mean "
                                "shape points moved (mm)"))


ANALYSIS_FIGURES = (("analysis_map.png", "Group difference along the surface normal on the mean shape (mm); grey: "
                                          "not significant at FDR 5 % (as the picture's legend says)"),
                    ("analysis_scores.png", "Mode scores of the instances by group (SD)"))


def write_report_html(out_dir, model, report: Report | dict | None = None, *,
                      title: str = "SSM Builder model report") -> Path:
    """``report.html`` in ``out_dir`` from the report (default ``out_dir/report.json``), the figures
    in ``out_dir`` and the model's shapes."""
    out_dir = Path(out_dir)
    if report is None:
        report = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    images = {caption: (out_dir / name).read_bytes() for name, caption in FIGURES if (out_dir / name).is_file()}
    report = report if isinstance(report, Report) else Report.from_dict(report)
    flagged = {f.get("instance") for f in (report.section("quality") or {}).get("findings", []) if f.get("instance")}
    position = {str(n): i for i, n in enumerate(model.instance_names)}
    drawn = thumbnail_names(position, flagged)
    thumbs = instance_thumbnails(np.asarray(model.instance_points)[[position[n] for n in drawn]], model.faces, drawn)
    analysis = {caption: (out_dir / "analysis" / name).read_bytes() for name, caption in ANALYSIS_FIGURES
                if (out_dir / "analysis" / name).is_file()}
    return write_html_report(out_dir / "report.html", report, images=images, thumbnails=thumbs, title=title,
                             analysis_images=analysis)


def joint_report(joint, *, project: str | Absent, extra: dict | None = None) -> Report:
    """The report of a joint study (:class:`~ssm_addon.pipeline.joint.JointStudy`): the joint model,
    its metrics and findings with every structure's (named ``structure/subject``), and under
    ``joint`` each structure's template, correspondence and metrics, the shape-and-pose
    figures and the collisions."""
    model = joint.model
    why = "a joint model: each structure's is in the joint section (joint.structures)"
    findings = [dict(f.to_dict(), instance=f"{name}/{f.instance}" if f.instance else name)
                for name, study in joint.structures.items() for f in study.findings]
    findings += [f.to_dict() for f in joint.findings]
    structures = {}
    per_subject: dict[str, dict] = {str(s): {} for s in joint.subjects}
    for name, study in joint.structures.items():
        tpl = study.template
        check = study.correspondence_check
        structures[name] = {
            "template": {"instance": study.template_instance, "points": int(len(tpl.points_object)),
                         "triangles": int(len(tpl.faces)), "genus": int(genus(len(tpl.points_object), tpl.faces))},
            "correspondence": {"method": study.params.correspondence.method, "used": correspondence_used(study),
                               "start": {s: study.coating_start.get(s, study.coatings[s].fit.start)
                                         for s in joint.subjects},
                               "template_choice": jsonable(study.template_choice),
                               "rounds": [r.to_dict() for r in study.correspondence_rounds],
                               "self_check": check.to_dict() if check is not None else None,
                               "self_check_measured": self_check_measured(check),
                               "sides": sides_record(study, model)},
            "metrics": joint.structure_metrics.get(name, {}),
            "points": [int(model.structure_offsets[list(model.structure_names).index(name)]),
                       int(model.structure_offsets[list(model.structure_names).index(name) + 1])],
        }
        for s in joint.subjects:
            fit = study.coatings[s].fit
            row = per_subject[str(s)]
            row["mean_distance_mm"] = max(row.get("mean_distance_mm", 0.0), float(fit.mean_distance_mm))
            row["max_distance_mm"] = max(row.get("max_distance_mm", 0.0), float(fit.max_distance_mm))
            row["folded_after"] = row.get("folded_after", 0) + int(fit.folded_after)
            row["converged"] = bool(row.get("converged", True) and fit.converged)
    joint_doc = {"structures": structures, "reference": joint.reference, "align_on": joint.params.joint.align_on,
                 "shape_pose": joint.shape_pose, "collisions": joint.collisions}
    return Report(
        project=project,
        parameters={**study_parameters(next(iter(joint.structures.values()))), "joint": dataclasses.asdict(
            joint.params.joint), "structures": {n: st.params.to_tables() for n, st in joint.structures.items()}},
        model=model_summary(model), template=Absent(why), correspondence=Absent(why),
        quality={"parameters": dataclasses.asdict(joint.params.quality), "findings": findings,
                 "outlier_scores": joint.outlier_scores},
        metrics=joint.metrics.to_dict() if joint.metrics is not None else Absent("not computed"),
        instances=per_subject, timings_s=dict(joint.timings_s), fit_summary=aggregate_fit(per_subject),
        extra={"joint": joint_doc, **dict(extra or {})})


#: A self-check over fewer landmarked instances than this measures nothing of the population (the
#: template's own instance says only how its coating sits on it).
SELF_CHECK_MIN_INSTANCES = 3


def self_check_measured(check) -> str:
    """``""`` when the correspondence self-check measured the coatings (its landmark transfer error over
    at least :data:`SELF_CHECK_MIN_INSTANCES` instances), else why not."""
    if check is None:
        return "no self-check (no landmarks, or switched off)"
    n = len(getattr(check, "instance_mm", {}) or {})
    if n < SELF_CHECK_MIN_INSTANCES:
        return f"not measured: {n} landmarked instance(s), fewer than {SELF_CHECK_MIN_INSTANCES}"
    return ""


def _correspondence_rows(structures: dict) -> list[list[str]]:
    """A row per structure: what anchored its correspondence, its starts, rounds and self-check."""
    rows = []
    for name, st in structures.items():
        c = st.get("correspondence") or {}
        starts = {}
        for how in (c.get("start") or {}).values():
            starts[how] = starts.get(how, 0) + 1
        turned = [s for s, t in ((c.get("template_choice") or {}).get("starts") or {}).items()
                  if t.get("turn") not in ("frames", "input coordinates")]
        rounds = c.get("rounds") or []
        check = c.get("self_check") or {}
        measured = c.get("self_check_measured", "")
        mirrored = list((c.get("sides") or {}).get("mirrored") or ())
        rows.append([f"<b>{html.escape(name)}</b>", html.escape(str(c.get("used", ""))),
                     html.escape(", ".join(f"{k}: {v}" for k, v in sorted(starts.items()))),
                     html.escape(", ".join(turned[:6]) + (" …" if len(turned) > 6 else "")) or "none",
                     f"{sum(bool(r.get('kept', True)) for r in rounds)} of {len(rounds)} kept" if rounds else "none",
                     _num(check.get("study_mm"), 2) + " mm" if check and not measured else html.escape(measured or "—"),
                     html.escape(", ".join(mirrored[:6]) + (" …" if len(mirrored) > 6 else "")) or "none"])
    return rows


def _joint_section(doc: dict) -> list[str]:
    """The joint model's section: structures, their metrics, shape and relative pose, collisions."""
    j = doc.get("joint") or {}
    if not j:
        return []
    parts = [f"<h2>Joint model: {len(j['structures'])} structures</h2>",
             f"<p>Reference structure <b>{html.escape(str(j['reference']))}</b>; each subject aligned on "
             f"{'all structures together' if j.get('align_on') == 'all' else 'the reference structure'}.</p>"]
    rows = []
    for name, st in j["structures"].items():
        m = st.get("metrics") or {}

        def g(which, key, m=m):
            return _num(((m.get(which) or {}).get(key) or [None])[0], 3)
        rows.append([f"<b>{html.escape(name)}</b>", _num(st["template"]["points"]), html.escape(st["template"]["instance"]),
                     g("joint", "generalization_mm"), g("separate", "generalization_mm"),
                     g("joint", "specificity_mm"), g("separate", "specificity_mm")])
    parts.append(_table(rows, ["structure", "template points", "template instance", "generalization, joint rows (mm)",
                               "generalization, own model (mm)", "specificity, joint rows (mm)",
                               "specificity, own model (mm)"]))
    parts.append("<h3>Correspondence per structure</h3>")
    parts.append(_table(_correspondence_rows(j["structures"]),
                        ["structure", "anchored by", "starts", "turned starts", "rounds", "self-check",
                         "mirrored into the template's side"]))
    sp = j.get("shape_pose") or {}
    if sp:
        shares = sp.get("modes_pose_share", [])[:8]
        total = sp.get("total_variance_mm2")
        parts.append("<p>Shape and relative pose (" + html.escape(sp.get("weighting", "")) + "): share of each mode "
                     "that is relative pose: " + ", ".join(f"{i + 1}: {100 * s:.0f} %" for i, s in enumerate(shares))
                     + ". These modes are a PCA of their own (each structure's shape aligned in its own frame, beside "
                     "the relative poses"
                     + (f"; total variance {_num(total, 0)} mm²" if total is not None else "")
                     + "), not the joint model's modes, whose λ are of every structure's coordinates together in "
                     "the reference structure's frame.</p>")
        def noise(f, key, share):
            c = f.get("correspondence")
            if not c or "not_measured" in c:
                return "not measured" + (f": {html.escape(c['not_measured'])}" if c else "")
            return f"{_num(c[key], 2)} ({_num(100 * c[share], 0)} % of the data's variance)"

        parts.append(_table([[html.escape(pair), _num(f["data"]["turn_sd_deg"], 2), _num(f["model"]["turn_sd_deg"], 2),
                              noise(f, "turn_sd_deg", "turn_share"), _num(f["data"]["shift_sd_mm"], 2),
                              _num(f["model"]["shift_sd_mm"], 2), noise(f, "shift_sd_mm", "shift_share")]
                             for pair, f in sp.get("pairs", {}).items()],
                            ["pair", "turn SD, data (°)", "turn SD, model (°)", "turn SD the correspondence could give (°)",
                             "shift SD, data (mm)", "shift SD, model (mm)", "shift SD the correspondence could give (mm)"]))
        parts.append("<p>The correspondence's share: each subject's relative pose by the coatings' points against "
                     "by their surfaces (each structure put on its mean shape both ways); the spread of that "
                     "difference is what the coatings' own error could give the relative pose.</p>")
    col = j.get("collisions") or {}
    if col:
        parts.append(_table([[html.escape(pair), _num(100 * f["data"]["colliding_share"], 0) + " %",
                              _num(f["data"]["max_mm"], 2), _num(100 * f["model"]["colliding_share"], 0) + " %",
                              _num(f["model"]["max_mm"], 2)] for pair, f in col.items()],
                            ["pair", "subjects overlapping", "deepest, subjects (mm)", "model shapes overlapping",
                             "deepest, model (mm)"]))
    return parts
