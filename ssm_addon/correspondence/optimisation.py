"""Correspondence optimised across the population: points slide along their surfaces.

After the coating (paper 4) every instance carries the template's points, and the
correspondence between instances is what the landmark warp and the relaxation made of it.
This stage moves each instance's points *along its own surface* (object frame, mm; the
0.5 iso-surface of its binary object, through the sub-voxel distance map of paper 4.2) to
lower an objective of the whole population, balanced by terms that keep each instance's
mesh as it is where nothing asks it to move:

* **population term** -- the entropy of the shapes' distribution under a Gaussian model,
  ``H = 1/2 sum_j log(1 + lambda_j / alpha)`` (nats; lambda_j the eigenvalues of the
  covariance of the similarity-aligned shape vectors, eq. 5, alpha a floor that keeps the
  log finite where n < 3N): the correspondence entropy of Cates et al. (2007), which
  ShapeWorks minimises, the determinant of the covariance of Kotcheff & Taylor (1998), and
  Thodberg's (2003) simplification of the description length of Davies et al. (2002),
  whose cost per mode is log(lambda_j) above a cut-off and linear below it. We chose this
  form because its gradient needs only the thin SVD of the centred shapes (n x 3N: no
  reparameterisation of a sphere, so it works for any genus, and with a randomized SVD
  above :data:`EXACT_SVD_MAX_INSTANCES` instances its cost grows linearly with n), and
  because alpha states in mm what a negligible mode is. Each outer iteration linearises H
  at the current shapes: instance k's points are pulled towards ``y_k - sum_j
  alpha / (lambda_j + alpha) (y_k . v_j) v_j`` (model frame; brought back to the object
  frame by the inverse of its similarity alignment), which removes the part of its
  deviation from the mean that lies in the weak modes (lambda_j << alpha) and leaves the
  strong ones;
* **regularity** -- springs on the template's edges with the coating's own edge lengths as
  rest lengths (eq. 3's first term): the points stay evenly spread as the coating spread
  them, and a triangle is never folded (a step that would fold one keeps its vertices
  where they were);
* **landmarks held** -- a given landmark's place on the mesh (its triangle and barycentric
  weights, :class:`~ssm_addon.meshutil.LandmarkLocations`) is pulled to where the
  coating's landmark warp put it (the given landmark, or the model method's denoised one),
  with weight ``landmark_hold`` against one spring.

Every force is reduced to its tangential part (the distance map's normal) and each step
ends with the coating's projection onto the surface, so points are no farther from the
surface than the coating leaves them. The inner steps are damped Jacobi steps of the
quadratic energy (each vertex's step 0.8 of its force over its stiffness). The outer iterations stop when
the points move less than ``tolerance_mm`` (RMS over every point) or after
``optimise_iterations``.

Whether the population term lands points nearer their true places is a matter of
measurement, not of compactness: a configuration that is more compact is not necessarily
a better correspondence (the term can also shrink true shape variation). The defaults are
those that the dense-truth sets support (``docs/history.md``, "Correspondence
optimised across the population").

References
----------
.. [1] J. Cates, P. T. Fletcher, M. Styner, M. Shenton, R. Whitaker, "Shape modeling and
   analysis with entropy-based particle systems", IPMI 2007, LNCS 4584, pp. 333-345.
.. [2] A. C. W. Kotcheff, C. J. Taylor, "Automatic construction of eigenshape models by
   direct optimization", Medical Image Analysis 2(4), 1998, pp. 303-314.
.. [3] R. H. Davies, C. J. Twining, T. F. Cootes, J. C. Waterton, C. J. Taylor, "A minimum
   description length approach to statistical shape modeling", IEEE TMI 21(5), 2002.
.. [4] H. H. Thodberg, "Minimum description length shape and appearance models", IPMI
   2003, LNCS 2732, pp. 51-62.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..base.compute import executor_or_local
from ..base.errors import Cancelled, InputError, check_cancelled
from ..base.params import CoatingParams, CorrespondenceParams
from ..base.progress import CancelledFn, ProgressFn, report
from ..coating.distance_map import DistanceMap
from ..coating.relaxation import folded_triangles
from ..instances.importing import InstanceSpec, import_instance
from ..instances.volume import ObjectVolume
from ..meshutil import LandmarkLocations, edge_lengths
from ..meshutil import edges as mesh_edges
from ..model.pca import gram_factor, leading_modes, procrustes_fit

__all__ = ["EXACT_SVD_MAX_INSTANCES", "INNER_STEPS", "InstanceSource", "LandmarkHold", "Optimisation",
           "OptimisationCancelled", "OptimisationStep", "entropy_pull", "landmark_holds", "optimise_correspondence",
           "slide_on_surface"]

#: Inner (damped Jacobi) steps per instance and outer iteration.
INNER_STEPS = 10
#: Up to this many instances the population term uses the exact thin SVD (its Gram matrix,
#: n^2 * 3N); above, a randomized SVD of :data:`RANDOMIZED_MODES` modes (n * 3N * modes), so
#: the cost grows linearly with the number of instances.
EXACT_SVD_MAX_INSTANCES = 300
RANDOMIZED_MODES = 100
#: A point's step is this share of its force over its stiffness (a damped Jacobi step).
JACOBI_DAMPING = 0.8
#: Largest step of a point in one inner step, in voxels of its instance's spacing.
STEP_LIMIT_VOX = 0.25


@dataclass(frozen=True)
class InstanceSource:
    """Where a worker finds an instance's surface when its volume is not at hand (a streamed
    build keeps one volume): the instance and the import settings of paper 2."""

    spec: InstanceSpec
    spacing_mm: float
    frame_method: str
    space: str = "auto"
    distance_map_store: str = ""

    def volume(self) -> ObjectVolume:
        """The instance imported (paper 2), its distance map kept in ``distance_map_store`` when named."""
        ov = import_instance(self.spec, spacing_mm=self.spacing_mm, frame_method=self.frame_method, space=self.space)
        return replace(ov, distance_map_store=self.distance_map_store) if self.distance_map_store else ov


@dataclass(frozen=True)
class LandmarkHold:
    """The landmarks of one instance held during the optimisation.

    Attributes
    ----------
    triangles : (L,) int
        The template triangle of each landmark.
    bary : (L, 3)
        Its barycentric weights.
    targets_object : (L, 3) mm
        Where each is held (object frame of the instance).
    names : tuple of str
    """

    triangles: np.ndarray
    bary: np.ndarray
    targets_object: np.ndarray
    names: tuple = ()

    def points(self, points_object: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """(L, 3) mm: the landmarks' places on a mesh with the template's faces."""
        return np.einsum("lk,lkj->lj", self.bary, points_object[faces[self.triangles]])

    def residuals_mm(self, points_object: np.ndarray, faces: np.ndarray) -> np.ndarray:
        return np.linalg.norm(self.points(points_object, faces) - self.targets_object, axis=1)


def landmark_holds(locations: LandmarkLocations, faces: np.ndarray, warped: Mapping[str, np.ndarray],
                   given: Mapping[str, Sequence[str]]) -> dict[str, LandmarkHold]:
    """Each instance's given landmarks as :class:`LandmarkHold`: held where its landmark warp
    (eq. 2) put the template's landmark (``warped[name]``, object mm: the warp maps them
    exactly onto the landmarks it was given). Instances without given landmarks hold none.

    Examples
    --------
    >>> loc = LandmarkLocations(("a", "b"), np.array([0, 0]), np.array([[1.0, 0, 0], [0, 1.0, 0]]))
    >>> faces = np.array([[0, 1, 2]])
    >>> holds = landmark_holds(loc, faces, {"i": np.eye(3)}, {"i": ["b"], "j": []})
    >>> sorted(holds), holds["i"].names, holds["i"].targets_object.tolist()
    (['i'], ('b',), [[0.0, 1.0, 0.0]])
    """
    out = {}
    faces = np.asarray(faces)
    for name, names in given.items():
        keep = [i for i, n in enumerate(locations.names) if n in set(names)]
        if not keep or name not in warped:
            continue
        tri, bary = locations.triangles[keep], locations.bary[keep]
        at = np.einsum("lk,lkj->lj", bary, np.asarray(warped[name], float)[faces[tri]])
        out[name] = LandmarkHold(tri, bary, at, tuple(locations.names[i] for i in keep))
    return out


@dataclass(frozen=True)
class OptimisationStep:
    """One outer iteration, measured after it.

    Attributes
    ----------
    iteration : int
        1, 2, ...
    objective : float
        ``population_weight * entropy_nats + regularity``: what the iterations lower.
    entropy_nats : float
        The population term H of the shapes the iteration left (nats, module docstring).
    regularity : float
        Mean over instances of the spring and landmark energy per point, in squared voxels
        (0 where every edge has its rest length and every landmark its place).
    landmark_mm : float
        RMS distance of the held landmarks from their places (mm; 0 without landmarks).
    movement_mm : float
        RMS movement of every point in this iteration (mm).
    folds : int
        Folded triangles over all instances after it.
    """

    iteration: int
    objective: float
    entropy_nats: float
    regularity: float
    landmark_mm: float
    movement_mm: float
    folds: int = 0

    def to_dict(self) -> dict:
        return {k: (int(v) if k in ("iteration", "folds") else float(v)) for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class Optimisation:
    """The optimised correspondence and how it got there.

    Attributes
    ----------
    points : dict name -> (N, 3) mm
        Every instance's points after the optimisation (object frame of the instance).
    steps : tuple of OptimisationStep
        One per outer iteration; ``steps[0]`` is iteration 0, the start (movement 0).
    stop : str
        ``"converged"`` (moved less than the tolerance), ``"limit"`` (the iterations ran
        out) or ``"cancelled"`` (the last complete iteration is kept).
    instance_movement_mm : dict name -> float
        RMS distance of each instance's points from where the coating put them (mm).
    point_movement_mm : (N,) ndarray
        Mean over the instances of each point's distance from its coated place (mm): where
        on the template (and the mean shape) points moved most.
    surface_distance_mm, surface_mean_mm : dict name -> float
        Largest and mean distance of an instance's points from its surface after the
        optimisation (mm, exact to the marching-cubes surface, as the coating's fit figures).
    folds : dict name -> int
        Folded triangles after the optimisation.
    seconds : float
    """

    points: dict
    steps: tuple
    stop: str
    instance_movement_mm: dict = field(default_factory=dict)
    point_movement_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    surface_distance_mm: dict = field(default_factory=dict)
    surface_mean_mm: dict = field(default_factory=dict)
    folds: dict = field(default_factory=dict)
    seconds: float = 0.0

    @property
    def iterations(self) -> int:
        """Iterations done (the last step's number: without the population term every iteration's
        steps run in one task per instance, measured once at the end)."""
        return int(self.steps[-1].iteration) if self.steps else 0

    def to_dict(self) -> dict:
        """JSON-ready record (``report.json``'s ``correspondence.optimisation``), without the points."""
        return {"iterations": self.iterations, "stop": self.stop, "steps": [s.to_dict() for s in self.steps],
                "instance_movement_mm": {k: float(v) for k, v in self.instance_movement_mm.items()},
                "point_movement_mm": [float(x) for x in np.asarray(self.point_movement_mm, float)],
                "surface_distance_mm": {k: float(v) for k, v in self.surface_distance_mm.items()},
                "surface_mean_mm": {k: float(v) for k, v in self.surface_mean_mm.items()},
                "folds": {k: int(v) for k, v in self.folds.items()}, "seconds": float(self.seconds)}

    @classmethod
    def from_dict(cls, d: Mapping) -> Optimisation:
        """The record of :meth:`to_dict` (no points)."""
        return cls(points={}, steps=tuple(OptimisationStep(**s) for s in d.get("steps", ())), stop=str(d.get("stop", "")),
                   instance_movement_mm=dict(d.get("instance_movement_mm", {})),
                   point_movement_mm=np.asarray(d.get("point_movement_mm", ()), float),
                   surface_distance_mm=dict(d.get("surface_distance_mm", {})),
                   surface_mean_mm=dict(d.get("surface_mean_mm", {})), folds=dict(d.get("folds", {})),
                   seconds=float(d.get("seconds", 0.0)))


class OptimisationCancelled(Cancelled):
    """The optimisation was cancelled; ``result`` holds the last complete iteration."""

    def __init__(self, message: str, result: Optimisation):
        super().__init__(message)
        self.result = result


# --------------------------------------------------------------------------- population term
def _aligned(points: np.ndarray, iterations: int = 3):
    """Similarity alignment of (n, N, 3) shapes to their mean (generalized Procrustes from the
    first shape): aligned shapes, and s (n,), R (n, 3, 3), t (n, 3) with aligned = s x R^T + t."""
    mean = points[0]
    for _ in range(iterations):
        s, rot, t = procrustes_fit(points, mean, scale=True)
        aligned = s[:, None, None] * np.einsum("inj,ikj->ink", points, rot) + t[:, None]
        mean = aligned.mean(axis=0)
    return aligned, s, rot, t


def entropy_pull(points: np.ndarray, *, min_variance: float) -> tuple[np.ndarray, float]:
    """The linearised population term: each shape's pull, object frame of each shape (mm).

    Parameters
    ----------
    points : (n, N, 3) mm
        Corresponding points of every instance, each in its own object frame.
    min_variance : float
        alpha as a share of the total variance (the sum of the covariance's eigenvalues).

    Returns
    -------
    pull : (n, N, 3) mm
        ``-sum_j alpha / (lambda_j + alpha) (y_k . v_j) v_j`` of each centred, similarity-aligned
        shape y_k, turned and scaled back into the instance's frame (its descent direction of H
        times alpha; see the module docstring).
    entropy : float
        H = 1/2 sum_j log(1 + lambda_j / alpha), nats.

    Examples
    --------
    Shapes that differ along one direction only (one strong mode) are pulled by about
    ``min_variance`` of their deviation; a small deviation of one shape on its own is pulled
    most of the way back (part of it goes into the alignment and the mean):

    >>> rng = np.random.default_rng(0)
    >>> base = rng.normal(size=(50, 3))
    >>> shapes = np.stack([base + [0.0, 0.0, 0.5 * k] * (base[:, :1] > 0) for k in range(6)])
    >>> pull, h = entropy_pull(shapes, min_variance=1e-3)
    >>> bool(np.abs(pull).max() < 0.01 * np.abs(shapes - shapes.mean(axis=0)).max()), h > 0
    (True, True)
    >>> bumped = shapes.copy(); bumped[2, 7] += [0.0, 0.02, 0.0]
    >>> pull = entropy_pull(bumped, min_variance=1e-3)[0]
    >>> bool(-pull[2, 7, 1] > 0.5 * 0.02)
    True
    """
    points = np.asarray(points, float)
    n, npts, _ = points.shape
    if n < 3:
        raise InputError(f"correspondence optimisation: the population term needs at least 3 instances, got {n}")
    aligned, s, rot, _t = _aligned(points)
    centred = (aligned - aligned.mean(axis=0)).reshape(n, -1)
    total = float((centred ** 2).sum()) / (n - 1)
    alpha = max(float(min_variance) * total, 1e-300)
    if n <= EXACT_SVD_MAX_INSTANCES:
        w, z, _v = gram_factor(centred)  # z (n, r) = coefficients of the shapes on the modes times ...
        lam = w / (n - 1)
        # centred = U S Vt with U = v, S = sqrt(w): the pull's coefficients on the modes are
        # -alpha / (lambda + alpha) * (U S)_kj; as a matrix of shapes: -(v diag(alpha/(lam+alpha)) v^T) centred
        coef = _v * (alpha / (lam + alpha))
        pull = -(coef @ (_v.T @ centred))
        entropy = 0.5 * float(np.log1p(lam / alpha).sum())
    else:
        k = min(RANDOMIZED_MODES, n - 1)
        lam, modes = leading_modes(centred, n - 1, k, seed=0)
        scores = centred @ modes.T  # (n, k)
        # weak directions (beyond the k modes) count as variance 0: pulled entirely
        pull = -(centred - (scores * (lam / (lam + alpha))) @ modes)
        rest = max(total - float(lam.sum()), 0.0)
        entropy = 0.5 * float(np.log1p(lam / alpha).sum()) + 0.5 * math.log1p(rest / alpha)
    pull = pull.reshape(n, npts, 3)
    # back into each instance's frame: aligned = s x R^T + t, so a displacement d there is d R / s here
    return np.einsum("inj,ijk->ink", pull, rot) / s[:, None, None], entropy


# --------------------------------------------------------------------------- one instance
def slide_on_surface(points: np.ndarray, faces: np.ndarray, dm: DistanceMap, rest_lengths: np.ndarray, *,
                     targets: np.ndarray | None = None, population_weight: float = 0.0,
                     hold: LandmarkHold | None = None, landmark_hold: float = 1.0, steps: int = INNER_STEPS,
                     tolerance_mm: float = 0.0, coating: CoatingParams | None = None,
                     edges: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
    """Lower one instance's energy by moving its points along its surface (object frame, mm).

    The energy: ``population_weight/2 sum|p - targets|^2 + 1/2 sum_edges (|e| - rest)^2 +
    landmark_hold/2 sum_landmarks |place - target|^2``; each of ``steps`` damped Jacobi steps
    moves a point by :data:`JACOBI_DAMPING` times its tangential force over its stiffness (at most
    :data:`STEP_LIMIT_VOX` voxels), projects it onto the surface (paper 4.2) and keeps the
    vertices of a triangle the step would fold where they were. The steps stop early when one
    moves no point by ``tolerance_mm`` or more.

    Returns
    -------
    points : (N, 3) mm
    figures : dict
        ``energy`` (per point, squared voxels: springs and landmarks), ``landmark_rms_mm``,
        ``folds`` (folded triangles left), ``surface_distance_mm`` and ``surface_mean_mm`` (largest
        and mean, exact to the marching-cubes surface),
        ``steps`` (taken), ``converged`` (the last step moved less than ``tolerance_mm``).
    """
    coating = coating or CoatingParams()
    faces = np.asarray(faces)
    e = mesh_edges(faces) if edges is None else edges
    p = np.array(points, float)
    npts = len(p)
    h = dm.spacing_mm
    stiffness = np.bincount(e.ravel(), minlength=npts).astype(float) + float(population_weight) * (targets is not None)
    if hold is not None and len(hold.triangles):
        corners = faces[hold.triangles]
        stiffness += landmark_hold * np.bincount(corners.ravel(), weights=(hold.bary ** 2).ravel(), minlength=npts)
    rate = JACOBI_DAMPING / np.maximum(stiffness, 1e-12)
    limit = STEP_LIMIT_VOX * h
    folded_start = folded_triangles(p, faces, dm)

    def force(q):
        d = q[e[:, 1]] - q[e[:, 0]]
        length = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        fe = ((length - rest_lengths) / length)[:, None] * d
        f = np.zeros_like(q)
        for k in range(3):  # the springs, axis by axis (bincount is ordered: the same sums everywhere)
            f[:, k] = np.bincount(e[:, 0], weights=fe[:, k], minlength=npts) - np.bincount(e[:, 1], weights=fe[:, k],
                                                                                           minlength=npts)
        energy = 0.5 * float(((length - rest_lengths) ** 2).sum())
        if targets is not None and population_weight > 0:
            f += population_weight * (targets - q)
        if hold is not None and len(hold.triangles):
            r = hold.targets_object - hold.points(q, faces)
            energy += 0.5 * landmark_hold * float((r ** 2).sum())
            corners = faces[hold.triangles]
            for k in range(3):
                f[:, k] += landmark_hold * np.bincount(corners.ravel(), weights=(hold.bary * r[:, k:k + 1]).ravel(),
                                                       minlength=npts)
        return f, energy

    taken, converged = 0, False
    for _ in range(int(steps)):
        taken += 1
        f, _energy = force(p)
        _d, g = dm.sample(p)
        nrm = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
        f -= (f * nrm).sum(axis=1, keepdims=True) * nrm
        step = rate[:, None] * f
        size = np.linalg.norm(step, axis=1, keepdims=True)
        step *= np.minimum(1.0, limit / np.maximum(size, 1e-12))
        q = dm.project(p + step, coating.projection_iterations)
        new_folds = folded_triangles(q, faces, dm) & ~folded_start
        if new_folds.any():
            back = np.unique(faces[new_folds])
            q[back] = p[back]
        moved = float(np.sqrt(((q - p) ** 2).sum(axis=1).max()))
        p = q
        if moved < tolerance_mm:
            converged = True
            break
    _f, energy = force(p)
    figures = {"energy": energy / (npts * h * h),
               "landmark_rms_mm": (float(np.sqrt((hold.residuals_mm(p, faces) ** 2).mean()))
                                   if hold is not None and len(hold.triangles) else 0.0),
               "folds": int(folded_triangles(p, faces, dm).sum()),
               "steps": taken, "converged": converged}
    exact = dm.surface_distance(p)
    figures.update(surface_distance_mm=float(exact.max()), surface_mean_mm=float(exact.mean()))
    return p, figures


def _slide_job(args):
    surface, points, faces, rest, targets, weight, hold, landmark_hold, steps, tolerance_mm, coating = args
    volume = surface.volume() if isinstance(surface, InstanceSource) else surface
    dm = DistanceMap.from_object_volume(volume)
    return slide_on_surface(points, faces, dm, rest, targets=targets, population_weight=weight, hold=hold,
                            landmark_hold=landmark_hold, steps=steps, tolerance_mm=tolerance_mm, coating=coating)


# --------------------------------------------------------------------------- the population
def optimise_correspondence(points: Mapping[str, np.ndarray], faces: np.ndarray,
                            surfaces: Mapping[str, ObjectVolume | InstanceSource], *,
                            params: CorrespondenceParams | None = None, coating: CoatingParams | None = None,
                            holds: Mapping[str, LandmarkHold] | None = None, jobs: int = 1, executor=None,
                            progress: ProgressFn = None, cancelled: CancelledFn = None,
                            on_step: Callable[[OptimisationStep], None] | None = None) -> Optimisation:
    """Slide every instance's points along its surface to lower the population's objective.

    Parameters
    ----------
    points : dict name -> (N, 3) mm
        The coated points of every instance (its object frame), in study order.
    faces : (F, 3) int
        The template's triangles (paper 3).
    surfaces : dict name -> ObjectVolume or InstanceSource
        Each instance's object (its distance map is the surface, paper 4.2).
    params : CorrespondenceParams
        ``optimise_iterations``, ``population_weight``, ``min_variance``, ``landmark_hold``,
        ``optimise_tolerance_mm``.
    holds : dict name -> LandmarkHold, optional
        The landmarks held (:func:`landmark_holds`).
    executor : Executor, optional
        Where each instance's steps run (default ``jobs`` local processes); one map per
        outer iteration, each instance in one task.
    on_step : callable, optional
        Called with each iteration's :class:`OptimisationStep` as it ends (progress lines).

    Returns
    -------
    Optimisation

    Raises
    ------
    OptimisationCancelled
        ``cancelled()`` returned True; ``.result`` is the last complete iteration.
    """
    params = params or CorrespondenceParams()
    names = list(points)
    holds = dict(holds or {})
    faces = np.asarray(faces, np.int64)
    missing = [n for n in names if n not in surfaces]
    if missing:
        raise InputError(f"correspondence optimisation: no surface for {', '.join(missing)}")
    start = {n: np.array(points[n], float) for n in names}
    t0 = time.perf_counter()
    e = mesh_edges(faces)
    rest = {n: edge_lengths(start[n], e) for n in names}
    weight = float(params.population_weight)
    use_population = weight > 0 and len(names) >= 3
    iterations = int(params.optimise_iterations)
    current = dict(start)
    figures = {n: {} for n in names}
    steps: list[OptimisationStep] = []

    spacing = {n: float(surfaces[n].spacing_mm) for n in names}  # a volume's, or the import's (the same)

    def measure(it: int, moved: float) -> OptimisationStep:
        stack = np.stack([current[n] for n in names])
        entropy = entropy_pull(stack, min_variance=params.min_variance)[1] if len(names) >= 3 else 0.0
        energy, residuals = [], []
        for n in names:  # the springs' and the landmarks' energy per point, in squared voxels
            e_n = 0.5 * float(((edge_lengths(current[n], e) - rest[n]) ** 2).sum())
            if n in holds:
                r = holds[n].residuals_mm(current[n], faces)
                residuals.append(r)
                e_n += 0.5 * float(params.landmark_hold) * float((r ** 2).sum())
            energy.append(e_n / (len(current[n]) * spacing[n] ** 2))
        reg = float(np.mean(energy))
        lm = float(np.sqrt(np.mean(np.concatenate(residuals) ** 2))) if residuals else 0.0
        step = OptimisationStep(it, weight * entropy + reg, entropy, reg, lm, moved,
                                int(sum(figures[n].get("folds", 0) for n in names)))
        steps.append(step)
        if on_step is not None:
            on_step(step)
        return step

    def result(stop: str) -> Optimisation:
        moved = {n: float(np.sqrt(((current[n] - start[n]) ** 2).sum(axis=1).mean())) for n in names}
        per_point = np.mean([np.linalg.norm(current[n] - start[n], axis=1) for n in names], axis=0)
        return Optimisation(points=dict(current), steps=tuple(steps), stop=stop, instance_movement_mm=moved,
                            point_movement_mm=per_point,
                            surface_distance_mm={n: figures[n]["surface_distance_mm"] for n in names
                                                 if "surface_distance_mm" in figures[n]},
                            surface_mean_mm={n: figures[n]["surface_mean_mm"] for n in names
                                             if "surface_mean_mm" in figures[n]},
                            folds={n: figures[n].get("folds", 0) for n in names},
                            seconds=time.perf_counter() - t0)

    measure(0, 0.0)
    # without the population term the instances do not depend on each other: every step in one task
    outer, inner = (iterations, INNER_STEPS) if use_population else (1, INNER_STEPS * iterations)
    stop = "limit"
    with executor_or_local(executor, jobs, len(names)) as pool:
        for it in range(1, outer + 1):
            try:
                check_cancelled(cancelled)
            except Cancelled:
                raise OptimisationCancelled(f"correspondence optimisation cancelled after {it - 1} iteration(s)",
                                            result("cancelled")) from None
            targets = {}
            if use_population:
                stack = np.stack([current[n] for n in names])
                pull = entropy_pull(stack, min_variance=params.min_variance)[0]
                targets = {n: current[n] + pull[k] for k, n in enumerate(names)}
            args = [(surfaces[n], current[n], faces, rest[n], targets.get(n), weight if use_population else 0.0,
                     holds.get(n), float(params.landmark_hold), inner,
                     0.0 if use_population else float(params.optimise_tolerance_mm), coating) for n in names]
            try:
                out = pool.map(_slide_job, args, labels=names, verb="optimised", cancelled=cancelled)
            except Cancelled:
                raise OptimisationCancelled(f"correspondence optimisation cancelled after {it - 1} iteration(s)",
                                            result("cancelled")) from None
            before = current
            current = {n: o[0] for n, o in zip(names, out)}
            figures = {n: o[1] for n, o in zip(names, out)}
            moved = float(np.sqrt(np.mean([((current[n] - before[n]) ** 2).sum(axis=1).mean() for n in names])))
            measure(it if use_population else iterations, moved)
            report(progress, it / outer, f"optimisation: iteration {steps[-1].iteration}/{iterations}, objective "
                                         f"{steps[-1].objective:.4f}")
            if use_population and moved < params.optimise_tolerance_mm:
                stop = "converged"
                break
    if not use_population and all(figures[n].get("converged") for n in names):
        stop = "converged"
    return result(stop)
