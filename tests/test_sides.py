"""Sides (correspondence/sides.py, pipeline/sides.py): mirror-image instances put into the template's
side before they are coated, by a given side or found by landmarks or surface, and written back in
their own side."""

from __future__ import annotations

import numpy as np
import pytest

from ssm_addon.base.errors import InputError
from ssm_addon.base.params import TemplateParams
from ssm_addon.correspondence.sides import SIDE_FACTOR, landmark_side, surface_side
from ssm_addon.instances.volume import ObjectFrame, ObjectVolume, mirror_axis, mirrored, mirrored_frame
from ssm_addon.pipeline.project import project_text, read_project
from ssm_addon.template.template import build_template


def _chiral(turn: np.ndarray | None = None) -> ObjectVolume:
    """An ellipsoid (radii 30, 18, 12 mm) with two knobs off its axes, 1 mm voxels: no mirror symmetry.
    ``turn``: a rotation of its frame (the same voxels, another world pose)."""
    g = np.mgrid[-38:39, -26:27, -20:21].astype(float)
    mask = (g[0] / 30) ** 2 + (g[1] / 18) ** 2 + (g[2] / 12) ** 2 <= 1
    mask |= (g[0] - 18) ** 2 + (g[1] - 12) ** 2 + (g[2] - 6) ** 2 <= 49
    mask |= (g[0] + 12) ** 2 + (g[1] - 14) ** 2 + (g[2] + 5) ** 2 <= 25
    frame = ObjectFrame(np.array([10.0, -20.0, 5.0]), np.eye(3) if turn is None else turn)
    return ObjectVolume(mask, 1.0, np.array([-38.0, -26.0, -20.0]), frame, "chiral")


@pytest.fixture(scope="module")
def chiral_template():
    ov = _chiral()
    return ov, build_template(ov, TemplateParams())


def test_a_mirrored_volume_is_the_same_world_points_in_a_left_handed_frame():
    ov = _chiral()
    mv = mirrored(ov)
    assert mv.frame.mirrored and not ov.frame.mirrored and np.linalg.det(mv.frame.axes_world) == pytest.approx(-1)
    a = ov.frame.to_world(ov.voxel_to_object(np.argwhere(ov.mask)))
    b = mv.frame.to_world(mv.voxel_to_object(np.argwhere(mv.mask)))
    assert np.array_equal(np.unique(np.round(a, 6), axis=0), np.unique(np.round(b, 6), axis=0))
    # object coordinates: the mirror image along the axis nearest the world's x (left-right)
    k = mirror_axis(ov.frame)
    pa, pb = ov.voxel_to_object(np.argwhere(ov.mask)), mv.voxel_to_object(np.argwhere(mv.mask))
    flip = np.ones(3)
    flip[k] = -1
    assert np.array_equal(np.unique(np.round(pa * flip, 6), axis=0), np.unique(np.round(pb, 6), axis=0))
    back = mirrored(mv)  # mirroring twice gives the volume back
    assert np.array_equal(back.mask, ov.mask) and np.allclose(back.origin_object, ov.origin_object)
    assert np.allclose(back.frame.axes_world, ov.frame.axes_world)
    assert np.allclose(mirrored_frame(mirrored_frame(ov.frame)).axes_world, ov.frame.axes_world)


def test_landmarks_tell_a_mirror_image_from_a_turned_copy():
    rng = np.random.default_rng(3)
    tpl = rng.normal(size=(8, 3)) * 25
    turn = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    same = landmark_side(tpl, tpl @ turn.T * 1.1 + [100, 0, 0] + rng.normal(scale=1.0, size=tpl.shape))
    other = landmark_side(tpl, (tpl * [-1, 1, 1]) @ turn.T + rng.normal(scale=1.0, size=tpl.shape))
    assert (same.mirror, same.by) == (False, "landmarks") and (other.mirror, other.by) == (True, "landmarks")
    assert other.mirrored_mm * SIDE_FACTOR < other.as_is_mm and same.as_is_mm < 1.5
    assert landmark_side(tpl[:3], tpl[:3]) is None  # fewer than 4
    flat = tpl.copy()
    flat[:, 2] = 0.0  # in a plane: a reflection through it fits as well, only the surface can tell
    assert landmark_side(flat, flat) is None


def test_the_surface_tells_a_mirror_image_from_a_turned_copy_and_leaves_a_symmetric_shape_undecided(chiral_template):
    ov, template = chiral_template
    turn = np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])  # another world pose: the frame turned
    same = surface_side(template.points_object, template.faces, _chiral(turn))
    other = surface_side(template.points_object, template.faces, mirrored(_chiral(turn)))
    assert (same.mirror, same.by) == (False, "surface"), same
    assert (other.mirror, other.by) == (True, "surface"), other
    assert other.as_is_mm > 1.3 * other.mirrored_mm and other.mirrored_mm < 1.0  # boundary voxel centres: ~0.5 mm in
    g = np.mgrid[-32:33, -20:21, -14:15].astype(float)  # an ellipsoid is its own mirror image
    egg = ObjectVolume((g[0] / 30) ** 2 + (g[1] / 18) ** 2 + (g[2] / 12) ** 2 <= 1, 1.0,
                       np.array([-32.0, -20.0, -14.0]), ObjectFrame(np.zeros(3), np.eye(3)), "egg")
    egg_template = build_template(egg, TemplateParams())
    found = surface_side(egg_template.points_object, egg_template.faces, mirrored(egg))
    assert (found.mirror, found.by) == (False, "undecided"), found


def _project(tmp_path, sides: dict, extra: str = "") -> object:
    from foreign_data import slicer_ply

    g = np.linspace(0, 2 * np.pi, 9)
    lines = [extra]
    for name, side in sides.items():
        v = np.array([[np.cos(a) * 10, np.sin(a) * 10, z] for z in (0.0, 20.0) for a in g[:-1]])
        faces = np.array([[0, 1, 9]])
        path = slicer_ply(tmp_path / f"{name}.ply", v, faces)
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{path.name}"'] + (
            [f"side = {side!r}".replace("'", '"')] if side is not None else []) + [""]
    p = tmp_path / "p.toml"
    p.write_text("\n".join(lines))
    return p


def test_a_project_gives_sides_and_mirrors_the_other_side(tmp_path):
    p = _project(tmp_path, {"a": "left", "b": "Right", "c": "L", "d": None})
    pr = read_project(p)
    by = {i.name: (i.side, i.mirror) for i in pr.instances}
    assert by == {"a": ("left", False), "b": ("right", True), "c": ("left", False), "d": (None, None)}
    assert 'side = "right"' in project_text(pr, tmp_path)  # written back as read
    given = read_project(_project(tmp_path, {"a": "left", "b": None, "c": None}, '[correspondence]\nsides = "given"\n'))
    assert [i.mirror for i in given.instances] == [False, False, False]  # no detection: the template's side


def test_bad_sides_are_named(tmp_path):
    with pytest.raises(InputError, match=r"instance 'b': side must be \"left\" or \"right\", got 'up'"):
        read_project(_project(tmp_path, {"a": "left", "b": "up", "c": None}))
    with pytest.raises(InputError, match=r"instance 'b' gives side = 'right' but the template instance 'a' gives none"):
        read_project(_project(tmp_path, {"a": None, "b": "right", "c": None}))
