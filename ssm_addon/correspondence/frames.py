"""Correspondence without landmarks: the template put onto each instance by its object frame
(paper 2) and the turns of its principal axes, then coated (paper 4.2); turns the population
disagrees with found and corrected.

Without landmarks nothing but the shapes anchors the correspondence. The object frames
(centre of mass, second-moment axes) align the template with an instance roughly (paper fig.
8, left), but a near-symmetric shape's axes may come out turned end for end, and a turn of
the template about an axis is then a correspondence that maps the front of one instance onto
the back of another. So each instance's start is the template in the pose that fits its
surface best: the frames' identity or one of the three proper turns of the axes
(:data:`~ssm_addon.correspondence.rounds.AXIS_TURNS`), each refined by a few rigid ICP steps
(:func:`~ssm_addon.fitting.fit.rigid_screen`), the pose of the input coordinates preferred
unless a turn fits :data:`~ssm_addon.correspondence.rounds.WORLD_POSE_TOLERANCE` times closer,
and the template scaled to the instance's size. After every instance is coated, an instance
whose coating lies far from the population's mean shape (by its correspondence, rigidly) is
coated again from the other turns and the turn nearest the others' mean is kept
(:func:`population_turns`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.compute import executor_or_local
from ..base.params import CoatingParams
from ..base.progress import CancelledFn
from ..coating.coating import CoatingResult, CoatingStart, coat_from_start
from ..coating.distance_map import DistanceMap
from ..fitting.fit import Pose, Target, rigid_screen
from ..instances.volume import ObjectFrame, ObjectVolume
from ..meshutil import Mesh
from ..model.pca import procrustes_fit
from .rounds import AXIS_TURNS, WORLD_POSE_TOLERANCE, aligned_to

__all__ = ["TURN_NAMES", "TURNED_FACTOR", "FramesStart", "coat_from_template_pose", "coat_without_landmarks",
           "far_from_population", "population_turns", "template_start"]

#: Names of :data:`~ssm_addon.correspondence.rounds.AXIS_TURNS` (the object frames' identity, then
#: the turns by 180 degrees about the x, y and z axes of the object frame).
TURN_NAMES = ("frames", "turned about x", "turned about y", "turned about z")
#: A coating this many times farther from the population's mean shape than the median
#: instance (RMS over the points, after a rigid alignment by its correspondence) is tried
#: in the other turns.
TURNED_FACTOR = 2.0
SCREEN_SAMPLES = 1500


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
                   turns: tuple[int, ...] = (0, 1, 2, 3), distance_map: DistanceMap | None = None
                   ) -> tuple[np.ndarray, FramesStart]:
    """The template's points put onto ``target`` (its object frame, mm) without landmarks.

    Parameters
    ----------
    template_points : (N, 3) mm
        The template in its instance's object frame.
    target : ObjectVolume
    template_frame : ObjectFrame, optional
        The template instance's frame: with the target's, the pose the input coordinates
        give, preferred to a turn that fits less than ``WORLD_POSE_TOLERANCE`` times closer.
    turns : indices into :data:`~ssm_addon.correspondence.rounds.AXIS_TURNS` to try.

    Returns
    -------
    (start points (N, 3) mm, FramesStart)
    """
    pts = np.asarray(template_points, float)
    dm = distance_map if distance_map is not None else DistanceMap.from_object_volume(target)
    surface = Target.from_mesh(dm.surface_vertices, dm.surface_faces, max_samples=4 * SCREEN_SAMPLES)
    centre_t = dm.surface_vertices.mean(axis=0)
    centre_s = pts.mean(axis=0)
    size = np.sqrt(((dm.surface_vertices - centre_t) ** 2).sum(axis=1).mean())
    scale = float(size / max(np.sqrt(((pts - centre_s) ** 2).sum(axis=1).mean()), 1e-12))
    scaled = centre_s + scale * (pts - centre_s)
    candidates = []
    for k in turns:
        rot = AXIS_TURNS[k]
        candidates.append((TURN_NAMES[k], Pose(rot, centre_t - rot @ centre_s)))
    world = None
    if template_frame is not None:
        there = target.frame.to_object(template_frame.to_world(pts))
        _s, rot, t = procrustes_fit(pts[None], there, scale=False)
        world = ("input coordinates", Pose(rot[0], centre_t - rot[0] @ centre_s))
        candidates.insert(0, world)
    screened = []
    for name, pose in candidates:
        refined, d = rigid_screen(scaled, surface, pose, partial=False, samples=SCREEN_SAMPLES)
        screened.append((name, refined, d))
    best = min(screened, key=lambda c: c[2])
    if world is not None and screened[0][2] <= WORLD_POSE_TOLERANCE * best[2]:
        best = screened[0]
    start = best[1].apply(scaled)
    return start, FramesStart(best[0], {name: d for name, _p, d in screened}, scale)


def coat_from_template_pose(template: Mesh, target: ObjectVolume, *, coating: CoatingParams,
                            template_frame: ObjectFrame | None = None, turns: tuple[int, ...] = (0, 1, 2, 3),
                            name: str = "") -> tuple[CoatingResult, FramesStart]:
    """:func:`template_start`, then the coating's registration, projection and relaxation from it
    (paper 4.2; ``fit.start`` = object frames)."""
    dm = DistanceMap.from_object_volume(target)
    start, how = template_start(template.vertices, target, template_frame=template_frame, turns=turns,
                                distance_map=dm)
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
    ``turns``: per name, the turns to try (default all four). Returns name -> (CoatingResult, FramesStart)."""
    names = list(targets)
    args = [(template, targets[n], coating, template_frame, (turns or {}).get(n, (0, 1, 2, 3)), n) for n in names]
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
