"""Quality gates: results that are probably wrong, named with the reason.

A shape model that is silently wrong is worse than none. Every gate compares one figure
with a threshold of :class:`~ssm_addon.base.params.QualityParams` (the project's
``[quality]`` table) and returns :class:`Finding` objects that name the instance, the
gate, the figure and the threshold:

============================  ==============================================  ==========
gate                          figure                                          stage
============================  ==============================================  ==========
``components``                share of the second-largest connected part      import
``volume``                    volume / median volume of the study             import
``duplicate``                 the same file and label, or bit-identical       import
                              content, as another instance
``landmark_distance``         landmark to surface distance (mm; an error)     import
``landmark_residual``         coated landmark to given landmark (mm)          coating
``landmark_transfer``         given landmark to the others' model's           coating
                              prediction (mm; the correspondence self-check)
``rounds``                    model method's rounds stopped at their limit    coating
``frame``                     coating turned against the template instance's  model
                              (object frames that disagree; alignment none)
``twist``                     coating's points turned on its own surface      model
                              against the others' (degrees; correspondence
                              against shape, :mod:`~ssm_addon.correspondence.frames`)
``pose_noise``                share of a joint model's relative-pose variance  model
                              the coatings' own error could explain
                              (:func:`~ssm_addon.pipeline.joint.relative_pose_noise`)
``collision``                 a joint model's structures overlapping far       model
                              more than the subjects' own do
``folds``                     folded triangles left                           coating
``surface_distance``          largest vertex distance to the surface (voxels) coating
``convergence``               relaxation stopped by its iteration limit       coating
``outlier``                   leave-one-out Mahalanobis distance (F test)     model
``reconstruction``            leave-one-out reconstruction error / median     model
============================  ==============================================  ==========

Input problems that make a build meaningless (a mask of a few voxels, landmarks far
from their instance's surface) are :class:`~ssm_addon.base.errors.InputError` at once; the
rest are findings. :func:`warnings_text` is the summary the command line prints last;
with ``strict`` a build with findings fails (:class:`QualityError`).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.special import fdtrc, stdtr  # F and t tails (scipy.stats costs 0.5 s to import)

from ..base.errors import InputError, SSMError
from ..base.params import QualityParams
from ..meshutil import marching_cubes
from ..model.pca import gram_factor, procrustes_fit

__all__ = [
    "Finding",
    "QualityError",
    "check_coating",
    "check_correspondence_rounds",
    "check_duplicate_instances",
    "check_frames",
    "check_input_surface",
    "check_landmark_transfer",
    "check_landmarks_on_surface",
    "check_model",
    "check_volume",
    "check_volumes_together",
    "content_digest",
    "loo_outlier_scores",
    "warnings_text",
]


class QualityError(SSMError):
    """A strict build stopped because quality gates failed (the message lists them)."""


@dataclass(frozen=True)
class Finding:
    """One failed quality gate.

    Attributes
    ----------
    instance : str
        The instance's name ("" for the study as a whole).
    gate : str
        The gate's name (see the module docstring).
    message : str
        What was found, with the figure and the threshold, in words.
    value, threshold : float
    stage : str
        The pipeline stage that found it (``import``, ``coating``, ``model``; set by the
        stage's result, :class:`ssm_addon.pipeline.study.StageResult`).
    """

    instance: str
    gate: str
    message: str
    value: float = float("nan")
    threshold: float = float("nan")
    stage: str = ""

    def to_dict(self) -> dict:
        """JSON-ready (NaN figures as None): the form of ``report.json`` and the Blender scene."""
        d = asdict(self)
        for k in ("value", "threshold"):
            d[k] = None if not math.isfinite(d[k]) else float(d[k])
        return d

    @classmethod
    def from_dict(cls, d) -> Finding:
        """The finding of :meth:`to_dict`'s form."""
        return cls(instance=str(d.get("instance", "")), gate=str(d["gate"]), message=str(d["message"]),
                   value=float("nan") if d.get("value") is None else float(d["value"]),
                   threshold=float("nan") if d.get("threshold") is None else float(d["threshold"]),
                   stage=str(d.get("stage", "")))

    def __str__(self) -> str:
        return f"{self.instance}: {self.message}" if self.instance else self.message


# ------------------------------------------------------------------------------- import
def check_volume(name: str, object_volume, params: QualityParams) -> list[Finding]:
    """Gates on one imported instance: enough voxels (else an error), one main component.

    Raises
    ------
    InputError
        The mask has fewer than ``params.min_voxels`` voxels (a wrong label or a stray
        fragment: nothing to model).
    """
    mask = np.asarray(object_volume.mask, dtype=bool)
    n = int(np.count_nonzero(mask))
    if n < params.min_voxels:
        raise InputError(f"instance {name!r} ({object_volume.source or 'mask'}): only {n} voxel(s) at "
                         f"{object_volume.spacing_mm:g} mm; at least {params.min_voxels} are needed (wrong label?)")
    labels, count = ndimage.label(mask)
    if count < 2:
        return []
    sizes = np.sort(np.bincount(labels.ravel())[1:])[::-1]
    share = float(sizes[1] / n)
    if share > params.max_second_component:
        return [Finding(name, "components", f"{count} separate parts; the second-largest holds {100 * share:.0f} % of "
                        f"the voxels (threshold {100 * params.max_second_component:.0f} %): two objects under one label?",
                        share, params.max_second_component)]
    return []


def check_volumes_together(volumes_mm3: dict[str, float], params: QualityParams) -> list[Finding]:
    """Instances whose volume is far from the study's median (a wrong label, another structure)."""
    if len(volumes_mm3) < 3:
        return []
    median = float(np.median(list(volumes_mm3.values())))
    out = []
    for name, v in volumes_mm3.items():
        ratio = v / median if median > 0 else float("inf")
        if ratio > params.max_volume_ratio or ratio < 1.0 / params.max_volume_ratio:
            out.append(Finding(name, "volume", f"volume {v / 1000:.1f} cm³ is {ratio:.2f}× the study's median "
                               f"{median / 1000:.1f} cm³ (allowed {1 / params.max_volume_ratio:.2f}–"
                               f"{params.max_volume_ratio:g}×): another structure or a wrong label?",
                               ratio, params.max_volume_ratio))
    return out


def content_digest(*arrays) -> str:
    """SHA-1 of arrays' bytes (shape and dtype included): equal for bit-identical content."""
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def check_duplicate_instances(sources: dict[str, tuple], digests: dict[str, str] | None = None) -> list[Finding]:
    """Instances that are another instance again: the same file and label, or bit-identical content
    (a copied file under another name). A shape counted twice narrows the model's variance.

    Parameters
    ----------
    sources : dict name -> (file path, label)
    digests : dict name -> str, optional
        :func:`content_digest` of what each instance became (its object mask, or its coating).
    """
    by_source: dict = {}
    by_digest: dict = {}
    out = []
    for name, source in sources.items():
        digest = (digests or {}).get(name)
        if source in by_source:
            path, label = source
            where = f"{Path(str(path)).name}" + (f", label {label}" if label is not None else "")
            out.append(Finding(name, "duplicate", f"the same file and label as instance {by_source[source]!r} "
                                                  f"({where}): one shape counted twice"))
        elif digest is not None and digest in by_digest:
            out.append(Finding(name, "duplicate", f"identical to instance {by_digest[digest]!r} (bit for bit): the "
                                                  "same shape under another name, counted twice"))
        by_source.setdefault(source, name)
        if digest is not None:
            by_digest.setdefault(digest, name)
    return out


def _surface_points_world(object_volume) -> np.ndarray:

    verts, _ = marching_cubes(object_volume.mask)
    return object_volume.frame.to_world(object_volume.voxel_to_object(verts))


def _near_surface_distances(object_volume, points_world: np.ndarray, limit_mm: float) -> np.ndarray:
    """Distances (mm) of points to the mask's surface, looked up in a window of ``limit_mm``.

    The surface is taken at the boundary voxels' centres less half a voxel (within a
    voxel of the marching-cubes surface); a point with no boundary voxel within
    ``limit_mm`` gets ``inf``. A few hundred voxels per point: milliseconds per instance.
    """
    ov = object_volume
    mask = np.asarray(ov.mask, dtype=bool)
    h = float(ov.spacing_mm)
    ijk = ov.object_to_voxel(ov.frame.to_object(points_world))
    w = int(np.ceil(limit_mm / h)) + 2
    out = np.full(len(ijk), np.inf)
    shape = np.array(mask.shape)
    for k, c in enumerate(ijk):
        lo = np.maximum(np.floor(c).astype(int) - w, 0)
        hi = np.minimum(np.floor(c).astype(int) + w + 2, shape)
        if np.any(hi <= lo):
            continue
        sub = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
        pad = np.pad(sub, 1, mode="edge")
        boundary = sub & ~(pad[:-2, 1:-1, 1:-1] & pad[2:, 1:-1, 1:-1] & pad[1:-1, :-2, 1:-1] & pad[1:-1, 2:, 1:-1]
                           & pad[1:-1, 1:-1, :-2] & pad[1:-1, 1:-1, 2:])
        idx = np.argwhere(boundary)
        if len(idx):
            out[k] = max(float(np.sqrt(((idx + lo - c) ** 2).sum(axis=1).min())) * h - 0.5 * h, 0.0)
    return out


def check_landmarks_on_surface(name: str, object_volume, landmarks, params: QualityParams,
                               source: str = "") -> np.ndarray:
    """Every landmark must lie within ``params.max_landmark_distance_mm`` of its instance's surface.

    Returns the distances (mm). A landmark file whose points fit the surface far better
    with x and y negated gets an error saying the file's coordinate system (LPS vs RAS)
    is probably declared wrongly.

    Raises
    ------
    InputError
        Naming the instance, the landmark file, the farthest landmark and its distance.
    """
    if landmarks is None or not len(landmarks):
        return np.zeros(0)
    pts = np.asarray(landmarks.points_world, dtype=float)
    limit = params.max_landmark_distance_mm
    d = _near_surface_distances(object_volume, pts, limit)
    if float(d.max()) <= limit:
        return d
    tree = cKDTree(_surface_points_world(object_volume))  # the exact figures, for the message
    d = tree.query(pts)[0]
    if float(d.max()) <= limit:
        return d
    worst = int(np.argmax(d))
    where = source or landmarks.source or "its landmark file"
    flipped = tree.query(pts * np.array([-1.0, -1.0, 1.0]))[0]
    hint = ""
    if float(np.median(flipped)) <= limit and float(np.median(flipped)) < 0.2 * float(np.median(d)):
        hint = (f"; with x and y negated they lie {np.median(flipped):.1f} mm from it (median): the file's "
                f"coordinates look like LPS declared as RAS (or the reverse); fix its coordinate system")
    elif float(np.median(d)) > limit:
        hint = (f"; all {len(d)} landmarks are far (median {np.median(d):.0f} mm): the landmarks of another "
                f"instance, or of another image?")
    raise InputError(f"instance {name!r}: landmark {landmarks.names[worst]!r} of {where} is {d[worst]:.1f} mm from "
                     f"the instance's surface (allowed {limit:g} mm, [quality] max_landmark_distance_mm){hint}")


# ------------------------------------------------------------------------------ coating
def check_coating(name: str, fit, params: QualityParams) -> list[Finding]:
    """Gates on one coated instance (:class:`~ssm_addon.coating.coating.FitFigures`)."""
    out = []
    residuals = tuple(fit.landmark_residuals_mm)
    res = max(residuals, default=0.0)
    if res > params.max_landmark_residual_mm:
        names = tuple(fit.landmark_names)
        which = f"given landmark {names[residuals.index(res)]!r}" if len(names) == len(residuals) else "a given landmark"
        out.append(Finding(name, "landmark_residual", f"the coating is {res:.1f} mm from {which} (allowed "
                           f"{params.max_landmark_residual_mm:g} mm): landmarks inconsistent with the template's?",
                           res, params.max_landmark_residual_mm))
    if fit.folded_after > params.max_folded_triangles:
        out.append(Finding(name, "folds", f"{fit.folded_after} folded triangle(s) left (allowed "
                           f"{params.max_folded_triangles})", fit.folded_after, params.max_folded_triangles))
    vox = fit.max_distance_mm / max(fit.spacing_mm, 1e-12)
    if not math.isfinite(vox) or vox > params.max_surface_distance_vox:
        out.append(Finding(name, "surface_distance", f"a vertex is {fit.max_distance_mm:.2f} mm "
                           f"({vox:.2f} voxels) from the surface (allowed {params.max_surface_distance_vox:g} voxel)",
                           vox, params.max_surface_distance_vox))
    if params.require_convergence and not fit.converged:
        out.append(Finding(name, "convergence", f"the relaxation stopped at its limit of {fit.iterations} steps "
                           "before reaching its velocity tolerance", fit.iterations))
    return out


#: The coating's triangles this many times as long as the template's where a mesh lies beyond the
#: limit (``beyond["stretch"]``): the template stretched over a larger part, said in the finding
#: (docs/history.md, "The reach pulls every part at least a voxel thick")
STRETCHED = 1.5


def check_input_surface(name: str, distances: dict, params: QualityParams, template=None) -> list[Finding]:
    """Gate on a mesh instance's coating against the user's own mesh (``from_input``: the mesh's
    vertices to the coated surface, mm): far apart where the template's points do not reach a
    thin part of the surface, which the model then does not hold. ``template``: the
    ``[template]`` parameters, for the remedy. Where the coating's triangles there are at least
    ``STRETCHED`` times as long as the template's (``beyond["stretch"]``), the finding says so."""
    worst = float((distances.get("from_input") or {}).get("max_mm", float("nan")))
    if not (math.isfinite(worst) and worst > params.max_input_distance_mm):
        return []
    mean = float(distances["from_input"]["mean_mm"])
    if template is None:
        remedy = "use a denser template or a finer spacing"
    elif template.max_distance_mm is None:
        remedy = ("give the template a tolerance ([template] max_distance_mm = 1, now off) or make it denser "
                  f"(smaller r_min_mm and r_max_mm, now {template.r_min_mm:g} and {template.r_max_mm:g} mm)")
    else:
        remedy = (f"a smaller [template] max_distance_mm (now {template.max_distance_mm:g} mm) or a finer spacing (now "
                  f"{template.spacing_mm:g} mm); where that does not help, the coating does not reach a part the "
                  "template's instance holds smaller: a template from an instance that has it ([template] instance)")
    beyond = distances["from_input"].get("beyond") or {}
    where = ""
    cut = "cut off by the coating"
    stretch = float(beyond.get("stretch") or 0.0)
    if stretch >= STRETCHED:
        cut += (f", whose triangles there are up to {stretch:.1f}× as long as the template's (a part larger than the "
                "template instance's, and the template too sparse for it)")
    cause = f"a part of the surface, a thin process or a notch, is {cut}; {remedy}"
    if beyond.get("count"):
        x, y, z = beyond["centre_offset_mm"]
        where = (f"; {beyond['count']:,} of its vertices ({100 * beyond['share']:.2g} %) lie beyond, centred "
                 f"({x:+.0f}, {y:+.0f}, {z:+.0f}) mm from its centre (x, y, z, RAS)")
        voxels = beyond.get("voxels") or {}
        lost, h = int(voxels.get("count", 0)), float(voxels.get("spacing_mm", 0.0))
        # the instance's mesh_spacing sets only the voxels its object frame is found on; the
        # coating follows the voxels at the [template] spacing
        finer = f"a finer [template] spacing (now {h:g} mm) keeps a part finer than a voxel"
        if lost and lost >= beyond["count"]:
            cause = (f"they lie farther from the instance's {h:g} mm voxels, which the coating follows, than "
                     f"those voxels lie from the coating: a part finer than a voxel, lost at the import more "
                     f"than by the coating; {finer}")
        elif lost:
            cause = (f"{lost:,} of them lie farther from the instance's {h:g} mm voxels than those voxels lie "
                     f"from the coating (finer than a voxel: {finer}), the others are {cut}, a thin process or a "
                     f"notch; {remedy}")
    return [Finding(name, "input_surface", f"its mesh lies up to {worst:.2f} mm from its coating (mean {mean:.2f} mm; "
                    f"allowed {params.max_input_distance_mm:g} mm{where}): {cause}", worst,
                    params.max_input_distance_mm)]


def check_landmark_transfer(check, params: QualityParams) -> list[Finding]:
    """Gate on the correspondence self-check (:class:`~ssm_addon.correspondence.rounds.CorrespondenceCheck`):
    an instance whose given landmark lies far from where the other instances' model puts
    it (a landmark placed on the wrong feature, swapped, or a coating that slid)."""
    out = []
    for name, per in check.landmark_mm.items():
        worst = max(per, key=per.get)
        if per[worst] > params.max_landmark_transfer_mm:
            out.append(Finding(name, "landmark_transfer", f"given landmark {worst!r} is {per[worst]:.1f} mm from "
                               f"where the other instances' model puts it (allowed {params.max_landmark_transfer_mm:g}"
                               " mm): a landmark on the wrong place, or correspondence that slid",
                               per[worst], params.max_landmark_transfer_mm))
    return out


def check_frames(names, points: np.ndarray, reference: str, alignment: str,
                 max_turn_deg: float = 45.0) -> list[Finding]:
    """Gate on the model frame: with ``[model] alignment = "none"`` the coatings are modelled
    in their object frames, which must agree. An instance whose coating (N, 3 mm, in
    correspondence) is turned more than ``max_turn_deg`` against the template instance's
    had its frame's axes resolved otherwise (a near-symmetric shape whose moments frame
    flips): its turn would enter the model as shape variation."""
    names = list(names)
    if alignment != "none" or len(names) < 2 or reference not in names:
        return []
    pts = np.asarray(points, float)
    _s, rot, _t = procrustes_fit(pts, pts[names.index(reference)], scale=False)
    turn = np.degrees(np.arccos(np.clip((np.trace(rot, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))
    return [Finding(n, "frame", f"its coating is turned {a:.0f}° against the template instance's {reference!r} in "
                    f"the object frames (allowed {max_turn_deg:g}°): the frames disagree, and with [model] "
                    "alignment = \"none\" the turn IS modelled as shape (the model's first modes hold it); set "
                    "alignment = \"rigid\" (the default)", float(a), max_turn_deg)
            for n, a in zip(names, turn) if a > max_turn_deg]


def check_correspondence_rounds(rounds, check, tolerance_mm: float) -> list[Finding]:
    """Gate on the model method's rounds: stopping at the round limit means they did not settle."""
    if check.stop != "limit" or not rounds:
        return []
    last = rounds[-1]
    return [Finding("", "rounds", f"the correspondence rounds stopped at their limit of {len(rounds)} without "
                    f"settling: the mean shape still moved {last.mean_change_mm:.3f} mm in round {last.round} "
                    f"(tolerance {tolerance_mm:g} mm); raise [correspondence] iterations or check the landmarks",
                    last.mean_change_mm, tolerance_mm)]


# -------------------------------------------------------------------------------- model
EXACT_LOO_MAX = 300
SUBSPACE_MODES = 300
"""Above this many instances the leave-one-out scores use the model's leading subspace (see
:func:`_loo_scores_in_subspace`); below it, one n × n eigenproblem per instance."""
# a component of a rank-one downdate this small against the largest variance is deflated
# (:func:`_downdated_spectrum`): its eigenvalue would lie within rounding of its pole
DEFLATION = 1e-13


def _descending_eig(mat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of a symmetric matrix, largest first, without the numerically zero ones."""
    w, v = np.linalg.eigh(mat)
    order = np.argsort(w)[::-1]
    w, v = w[order], v[:, order]
    keep = w > 1e-10 * max(w[0], 1e-300)
    return w[keep], v[:, keep]


def _row_scores(lam: np.ndarray, b: np.ndarray, total: float, tt: float, npts: int, m: int,
                variance_fraction: float) -> tuple[float, int, float, float]:
    """(D², K, reconstruction RMS in mm, largest t) of one held-out shape, from its LOO model's
    variances ``lam`` (descending), its coefficients ``b``, the total variance and |y|² = ``tt``."""
    k = int(min(np.searchsorted(np.cumsum(lam) / total, variance_fraction - 1e-12) + 1, len(lam)))
    d2 = float(np.sum(b[:k] ** 2 / lam[:k]))
    rms = math.sqrt(max(tt - float(np.sum(b[:k] ** 2)), 0.0) / npts)
    t = float(np.max(np.abs(b[:k]) / np.sqrt(lam[:k] * (m + 1) / max(m - 1, 1))))
    return d2, k, rms, t


def _downdated_spectrum(w: np.ndarray, ci: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Variances λ (descending, numerically non-zero) of the model without instance i in the
    subspace, and the squared coefficients b² of the held-out shape on their modes.

    The covariance without i is (W − a cᵢcᵢᵀ)/m (m = n − 1, a = n/m): a diagonal less a rank
    one. Its eigenvalues come from LAPACK; for an eigenvector u of eigenvalue μ,
    (W/m − μ)u = (a/m)(cᵢ·u) cᵢ, so (cᵢ·u)² = 1 / ((a/m)² Σₖ cᵢₖ² / (wₖ/m − μ)²) (the
    secular equation's weights): the coefficients without the eigenvectors. A component
    whose part of the downdate is within rounding of the largest variance
    (a cᵢₖ² <= ``DEFLATION`` w₁) is deflated first: wₖ/m is a variance with mode eₖ (its
    eigenvalue would lie within rounding of the pole, where the weight is not determined).
    """
    m = n - 1
    a = n / m
    small = a * ci * ci <= DEFLATION * max(float(w[0]) if len(w) else 0.0, 1e-300)
    c, wk = ci[~small], w[~small]
    mu = np.linalg.eigvalsh((np.diag(wk) - a * np.outer(c, c)) / m)
    gap = (wk / m)[None, :] - mu[:, None]
    with np.errstate(divide="ignore"):  # a root on a pole (equal variances) holds none of cᵢ: weight 0
        spread = ((c * c)[None, :] / (gap * gap)).sum(axis=1)
    b2 = np.divide((n / m) ** 2, (a / m) ** 2 * spread, out=np.zeros(len(mu)), where=spread > 0)
    lam = np.concatenate([mu, w[small] / m])
    b2 = np.concatenate([b2, (ci[small] * (n / m)) ** 2])
    order = np.argsort(-lam, kind="stable")
    lam, b2 = lam[order], b2[order]
    keep = lam > 1e-10 * max(lam[0] if len(lam) else 0.0, 1e-300)
    return lam[keep], b2[keep]


def _loo_scores_in_subspace(xc: np.ndarray, npts: int, variance_fraction: float) -> dict:
    """Leave-one-out scores from one eigendecomposition plus an r × r eigenvalue problem per
    instance.

    With the full model's modes as basis (coefficients c_i, Σ c_i = 0, Σ c_i c_iᵀ = W
    diagonal), the model without i has mean −c_i/(n−1) and covariance
    S₋ᵢ = (W − n/(n−1) c_i c_iᵀ)/(n−1): a rank-one downdate, solved in the leading
    r = min(n − 1, :data:`SUBSPACE_MODES`) modes (:func:`_downdated_spectrum`). Exact up to
    301 instances; above, the total variance and the held-out shape's squared distance stay
    exact and what is lost is the part of the leave-one-out modes outside the full model's
    leading 300. O(min(n, 3N)³ + n r³).
    """
    n = len(xc)
    w, z, _v = gram_factor(xc)  # ascending, the non-zero ones
    w, z = w[::-1], z[:, ::-1]
    r = int(min(n - 1, SUBSPACE_MODES, len(w)))
    c = z[:, :r]  # (n, r) coordinates of the centred shapes in the leading modes
    total = float(w.sum())
    sq = np.einsum("ij,ij->i", xc, xc)  # |p_i − p̄|²
    m = n - 1
    m2, ks, err, tmax = np.full(n, np.nan), np.zeros(n, dtype=int), np.full(n, np.nan), np.full(n, np.nan)
    for i in range(n):
        lam, b2 = _downdated_spectrum(w[:r], c[i], n)
        if not len(lam):
            continue
        total_i = (total - sq[i] * n / m) / m  # exact variance of the model without i
        m2[i], ks[i], err[i], tmax[i] = _row_scores(lam, np.sqrt(b2), total_i, sq[i] * (n / m) ** 2, npts, m,
                                                     variance_fraction)
    return {"mahalanobis2": m2, "modes": ks, "loo_error_mm": err, "max_t": tmax}


def loo_outlier_scores(instance_points: np.ndarray, *, variance_fraction: float = 0.95, method: str = "auto") -> dict:
    """Leave-one-out outlier scores of every training shape (paper 5's model without it).

    For each instance i the model of the others (eqs. 4–6, 1/n normalisation) gives its
    coefficients b_k = q_k·(p_i − p̄) on the first K modes that hold
    ``variance_fraction`` of that model's variance, the squared Mahalanobis distance
    D² = Σ b_k²/λ_k and the reconstruction error (RMS over points, mm).

    ``method``: ``"exact"`` solves one n × n eigenproblem per instance (through the n × n Gram
    matrix); ``"subspace"`` works in the leading r <= :data:`SUBSPACE_MODES` modes of all
    instances, from the smaller of the Gram matrix and the 3N × 3N scatter, with one r × r
    eigenvalue problem per instance (:func:`_loo_scores_in_subspace`; the same scores to
    rounding up to 301 instances); ``"auto"`` takes the subspace above ``EXACT_LOO_MAX``
    instances.

    Returns
    -------
    dict with ``mahalanobis2`` (n,), ``modes`` (n,) K per instance, ``loo_error_mm`` (n,),
    and ``max_t`` (n,): the largest |b_k| / √(λ_k (m+1)/(m−1)) over the K modes, which for a
    new Gaussian shape follows Student's t with m − 1 degrees of freedom (m = n − 1).
    """
    if method not in ("auto", "exact", "subspace"):
        raise InputError(f"outlier scores: unknown method {method!r} (auto, exact, subspace)")
    x = np.asarray(instance_points, dtype=float)
    n = x.shape[0]
    flat = x.reshape(n, -1)
    xc = flat - flat.mean(axis=0)
    m2, ks, err, tmax = np.full(n, np.nan), np.zeros(n, dtype=int), np.full(n, np.nan), np.full(n, np.nan)
    if n < 3:
        return {"mahalanobis2": m2, "modes": ks, "loo_error_mm": err, "max_t": tmax}
    npts = x.shape[1]
    if method == "subspace" or (method == "auto" and n > EXACT_LOO_MAX):
        return _loo_scores_in_subspace(xc, npts, variance_fraction)
    gram = xc @ xc.T
    for i in range(n):
        rest = np.delete(np.arange(n), i)
        a = 1.0 / (n - 1)
        g_ii = gram[i, i]
        col = gram[rest, i]
        g = gram[np.ix_(rest, rest)] + a * (col[:, None] + col[None, :]) + a * a * g_ii
        yt = (col + a * g_ii) * (n / (n - 1))
        tt = g_ii * (n / (n - 1)) ** 2
        w, v = _descending_eig(g)
        if not len(w):
            continue
        lam = w / (n - 1)
        m2[i], ks[i], err[i], tmax[i] = _row_scores(lam, (v.T @ yt) / np.sqrt(w), float(lam.sum()), tt, npts, n - 1,
                                                     variance_fraction)
    return {"mahalanobis2": m2, "modes": ks, "loo_error_mm": err, "max_t": tmax}


def check_model(model, params: QualityParams) -> tuple[list[Finding], dict]:
    """Outlier gates on the training shapes of a model; returns (findings, scores per instance).

    An instance is an outlier when its coefficients in the model of the others are
    unlikely for a new shape of that Gaussian population. Two tests, the smaller p-value
    counts:

    * all k modes at once: with m = n − 1 training shapes, F = D² (m − k) / (k (m + 1))
      follows F(k, m − k) (Hotelling's prediction region; D² with the paper's 1/m
      variances), exact for small studies where a chi-square test flags ordinary shapes;
    * one mode far out: the largest |t| over the k modes, Student's t with m − 1 degrees
      of freedom, Bonferroni-corrected (× k): the F test has little power when many modes
      are kept and few shapes estimate them.

    A reconstruction finding needs the instance's leave-one-out reconstruction error above
    ``max_loo_error_ratio`` × the median and unlikely for a population of this size
    (:func:`reconstruction_p_values`: below ``1 - outlier_probability`` after n comparisons),
    so that the largest of a random population's errors is not named for being the largest.
    """
    names = [str(s) for s in model.instance_names]
    if len(names) > params.max_outlier_instances:
        return [], {}
    scores = loo_outlier_scores(model.instance_points, variance_fraction=params.outlier_variance_fraction)
    out, per = [], {}
    errors = scores["loo_error_mm"]
    median_err = float(np.nanmedian(errors)) if np.isfinite(errors).any() else float("nan")
    p_recon = reconstruction_p_values(errors)
    m = len(names) - 1
    for i, name in enumerate(names):
        d2, k, e = scores["mahalanobis2"][i], int(scores["modes"][i]), errors[i]
        if not math.isfinite(d2) or k < 1 or m - k < 1:
            continue
        scale = (m - k) / (k * (m + 1))
        p_all = float(fdtrc(k, m - k, d2 * scale))
        t_max = float(scores["max_t"][i])
        p_one = min(1.0, k * 2.0 * float(stdtr(max(m - 1, 1), -t_max)))
        p = min(p_all, p_one)
        per[name] = {"mahalanobis": math.sqrt(d2), "modes": k, "p_value": p, "p_value_all_modes": p_all,
                     "largest_t": t_max, "p_value_one_mode": p_one, "loo_error_mm": float(e),
                     "loo_error_ratio": float(e / median_err) if median_err > 0 else None,
                     "loo_error_p_value": float(p_recon[i])}
        if p < 1.0 - params.outlier_probability:
            why = (f"{t_max:.1f} standard deviations out along one mode" if p_one <= p_all
                   else f"Mahalanobis distance {math.sqrt(d2):.2f} over {k} modes")
            out.append(Finding(name, "outlier", f"unlike the other instances: {why} of the model without it "
                               f"(p = {p:.2g}, below {1 - params.outlier_probability:.2g})", p,
                               1.0 - params.outlier_probability))
        if (median_err > 0 and e / median_err > params.max_loo_error_ratio
                and p_recon[i] < 1.0 - params.outlier_probability):
            out.append(Finding(name, "reconstruction", f"the model without it reconstructs it with {e:.2f} mm RMS, "
                               f"{e / median_err:.1f}× the median of the instances (allowed "
                               f"{params.max_loo_error_ratio:g}×; p = {p_recon[i]:.2g} that one of {len(names)} "
                               "instances of one population lies so far out)", e / median_err,
                               params.max_loo_error_ratio))
    return out, per


def reconstruction_p_values(errors: np.ndarray) -> np.ndarray:
    """Per instance, how likely a population of this size holds a leave-one-out reconstruction error
    so far above the others' (one-sided, Bonferroni-corrected × n).

    The logarithm of each error against the others' (their mean and SD): t = (log e_i − mean) /
    (SD √(1 + 1/m)) follows Student's t with m − 1 degrees of freedom for m others from one
    log-normal population (the prediction interval of a new value). NaN errors and populations
    of fewer than 4 give 1 (nothing said).

    >>> p = reconstruction_p_values(np.array([1.0, 1.1, 0.9, 1.05, 0.95, 1.02, 0.98, 3.0]))
    >>> bool(p[-1] < 0.01), bool(p[:-1].min() > 0.5)
    (True, True)
    """
    e = np.asarray(errors, float)
    out = np.ones(len(e))
    ok = np.isfinite(e) & (e > 0)
    n = int(ok.sum())
    m = n - 1  # the others of each instance
    if m < 3:
        return out
    le = np.log(e[ok])
    centred = le - le.mean()  # the others' mean and SD from the whole set's sums, without the one
    mean = (centred.sum() - centred) / m
    var = np.maximum((np.sum(centred ** 2) - centred ** 2 - m * mean ** 2) / (m - 1), 0.0)
    sd = np.sqrt(var)
    gap = centred - mean
    scale = sd * math.sqrt(1.0 + 1.0 / m)
    spread = sd > 1e-7 * max(1.0, float(np.abs(centred).max()))  # above the sums' rounding
    t = np.where(spread, gap / np.where(spread, scale, 1.0), 0.0)
    p = np.minimum(1.0, n * stdtr(m - 1, -t))
    out[ok] = np.where(spread, p, np.where(gap > 0, 0.0, 1.0))
    return out


def warnings_text(findings: list[Finding]) -> str:
    """The WARNINGS summary: one line per finding, grouped by instance."""
    if not findings:
        return ""
    lines = [f"WARNINGS ({len(findings)} in {len({f.instance for f in findings})} instance(s); "
             "thresholds in [quality]):"]
    lines += [f"  {f.instance or 'study'} [{f.gate}]: {f.message}" for f in findings]
    return "\n".join(lines)
