"""Correspondence without landmarks: the template put onto each instance by a dense similarity
registration of the two surfaces from every rotation of the object frame's axes (paper 2), then
coated (paper 4.2); turns the population disagrees with found and corrected.

Without landmarks nothing but the shapes anchors the correspondence. The object frames
(centre of mass, second-moment axes) align the template with an instance roughly (paper fig.
8, left), but a near-symmetric shape's axes may come out turned end for end, two nearly equal
second moments may swap two axes, and a mesh in scanner coordinates pairs its axes with the
patient's however it lies; a turn of the template is then a correspondence that maps the front
of one instance onto the back of another. So each instance's start is the template in the pose
that fits its surface best (:func:`template_start`): registered as a similarity (rotation,
translation, one scale; symmetric closest points weighted by area, :func:`surface_similarity`)
from each of the 24 rotations that map the frame's axes onto themselves
(:data:`FRAME_ROTATIONS`) and from the pose of the input coordinates, which is preferred unless
another fits :data:`~ssm_addon.correspondence.rounds.WORLD_POSE_TOLERANCE` times closer. The
surfaces are sampled by area, not by the template's points, which eq. (1) makes denser where
the surface is curved. After every instance is coated, an instance whose coating lies far from
the population's mean shape (by its correspondence, rigidly) is coated again from the other
rotations and the one nearest the others' mean is kept (:func:`population_turns`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ..base.compute import executor_or_local
from ..base.params import CoatingParams
from ..base.progress import CancelledFn
from ..coating.coating import CoatingResult, CoatingStart, coat_from_start
from ..coating.distance_map import DistanceMap
from ..coating.registration import register_to_surface
from ..fitting.fit import AXIS_ROTATIONS, Pose, axis_rotation, turn_angle_deg, weighted_pose
from ..instances.volume import ObjectFrame, ObjectVolume
from ..meshutil import Mesh, MeshLocator, face_centroids, face_normals
from ..model.pca import procrustes_fit
from .rounds import AXIS_TURNS, WORLD_POSE_TOLERANCE, aligned_to

__all__ = ["FRAME_ROTATIONS", "ROTATION_NAMES", "nearest_frame_rotation", "TURN_NAMES", "TURNED_FACTOR", "FramesStart", "SurfacePairs", "area_samples", "input_rotation", "coat_from_template_pose", "coat_without_landmarks",
           "far_from_population", "population_turns", "surface_similarity", "template_start", "TWIST_FACTOR", "TWIST_MIN_DEG", "Twist", "coating_twists", "twisted"]



def _frame_rotations() -> tuple[np.ndarray, ...]:
    """The 24 proper rotations that map the coordinate axes onto themselves (signed permutation
    matrices of determinant 1), the identity and the three turns of 180 degrees about x, y, z
    (:data:`~ssm_addon.correspondence.rounds.AXIS_TURNS`) first, the rest in the order of
    :data:`~ssm_addon.fitting.fit.AXIS_ROTATIONS`."""
    out = [np.asarray(r, float) for r in AXIS_TURNS]
    return tuple(out + [r for r in AXIS_ROTATIONS if not any(np.array_equal(r, q) for q in out)])


#: The rotations a template's first pose on an instance is registered from: every way the object
#: frames' axes (paper 2) can map onto each other, so that axes that came out swapped (two second
#: moments nearly equal) or turned end for end (a near-symmetric shape) are found.
FRAME_ROTATIONS = _frame_rotations()


def _rotation_name(r: np.ndarray) -> str:
    axes = "xyz"
    return "axes " + " ".join(("-" if r[i, j] < 0 else "+") + axes[j] for i in range(3) for j in range(3) if r[i, j])


#: Names of :data:`FRAME_ROTATIONS`: the object frames' identity, the turns by 180 degrees about
#: the x, y and z axes of the object frame, then each other rotation by where it sends x, y and z.
ROTATION_NAMES = ("frames", "turned about x", "turned about y", "turned about z") + tuple(
    _rotation_name(r) for r in FRAME_ROTATIONS[4:])
TURN_NAMES = ROTATION_NAMES


def nearest_frame_rotation(rotation: np.ndarray) -> int:
    """The index into :data:`FRAME_ROTATIONS` of the rotation nearest ``rotation`` (3, 3): the one
    turned least from it (largest trace of Fᵀ R, which is 1 + 2 cos of the angle between them); ties
    go to the earlier one.

    >>> nearest_frame_rotation(FRAME_ROTATIONS[5] @ axis_rotation(np.array([0.0, 0.0, 1.0]), 20.0))
    5
    """
    return int(np.argmax(np.einsum("kij,ij->k", np.asarray(FRAME_ROTATIONS), np.asarray(rotation, float))))
#: A coating this many times farther from the population's mean shape than the median
#: instance (RMS over the points, after a rigid alignment by its correspondence) is tried
#: in the other turns.
TURNED_FACTOR = 2.0
#: Template samples (triangle centroids) and target samples of the start's similarity registration.
SCREEN_SAMPLES = 1500
TARGET_SAMPLES = 6000
#: Steps of the registration from every rotation (on every ``SCREEN_STRIDE``-th sample of both), and
#: of the nearest ``FINALISTS`` in full.
SCREEN_STRIDE = 3
SCREEN_ITERATIONS = 6
REGISTRATION_ITERATIONS = 30
FINALISTS = 3
#: Point-to-plane steps that finish a finalist's registration where its point pairs are still
#: turning it by more than ``CREEP_DEG`` a step (kept where they bring the surfaces nearer): point
#: pairs creep along a round surface (a patella turns a few degrees in 30 steps), the
#: point-to-plane steps slide along it to where it fits.
PLANE_ITERATIONS = 10
CREEP_DEG = 0.05
#: The input coordinates' registration ending within this angle (degrees) of the best turn's is in
#: the same basin: the turn's pose is taken, which does not depend on the scanner pose.
SAME_BASIN_DEG = 10.0


@dataclass(frozen=True)
class FramesStart:
    """How the template was put onto an instance without landmarks.

    Attributes
    ----------
    turn : str
        ``"input coordinates"`` or one of :data:`TURN_NAMES`.
    distances_mm : dict turn -> mm
        Mean distance of the rigidly screened template from the surface, per candidate.
    scale : float
        The template's scale to the instance's size.
    """

    turn: str
    distances_mm: dict
    scale: float

    def to_dict(self) -> dict:
        return {"turn": self.turn, "distances_mm": {k: float(v) for k, v in self.distances_mm.items()},
                "scale": float(self.scale)}


def template_start(template_points: np.ndarray, target: ObjectVolume, *, template_frame: ObjectFrame | None = None,
                   turns: tuple[int, ...] | None = None, distance_map: DistanceMap | None = None,
                   template_faces: np.ndarray | None = None) -> tuple[np.ndarray, FramesStart]:
    """The template's points put onto ``target`` (its object frame, mm) without landmarks.

    A dense similarity registration of the two surfaces (:func:`surface_similarity`: rotation,
    translation and one scale, symmetric closest points weighted by surface area) from each of
    the rotations in ``turns`` (the 24 rotations of :data:`FRAME_ROTATIONS`, which map the object
    frame's axes onto themselves, so that a frame whose axes came out swapped or turned end for
    end is still found) and from the pose the input coordinates give; the nearest few are
    finished by :meth:`SurfacePairs.register` (point-to-plane steps where they still creep);
    the pose nearest the surface wins, the input coordinates' unless another fits
    ``WORLD_POSE_TOLERANCE`` times closer or theirs ends within ``SAME_BASIN_DEG`` of it (then
    the turn's: the same pose for the inputs in any scanner pose).

    Parameters
    ----------
    template_points : (N, 3) mm
        The template in its instance's object frame.
    target : ObjectVolume
    template_frame : ObjectFrame, optional
        The template instance's frame: with the target's, the pose the input coordinates
        give, preferred to a turn that fits less than ``WORLD_POSE_TOLERANCE`` times closer.
    turns : indices into :data:`FRAME_ROTATIONS` to try (default: all 24).
    template_faces : (F, 3), optional
        The template's triangles: the surface is sampled by area (its points are denser where
        it is curved, eq. 1, which would pull the centre and the scale there); without them
        every point weighs the same.

    Returns
    -------
    (start points (N, 3) mm, FramesStart)
    """
    pts = np.asarray(template_points, float)
    turns = tuple(range(len(FRAME_ROTATIONS))) if turns is None else tuple(turns)
    dm = distance_map if distance_map is not None else DistanceMap.from_object_volume(target)
    src, src_w = area_samples(pts, template_faces, SCREEN_SAMPLES)
    tgt, tgt_w, tgt_normals = area_samples(dm.surface_vertices, dm.surface_faces, TARGET_SAMPLES, normals=True)
    centre_s, centre_t = src_w @ src / src_w.sum(), tgt_w @ tgt / tgt_w.sum()
    scale = float(np.sqrt(tgt_w.sum() / max(src_w.sum(), 1e-12))) if template_faces is not None else float(
        np.sqrt(((tgt - centre_t) ** 2).sum(axis=1) @ tgt_w / tgt_w.sum())
        / max(np.sqrt(((src - centre_s) ** 2).sum(axis=1).mean()), 1e-12))
    candidates = [(ROTATION_NAMES[k], Pose(FRAME_ROTATIONS[k], centre_t - scale * FRAME_ROTATIONS[k] @ centre_s, scale))
                  for k in turns]
    world = None
    if template_frame is not None:
        rot = input_rotation(pts, template_frame, target.frame)
        world = ("input coordinates", Pose(rot, centre_t - scale * rot @ centre_s, scale))
        candidates.insert(0, world)
    surface = SurfacePairs(src, src_w, tgt, tgt_w, tgt_normals)
    coarse = SurfacePairs(src[::SCREEN_STRIDE], src_w[::SCREEN_STRIDE], tgt[::SCREEN_STRIDE], tgt_w[::SCREEN_STRIDE])
    screened = [(name, *coarse.register(pose, SCREEN_ITERATIONS)) for name, pose in candidates]
    # the nearest few screened poses registered in full; the input coordinates' pose always
    finalists = sorted(range(len(screened)), key=lambda i: (screened[i][2], i))[:FINALISTS]
    if world is not None and 0 not in finalists:
        finalists.append(0)
    final = {i: surface.register(screened[i][1], REGISTRATION_ITERATIONS, plane_iterations=PLANE_ITERATIONS)
             for i in finalists}
    distances = {screened[i][0]: final[i][1] if i in final else screened[i][2] for i in range(len(screened))}
    best = min((i for i in final if i or world is None), key=lambda i: (final[i][1], i), default=0)
    # the input coordinates choose the basin, not the pose within it: where their registration ends
    # within SAME_BASIN_DEG of the best turn's, the turn's pose is kept (the same for any input pose)
    if world is not None and best != 0 and final[0][1] <= WORLD_POSE_TOLERANCE * final[best][1] and turn_angle_deg(
            final[0][0].rotation, final[best][0].rotation) > SAME_BASIN_DEG:
        best = 0
    pose = final[best][0]
    return pose.apply(pts), FramesStart(screened[best][0], distances, float(pose.scale))


def input_rotation(points: np.ndarray, template_frame: ObjectFrame, target_frame: ObjectFrame) -> np.ndarray:
    """(3, 3) the rotation the input coordinates give from the template's object frame to an
    instance's: the template's points (its object mm) put into world mm and seen in the instance's
    frame (the rigid fit of the two). For an instance mirrored into the template's side the template
    is mirrored left to right first (world x, in RAS and LPS), as a right bone is a left one's."""
    pts = np.asarray(points, float)
    world = template_frame.to_world(pts)
    if template_frame.mirrored != target_frame.mirrored:
        world = world * np.array([-1.0, 1.0, 1.0])
    _s, rot, _t = procrustes_fit(pts[None], target_frame.to_object(world), scale=False)
    return rot[0]


