"""Sides: mirror-image instances (left and right bones) put into the template's side.

A study may mix left and right bones. A rotation cannot turn a left femur into a right one,
so a template coated onto a mirror image of its own instance's shape would map the front of
one onto the back of the other, and the model would read the difference of sides as shape.
Each such instance is mirrored into the template's side before it is coated
(:func:`ssm_addon.instances.volume.mirrored`: its object frame becomes left-handed, so its
coating is in the template's side in object mm and back in its own side in world mm), and
the model is of the template's side.

Which instances are mirror images is given (a project's per-instance ``side``) or found:

* by landmarks (:func:`landmark_side`): the template instance's landmarks map onto an
  instance's by a similarity far closer with a reflection than without (Umeyama 1991);
* by surfaces (:func:`surface_side`): the template's surface is registered onto the
  instance's and onto its mirror image by the start's similarity registration from every
  rotation of the frame's axes (:func:`ssm_addon.correspondence.frames.template_start`'s
  screening), and the mirror image fits far closer.

Both decide only when one side fits :data:`SIDE_FACTOR` times closer than the other; else the
instance is taken as the template's side, and the decision says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..fitting.fit import Pose, weighted_pose
from ..instances.volume import ObjectFrame, ObjectVolume, mirror_axis, mirrored_frame
from .frames import FRAME_ROTATIONS, SurfacePairs, area_samples, input_rotation

__all__ = ["SIDE_FACTOR", "SideDecision", "landmark_side", "subject_sides", "surface_side"]

#: One side is decided when it fits this many times closer than the other (the template's
#: similarity onto the landmarks, RMS mm; or onto the surface, mean mm); docs/history.md
#: ("Sides") has the ratios on real bones.
SIDE_FACTOR = 1.1
#: Landmarks needed to tell a side (a similarity of 3 points has no handedness).
LANDMARK_SIDE_MIN_POINTS = 4
#: The surface test's registration: steps from every rotation on every ``SIDE_SCREEN_STRIDE``-th
#: sample, and in full from the ``SIDE_FINALISTS`` nearest screened poses and the input pose (cheaper than the start's:
#: it needs the distances, not the pose).
SIDE_SCREEN_STRIDE = 4
SIDE_SCREEN_ITERATIONS = 5
SIDE_ITERATIONS = 12
SIDE_FINALISTS = 1
#: The nearest screened rotations of the decided side handed to the start (which then screens only these).
START_ROTATIONS = 3
#: Template samples (triangle centroids) and boundary voxels the surface test registers.
SIDE_SAMPLES = 800
SIDE_TARGET_SAMPLES = 3000


@dataclass(frozen=True)
class SideDecision:
    """Whether an instance is mirrored into the template's side, and why.

    Attributes
    ----------
    mirror : bool
        True: the instance is a mirror image of the template's side and is mirrored before
        it is coated.
    by : str
        ``"given"`` (the project's ``side``), ``"landmarks"``, ``"surface"``, ``"subject"``
        (in a joint project, the subject's other structures decided against this one's own
        fits: :func:`subject_sides`), or ``"undecided"`` (neither side fits :data:`SIDE_FACTOR`
        times closer: taken as the template's side).
    as_is_mm, mirrored_mm : float
        How closely the template fits the instance as it is and mirrored (landmarks: RMS mm
        of the similarity; surface: mean symmetric distance, mm); NaN when not measured.
    side : str
        The side given for the instance, or ``""``.
    rotations : tuple of int
        The surface test's nearest rotations of the frame's axes on the decided side (indices into
        :data:`~ssm_addon.correspondence.frames.FRAME_ROTATIONS`, nearest first): the start's
        candidates, which need not be screened again.
    """

    mirror: bool
    by: str
    as_is_mm: float = float("nan")
    mirrored_mm: float = float("nan")
    side: str = ""
    rotations: tuple = ()

    def to_dict(self) -> dict:
        out = {"mirrored": bool(self.mirror), "by": self.by}
        if self.rotations:
            out["rotations"] = [int(k) for k in self.rotations]
        if self.side:
            out["side"] = self.side
        if np.isfinite(self.as_is_mm):
            out["as_is_mm"] = float(self.as_is_mm)
            out["mirrored_mm"] = float(self.mirrored_mm)
        return out

    @classmethod
    def from_dict(cls, d: dict) -> SideDecision:
        """The decision :meth:`to_dict` wrote."""
        return cls(mirror=bool(d.get("mirrored", False)), by=str(d.get("by", "")),
                   as_is_mm=float(d.get("as_is_mm", float("nan"))), mirrored_mm=float(d.get("mirrored_mm", float("nan"))),
                   side=str(d.get("side", "")), rotations=tuple(int(k) for k in d.get("rotations", ())))

    def text(self) -> str:
        if self.by == "given":
            return f"side {self.side} given"
        if self.by == "subject":
            return (f"its subject's other structures' side (its own surface fits {self.as_is_mm:.2f} mm as is, "
                    f"{self.mirrored_mm:.2f} mm mirrored)")
        what = "landmarks fit" if self.by == "landmarks" else "surface fits"
        return f"its {what} {self.as_is_mm:.2f} mm as is, {self.mirrored_mm:.2f} mm mirrored"


def _decide(as_is: float, mirrored: float, by: str, rotations=((), ())) -> SideDecision:
    if mirrored * SIDE_FACTOR < as_is:
        return SideDecision(True, by, as_is, mirrored, rotations=tuple(rotations[1]))
    if as_is * SIDE_FACTOR < mirrored:
        return SideDecision(False, by, as_is, mirrored, rotations=tuple(rotations[0]))
    return SideDecision(False, "undecided", as_is, mirrored, rotations=tuple(rotations[0]))


def _evidence(d: SideDecision) -> float:
    """log(as is / mirrored) of a decision: > 0 where the mirror image fits closer; 0 where not measured."""
    if not (np.isfinite(d.as_is_mm) and np.isfinite(d.mirrored_mm)) or d.as_is_mm <= 0 or d.mirrored_mm <= 0:
        return 0.0
    return float(np.log(d.as_is_mm / d.mirrored_mm))


def subject_sides(decisions: dict, *, parity: dict | None = None) -> dict:
    """One side per subject of a joint project, from each structure's own decisions.

    A subject's structures are mirrored together or not at all: one mirrored alone would carry
    the subject's relative poses into another side. Each structure's decision (against its own
    template) is evidence, ``log(as is / mirrored)`` of its fits (landmarks' RMS or the surface's
    mean distance, so the landmarks' sharper ratios weigh more); the subject is a mirror image of
    the reference structure's template side when the sum over its structures favours the mirror
    image by :data:`SIDE_FACTOR` or more, the template's side when it favours that by as much, and
    undecided (taken as the template's side) between.

    Parameters
    ----------
    decisions : dict
        structure -> subject -> :class:`SideDecision` (that structure's, against its template).
    parity : dict, optional
        structure -> whether its template instance is a mirror image of the reference structure's
        template instance (default False: the structures share one template subject's side).

    Returns
    -------
    dict
        structure -> subject -> :class:`SideDecision`, ``mirror`` the same for every structure
        of a subject (each XOR its structure's ``parity``); ``by`` the structure's own where it
        agrees, ``"subject"`` where the subject's other structures decided it, ``"undecided"``.

    >>> a = SideDecision(True, "surface", 3.0, 2.0)
    >>> b = SideDecision(False, "undecided", 2.0, 2.1)
    >>> out = subject_sides({"femur": {"S2": a}, "tibia": {"S2": b}})
    >>> out["femur"]["S2"].mirror, out["tibia"]["S2"].mirror, out["tibia"]["S2"].by
    (True, True, 'subject')
    """
    parity = parity or {}
    subjects = sorted({s for per in decisions.values() for s in per})
    out = {name: {} for name in decisions}
    threshold = float(np.log(SIDE_FACTOR))
    for s in subjects:
        total = sum(-_evidence(per[s]) if parity.get(name, False) else _evidence(per[s])
                    for name, per in decisions.items() if s in per)
        mirror = total > threshold
        undecided = abs(total) <= threshold
        for name, per in decisions.items():
            if s not in per:
                continue
            own = per[s]
            this = mirror != bool(parity.get(name, False))
            if undecided:
                out[name][s] = SideDecision(this, "undecided", own.as_is_mm, own.mirrored_mm,
                                            rotations=own.rotations if not this else ())
            elif own.by != "undecided" and own.mirror == this:
                out[name][s] = own
            else:  # the subject's other structures decide; the own rotations are of the other side
                out[name][s] = SideDecision(this, "subject", own.as_is_mm, own.mirrored_mm,
                                            rotations=own.rotations if own.mirror == this else ())
    return out


def _similarity_rms(src: np.ndarray, tgt: np.ndarray, *, reflect: bool) -> float:
    """RMS (mm) of the least-squares similarity ``src`` -> ``tgt`` (Umeyama 1991), proper or with a
    reflection (the proper one of ``src`` mirrored: any reflection is a mirror and a rotation)."""
    src = src * np.array([-1.0, 1.0, 1.0]) if reflect else src
    pose = weighted_pose(src, tgt, np.ones(len(src)), scale=True)
    return float(np.sqrt(((pose.apply(src) - tgt) ** 2).sum(axis=1).mean()))


def landmark_side(template_landmarks: np.ndarray, landmarks: np.ndarray) -> SideDecision | None:
    """The side of an instance by its landmarks: the template instance's (``(L, 3)`` mm, any
    frame) mapped onto the instance's (``(L, 3)`` mm, the same names in the same order, any
    frame) by the closest similarity with and without a reflection.

    None when fewer than :data:`LANDMARK_SIDE_MIN_POINTS` landmarks are common or they lie in
    a plane (a reflection through that plane fits as well: only the surface can tell).

    >>> rng = np.random.default_rng(0)
    >>> a = rng.normal(size=(6, 3)) * 20
    >>> landmark_side(a, a * [-1, 1, 1] + 5).mirror, landmark_side(a, a + 5).mirror
    (True, False)
    """
    a, b = np.asarray(template_landmarks, float), np.asarray(landmarks, float)
    if len(a) < LANDMARK_SIDE_MIN_POINTS or len(a) != len(b):
        return None
    for p in (a, b):
        sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
        if sv[0] <= 0 or sv[2] < 0.05 * sv[0]:
            return None
    return _decide(_similarity_rms(a, b, reflect=False), _similarity_rms(a, b, reflect=True), "landmarks")


def _boundary_samples(volume: ObjectVolume, count: int) -> tuple[np.ndarray, np.ndarray]:
    """About ``count`` of the object's boundary voxels (object voxels with a background neighbour;
    object mm), each of weight 1."""
    mask = np.asarray(volume.mask, bool)
    edge = np.argwhere(mask & ~ndimage.binary_erosion(mask))
    pts = volume.voxel_to_object(edge[:: max(1, len(edge) // max(count, 1))])
    return pts, np.ones(len(pts))


def surface_side(template_points: np.ndarray, template_faces: np.ndarray, target: ObjectVolume, *,
                 template_frame: ObjectFrame | None = None) -> SideDecision:
    """The side of an instance by its surface.

    The template's surface (area samples of its triangles, object mm of its instance) is
    registered as a similarity onto the instance's boundary and onto its mirror image
    (:func:`ssm_addon.instances.volume.mirrored`) from each of the 24 rotations of the
    frame's axes (:data:`~ssm_addon.correspondence.frames.FRAME_ROTATIONS`), screened as
    :func:`~ssm_addon.correspondence.frames.template_start` screens, and from the pose the input
    coordinates give (``template_frame``: the template's instance's frame; for the mirror image,
    the template mirrored left to right, world x, as a right bone is a left one's); the nearest
    screened poses and the input pose of each side are registered in full. The side that fits
    :data:`SIDE_FACTOR` times closer (mean symmetric distance, mm) is decided.
    """
    pts = np.asarray(template_points, float)
    src, src_w = area_samples(pts, template_faces, SIDE_SAMPLES)
    tgt, tgt_w = _boundary_samples(target, SIDE_TARGET_SAMPLES)
    centre_s = src_w @ src / src_w.sum()
    scale = float(np.sqrt(((tgt - tgt.mean(axis=0)) ** 2).sum(axis=1).mean())
                  / max(np.sqrt(((src - centre_s) ** 2).sum(axis=1) @ src_w / src_w.sum()), 1e-12))
    flip = np.ones(3)
    flip[mirror_axis(target.frame)] = -1.0
    best, nearest = [], []
    for frame, t in ((target.frame, tgt), (mirrored_frame(target.frame), tgt * flip)):
        centre_t = t.mean(axis=0)
        poses = [Pose(r, centre_t - scale * r @ centre_s, scale) for r in FRAME_ROTATIONS]
        if template_frame is not None:
            rot = input_rotation(pts, template_frame, frame)
            poses.insert(0, Pose(rot, centre_t - scale * rot @ centre_s, scale))
        coarse = SurfacePairs(src[::SIDE_SCREEN_STRIDE], src_w[::SIDE_SCREEN_STRIDE], t[::SIDE_SCREEN_STRIDE],
                              tgt_w[::SIDE_SCREEN_STRIDE])
        screened = [coarse.register(p, SIDE_SCREEN_ITERATIONS) for p in poses]
        order = sorted(range(len(screened)), key=lambda i: (screened[i][1], i))
        finalists = sorted({*order[:SIDE_FINALISTS], *([0] if template_frame is not None else [])})
        first = 1 if template_frame is not None else 0  # the input pose is not a rotation of the axes
        nearest.append([i - first for i in order if i >= first][:START_ROTATIONS])
        full = SurfacePairs(src, src_w, t, tgt_w)
        best.append(min(full.register(screened[i][0], SIDE_ITERATIONS)[1] for i in finalists))
    return _decide(best[0], best[1], "surface", nearest)