def area_samples(vertices: np.ndarray, faces: np.ndarray | None, count: int, *, normals: bool = False):
    """About ``count`` samples of a surface and the area (mm²) each stands for.

    Every k-th triangle's centroid, weighted by k times its area (mm², the frame of
    ``vertices``), so that sums over the samples approximate integrals over the surface;
    without ``faces``, every k-th vertex with weight 1. With ``normals``, also the
    triangles' unit normals (as the faces turn).
    """
    v = np.asarray(vertices, float)
    if faces is None or not len(faces):
        if normals:
            raise ValueError("normals need the faces")
        step = max(1, len(v) // max(count, 1))
        return v[::step], np.ones(len(v[::step]))
    f = np.asarray(faces)
    step = max(1, len(f) // max(count, 1))
    f = f[::step]
    cross = face_normals(v, f, normalize=False)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    if normals:
        return face_centroids(v, f), area * step, cross / np.maximum(2.0 * area, 1e-300)[:, None]
    return face_centroids(v, f), area * step


class SurfacePairs:
    """The template's and the target's area samples (and the target's unit normals, for the
    point-to-plane steps), for :meth:`register`."""

    def __init__(self, src, src_w, tgt, tgt_w, tgt_normals=None):
        self.src, self.tgt, self.tgt_normals = src, tgt, tgt_normals
        self.w = np.concatenate([src_w / src_w.sum(), tgt_w / tgt_w.sum()])
        self.tgt_tree = cKDTree(tgt)

    def register(self, pose: Pose, iterations: int, *, plane_iterations: int = 0) -> tuple[Pose, float]:
        """:func:`surface_similarity` from ``pose``; where its last step still turned the pose by more
        than :data:`CREEP_DEG`, ``plane_iterations`` steps of :func:`plane_similarity` after it, kept
        where they end nearer: the pose and its symmetric mean distance (mm)."""
        pose, before = _point_steps(self.src, self.tgt, self.w, self.tgt_tree, pose, iterations)
        d = symmetric_distance(self.src, self.tgt, self.w, self.tgt_tree, pose)
        if (plane_iterations and self.tgt_normals is not None
                and turn_angle_deg(pose.rotation, before.rotation) > CREEP_DEG):
            plane = plane_similarity(self.src, self.tgt, self.tgt_normals, self.w, self.tgt_tree, pose, plane_iterations)
            if plane[1] < d:
                return plane
        return pose, d


def surface_similarity(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray, tgt_tree: cKDTree, pose: Pose,
                       iterations: int) -> tuple[Pose, float]:
    """A dense similarity registration of two sampled surfaces (symmetric ICP with scale).

    Each step pairs every source sample with its nearest target sample and every target
    sample with its nearest moved source sample, and solves the area-weighted least-squares
    similarity of all pairs (Umeyama 1991); both directions, so that a part of either surface
    the other lacks cannot hold the pose alone.

    Parameters
    ----------
    src, tgt : (M, 3), (K, 3) mm
        Surface samples (:func:`area_samples`), the source in its own frame, the target in its.
    weights : (M + K,)
        The samples' areas, each surface's summing to 1.
    tgt_tree : the target samples' k-d tree.
    pose : the start (source -> target).

    Returns
    -------
    (Pose, mean distance mm)
        The registered pose and the area-weighted mean of both directions' nearest distances.

    References
    ----------
    Besl & McKay (1992), A method for registration of 3-D shapes; Umeyama (1991),
    Least-squares estimation of transformation parameters between two point patterns.
    """
    pose, _before = _point_steps(src, tgt, weights, tgt_tree, pose, iterations)
    return pose, symmetric_distance(src, tgt, weights, tgt_tree, pose)


def _point_steps(src, tgt, weights, tgt_tree, pose: Pose, iterations: int) -> tuple[Pose, Pose]:
    """:func:`surface_similarity`'s steps: the pose after them and the pose before the last one."""
    before = pose
    for _ in range(iterations):
        x = pose.apply(src)
        _d, j = tgt_tree.query(x)
        _d, i = cKDTree(x).query(tgt)
        before, pose = pose, weighted_pose(np.vstack([src, src[i]]), np.vstack([tgt[j], tgt]), weights, scale=True)
    return pose, before


def symmetric_distance(src: np.ndarray, tgt: np.ndarray, weights: np.ndarray, tgt_tree: cKDTree, pose: Pose) -> float:
    """The area-weighted mean of both directions' nearest distances (mm) of the posed source
    samples and the target's (``weights`` as :func:`surface_similarity`'s)."""
    x = pose.apply(src)
    d_fwd = tgt_tree.query(x)[0]
    d_bwd = cKDTree(x).query(tgt)[0]
    n = len(src)
    return float(0.5 * (weights[:n] @ d_fwd + weights[n:] @ d_bwd))


#: Relative damping of the point-to-plane normal equations (a round surface leaves its turn about
#: its own axis free).
PLANE_DAMPING = 1e-6


def plane_similarity(src: np.ndarray, tgt: np.ndarray, tgt_normals: np.ndarray, weights: np.ndarray,
                     tgt_tree: cKDTree, pose: Pose, iterations: int) -> tuple[Pose, float]:
    """:func:`surface_similarity` with point-to-plane steps (Chen & Medioni 1992).

    The same pairs in both directions, each measured along the target sample's normal n: the
    step is the small similarity (scale e^σ, turn ω, shift δ about the pairs' centre c) that
    solves the area-weighted least squares of n · (y + σ (y - c) + ω × (y - c) + δ - q) (the
    pose linearised; the turn then applied exactly, Rodrigues), so a surface slides along the
    other as far as its shape allows in one step, where point pairs pull it a little each step.

    Returns
    -------
    (Pose, mean distance mm)
        As :func:`surface_similarity`.

    References
    ----------
    Chen & Medioni (1992), Object modelling by registration of multiple range images;
    Low (2004), Linear least-squares optimization for point-to-plane ICP surface registration.
    """
    for _ in range(iterations):
        y = pose.apply(src)
        _d, j = tgt_tree.query(y)
        _d, i = cKDTree(y).query(tgt)
        p, q, n = np.vstack([y, y[i]]), np.vstack([tgt[j], tgt]), np.vstack([tgt_normals[j], tgt_normals])
        c = weights @ p / weights.sum()
        pc = p - c
        a = np.hstack([np.einsum("ij,ij->i", n, pc)[:, None], np.cross(pc, n), n])
        b = -np.einsum("ij,ij->i", n, p - q)
        normal = a.T @ (a * weights[:, None])
        normal += PLANE_DAMPING * np.trace(normal) / 7.0 * np.eye(7)
        sigma, omega, delta = np.split(np.linalg.solve(normal, a.T @ (weights * b)), [1, 4])
        angle = float(np.linalg.norm(omega))
        turn = axis_rotation(omega, np.degrees(angle)) if angle > 0 else np.eye(3)
        grow = float(np.exp(sigma[0]))
        pose = Pose(turn @ pose.rotation, grow * turn @ (pose.translation - c) + c + delta, pose.scale * grow)
    return pose, symmetric_distance(src, tgt, weights, tgt_tree, pose)


def coat_from_template_pose(template: Mesh, target: ObjectVolume, *, coating: CoatingParams,
                            template_frame: ObjectFrame | None = None, turns: tuple[int, ...] | None = None,
                            name: str = "") -> tuple[CoatingResult, FramesStart]:
    """:func:`template_start`, the carry, then the coating's registration, projection and relaxation
    from it (paper 4.2; ``fit.start`` = object frames).

    The carry (not in the paper): a similarity pose leaves a part that is relatively longer or
    wider on this instance than on the template's (a femur's shaft, a vertebra's processes) met by
    a neighbouring part of the template, and the registration that follows pulls along the
    normals only, so nothing moves it back along the surface. A smooth displacement at the wide
    Gaussian widths ``coating.carry_sigmas_mm`` (mm), its pulls in full (along the surface too;
    :func:`~ssm_addon.coating.registration.register_to_surface` with ``normal_only=False``),
    deforms space about as a Gaussian-process registration with a squared-exponential kernel of
    that width does (Lüthi et al. 2018), before the normal-only widths refine it. With landmarks
    the warp of eq. (2) pins the parts instead and no carry runs.
    """
    dm = DistanceMap.from_object_volume(target)
    start, how = template_start(template.vertices, target, template_frame=template_frame, turns=turns,
                                distance_map=dm, template_faces=template.faces)
    if coating.carry_sigmas_mm and coating.registration_iterations > 0:
        start = register_to_surface(start, template.faces, dm, sigmas_mm=tuple(coating.carry_sigmas_mm),
                                    iterations=coating.registration_iterations, normal_only=False)
    result = coat_from_start(template, target, start=start, params=coating, distance_map=dm,
                             start_label=CoatingStart.OBJECT_FRAMES, name=name)
    return result, how


def _coat_job(args):
    template, target, coating, frame, turns, name = args
    return coat_from_template_pose(template, target, coating=coating, template_frame=frame, turns=turns, name=name)


def coat_without_landmarks(template: Mesh, targets: dict, *, coating: CoatingParams,
                           template_frame: ObjectFrame | None = None, turns: dict | None = None, jobs: int = 1,
                           executor=None, cancelled: CancelledFn = None) -> dict:
    """:func:`coat_from_template_pose` for every target (name -> ObjectVolume) on ``executor``;
    ``turns``: per name, the rotations to try (default all 24). Returns name -> (CoatingResult, FramesStart)."""
    names = list(targets)
    args = [(template, targets[n], coating, template_frame, (turns or {}).get(n), n) for n in names]
    with executor_or_local(executor, jobs, len(args)) as pool:
        found = pool.map(_coat_job, args, labels=names, verb="coated", cancelled=cancelled)
    return dict(zip(names, found))


def far_from_population(points: dict, reference: str) -> dict:
    """Each coating's RMS distance (mm) from the mean of the *others*, every coating moved rigidly
    onto ``reference``'s by its correspondence (:func:`~ssm_addon.correspondence.rounds.aligned_to`)."""
    names = list(points)
    stack = aligned_to(np.stack([points[n] for n in names]), points[reference])
    total = stack.sum(axis=0)
    out = {}
    for k, n in enumerate(names):
        others = (total - stack[k]) / max(len(names) - 1, 1)
        out[n] = float(np.sqrt(((stack[k] - others) ** 2).sum(axis=1).mean()))
    return out


def population_turns(coated: dict, reference: str, retry) -> tuple[dict, dict, dict]:
    """Coatings the population disagrees with, tried in the other turns.

    An instance whose coating is more than :data:`TURNED_FACTOR` times the median farther from
    the mean of the others (:func:`far_from_population`) is coated again from the other turns
    (``retry(names) -> {name: (CoatingResult, FramesStart)}``); the new coating is kept when it
    lies nearer the others' mean.

    Returns
    -------
    (coated, changed, unresolved)
        ``coated``: name -> (CoatingResult, FramesStart), with the kept retries;
        ``changed``: name -> (RMS from the others before, after) for the instances turned;
        ``unresolved``: name -> (RMS from the others, the median) for those no turn brought nearer.
    """
    points = {n: c.points_object for n, (c, _h) in coated.items()}
    if len(points) < 3:
        return coated, {}, {}
    far = far_from_population(points, reference)
    median = float(np.median(list(far.values())))
    suspects = [n for n, d in far.items() if n != reference and d > TURNED_FACTOR * median]
    if not suspects:
        return coated, {}, {}
    again = retry(suspects)
    out, changed, unresolved = dict(coated), {}, {}
    for n in [n for n in suspects if n in again]:
        trial = dict(points)
        trial[n] = again[n][0].points_object
        d = far_from_population(trial, reference)[n]
        if d < far[n]:
            out[n] = again[n]
            changed[n] = (far[n], d)
        else:
            unresolved[n] = (far[n], median)
    return out, changed, unresolved



#: A coating is named ``twist`` when its correspondence is turned more than this (degrees) against
#: its own surface's fit to the mean shape, and more than :data:`TWIST_FACTOR` times the median
#: instance's turn.
TWIST_MIN_DEG = 5.0
TWIST_FACTOR = 3.0
TWIST_SAMPLES = 800
TWIST_ITERATIONS = 8


@dataclass(frozen=True)
class Twist:
    """How far a coating's correspondence is turned against its own surface (:func:`coating_twists`).

    Attributes
    ----------
    angle_deg : float
        The turn between the pose that puts the coating's points onto the mean shape's points (by
        correspondence) and the pose that puts its surface onto the mean shape's surface.
    axis : (3,) unit vector
        The turn's axis in the mean shape's frame (the template's object frame, paper 2).
    axis_name : str
        The axis in words: the mean shape's longest, middle or shortest principal axis, or oblique.
    """

    angle_deg: float
    axis: np.ndarray
    axis_name: str

    def to_dict(self) -> dict:
        return {"angle_deg": float(self.angle_deg), "axis": [float(x) for x in self.axis], "axis_name": self.axis_name}


def coating_poses(points: dict, faces: np.ndarray, reference: str) -> tuple[dict, np.ndarray]:
    """Each coating put onto the population's mean shape twice: by its correspondence and by its surface.

    The mean shape is the coatings' mean, each moved rigidly onto ``reference``'s by its
    correspondence (:func:`~ssm_addon.correspondence.rounds.aligned_to`). A coating's points are
    put onto the mean's points by the similarity of least squares (Umeyama, by correspondence);
    its surface onto the mean's surface by symmetric point-to-plane ICP from that pose
    (:func:`_surface_to_surface`, which ignores which point is which). For a coating in
    correspondence the two poses differ only by what the shapes' differences make of them.

    Parameters
    ----------
    points : name -> (N, 3) mm
        The coatings, each in a frame of its own (its object frame, or the world), in
        correspondence.
    faces : (F, 3)
        The template's triangles.
    reference : str
        The instance the others are moved onto for the mean (the template instance).

    Returns
    -------
    (dict name -> (by points, by surface): :class:`~ssm_addon.fitting.fit.Pose` from the coating's
    frame to the mean's, the mean shape (N, 3) mm)
    """
    names = list(points)
    stack = aligned_to(np.stack([np.asarray(points[n], float) for n in names]), np.asarray(points[reference], float))
    mean = stack.mean(axis=0)
    tgt, tgt_w = area_samples(mean, faces, TWIST_SAMPLES)
    mean_mesh, mean_normals = MeshLocator(mean, faces), face_normals(mean, faces)
    out = {}
    for n in names:
        p = np.asarray(points[n], float)
        by_points = weighted_pose(p, mean, np.ones(len(p)), scale=True)
        src, src_w = area_samples(p, faces, TWIST_SAMPLES)
        w = np.concatenate([src_w / src_w.sum(), tgt_w / tgt_w.sum()])
        out[n] = (by_points, _surface_to_surface(src, MeshLocator(p, faces), face_normals(p, faces), tgt, mean_mesh,
                                                 mean_normals, w, by_points, TWIST_ITERATIONS))
    return out, mean


def twists_of(poses: dict, mean: np.ndarray) -> dict:
    """:class:`Twist` of each coating from :func:`coating_poses`' two poses: the turn between them,
    its axis named against the mean shape's principal axes."""
    centred = mean - mean.mean(axis=0)
    _u, _s, axes = np.linalg.svd(centred, full_matrices=False)  # rows: longest, middle, shortest
    out = {}
    for n, (by_points, by_surface) in poses.items():
        turn = by_surface.rotation @ by_points.rotation.T
        angle = turn_angle_deg(turn)
        axis = np.array([turn[2, 1] - turn[1, 2], turn[0, 2] - turn[2, 0], turn[1, 0] - turn[0, 1]])
        axis = axis / max(np.linalg.norm(axis), 1e-12)
        along = np.abs(axes @ axis)
        k = int(np.argmax(along))
        name = (("the mean shape's longest axis", "its middle axis", "its shortest axis")[k]
                if along[k] > 0.9 else "an oblique axis")
        out[n] = Twist(angle, axis, name)
    return out


def coating_twists(points: dict, faces: np.ndarray, reference: str) -> dict:
    """Each coating's turn against its own surface: where correspondence disagrees with shape.

    A coating can lie on its instance's surface and still hold its points in places turned
    about an axis against the others' (a bone near-symmetric about its long axis, coated without
    landmarks). Its surface then fits the mean shape's surface in one pose and its points fit the
    mean shape's points in another (:func:`coating_poses`); the turn between the two poses is the
    twist (:func:`twists_of`). The same for any frame of each coating (object or world).

    Returns
    -------
    dict name -> :class:`Twist`
    """
    return twists_of(*coating_poses(points, faces, reference))


def _surface_to_surface(src, src_mesh, src_normals, tgt, tgt_mesh, tgt_normals, weights, pose: Pose,
                        iterations: int) -> Pose:
    """Symmetric point-to-plane similarity ICP (Chen & Medioni 1992, linearised about the current
    pose) to the closest points *on the other surface* (exact, point to triangle), not to its
    samples: two meshes with the same triangles have samples in correspondence, and pairs between
    samples would hold the correspondence's pose. Point to plane, because a turn that slides a
    surface along itself is what it must find, and point-to-point steps creep there (a 12° turn of
    a spindle: 1.4° after 30 steps)."""
    for _ in range(iterations):
        x = pose.apply(src)
        c, _d, tri, _b = tgt_mesh.query(x, k=8)
        n_fwd = tgt_normals[tri]
        back, _d, tri_s, _b = src_mesh.query(pose.inverse(tgt), k=8)
        moved = pose.apply(back)
        n_bwd = src_normals[tri_s] @ pose.rotation.T
        a = np.vstack([x, moved])  # source points (moved) and where they should reach the plane of
        b = np.vstack([c, tgt])
        nrm = np.vstack([n_fwd, n_bwd])
        g = weights @ a / weights.sum()
        q = a - g
        rows = np.hstack([np.cross(q, nrm), nrm, (nrm * q).sum(axis=1, keepdims=True)])
        e = ((a - b) * nrm).sum(axis=1)
        sw = np.sqrt(weights)[:, None]
        step = np.linalg.lstsq(rows * sw, -e * sw[:, 0], rcond=None)[0]
        omega, shift, ds = step[:3], step[3:6], step[6]
        angle = float(np.linalg.norm(omega))
        r_inc = axis_rotation(omega, np.degrees(angle)) if angle > 1e-15 else np.eye(3)
        s_inc = 1.0 + ds
        pose = Pose(r_inc @ pose.rotation, s_inc * r_inc @ (pose.translation - g) + g + shift, s_inc * pose.scale)
    return pose


def twisted(twists: dict, *, min_deg: float = TWIST_MIN_DEG, factor: float = TWIST_FACTOR) -> tuple[dict, float]:
    """The coatings of :func:`coating_twists` turned more than ``min_deg`` and ``factor`` times the
    median instance's turn: (name -> Twist, the threshold in degrees)."""
    if len(twists) < 3:
        return {}, float("inf")
    limit = max(min_deg, factor * float(np.median([t.angle_deg for t in twists.values()])))
    return {n: t for n, t in twists.items() if t.angle_deg > limit}, limit
