"""Mesh utilities: topology counts, manifold checks, volume, normals, PLY round trips."""

from __future__ import annotations

import numpy as np
import pytest

from ssm_addon import meshutil as mu
from ssm_addon.base.errors import InputError
from ssm_addon.formats import meshes

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
CUBE_F = np.array([
    [0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
    [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7],
])


def grid_torus(n=12, m=8, R=3.0, r=1.0):
    """A torus as an n x m quad grid split into triangles (outward)."""
    u, v = np.meshgrid(np.arange(n) * 2 * np.pi / n, np.arange(m) * 2 * np.pi / m, indexing="ij")
    verts = np.stack([(R + r * np.cos(v)) * np.cos(u), (R + r * np.cos(v)) * np.sin(u), r * np.sin(v)], -1).reshape(-1, 3)
    idx = np.arange(n * m).reshape(n, m)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(b, -1, 1), np.roll(a, -1, 1)
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return verts, faces


def test_cube_has_18_edges_euler_2_genus_0_and_unit_volume():
    assert len(mu.edges(CUBE_F)) == 18
    assert mu.euler_characteristic(8, CUBE_F) == 2
    assert mu.genus(8, CUBE_F) == 0
    assert mu.signed_volume(CUBE_V, CUBE_F) == pytest.approx(1.0)
    assert mu.signed_volume(CUBE_V, CUBE_F[:, ::-1]) == pytest.approx(-1.0)
    assert mu.is_closed_manifold(CUBE_F).ok


def test_grid_torus_is_closed_manifold_of_genus_one():
    v, f = grid_torus()
    rep = mu.is_closed_manifold(f)
    assert rep.ok, rep.summary()
    assert mu.genus(len(v), f) == 1
    # volume of a torus 2 pi^2 R r^2, polygonal approximation slightly less
    assert 0.85 * 2 * np.pi**2 * 3 < mu.signed_volume(v, f) < 2 * np.pi**2 * 3


def test_genus_per_component_for_two_disjoint_shapes():
    v, f = grid_torus()
    f2 = np.concatenate([f, CUBE_F + len(v)])
    n, lab = mu.connected_components(f2, len(v) + 8)
    assert n == 2
    assert len(np.unique(lab[:len(v)])) == 1
    assert sorted(mu.genus(len(v) + 8, f2).tolist()) == [0, 1]


def test_open_mesh_reports_boundary_edges():
    rep = mu.is_closed_manifold(CUBE_F[1:])
    assert not rep.ok
    assert len(rep.boundary_edges) == 3


def test_flipped_face_reports_inconsistent_orientation():
    f = CUBE_F.copy()
    f[0] = f[0, ::-1]
    rep = mu.is_closed_manifold(f)
    assert not rep.ok
    assert len(rep.inconsistent_edges) == 3
    assert len(rep.boundary_edges) == 0


def test_three_faces_on_an_edge_are_non_manifold():
    f = np.concatenate([CUBE_F, [[0, 2, 6]]])
    rep = mu.is_closed_manifold(f)
    assert [0, 2] in rep.nonmanifold_edges.tolist()


def test_two_cubes_touching_at_a_vertex_are_a_non_manifold_vertex():
    f = np.concatenate([CUBE_F, CUBE_F + 7])  # vertex 7 of the first is vertex 0 of the second
    rep = mu.is_closed_manifold(f)
    assert rep.nonmanifold_vertices.tolist() == [7]
    assert len(rep.nonmanifold_edges) == 0 and len(rep.boundary_edges) == 0


def test_face_and_vertex_normals_point_outward_on_the_cube():
    fn = mu.face_normals(CUBE_V, CUBE_F)
    centres = CUBE_V[CUBE_F].mean(1) - 0.5
    assert np.all(np.einsum("ij,ij->i", fn, centres) > 0)
    vn = mu.vertex_normals(CUBE_V, CUBE_F)
    np.testing.assert_allclose(np.linalg.norm(vn, axis=1), 1.0)
    assert np.all(np.einsum("ij,ij->i", vn, CUBE_V - 0.5) > 0.5)


@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_keeps_vertices_faces_and_scalars(tmp_path, binary):
    v, f = grid_torus()
    c = np.linspace(0, 1, len(v))
    path = tmp_path / "t.ply"
    meshes.write_ply(path, v, f, vertex_scalars={"curvature": c}, binary=binary)
    v2, f2, s = meshes.read_ply(path)
    np.testing.assert_allclose(v2, v, atol=1e-5)
    np.testing.assert_array_equal(f2, f)
    np.testing.assert_allclose(s["curvature"], c, atol=1e-6)


def test_read_ply_rejects_a_non_ply_file(tmp_path):
    p = tmp_path / "x.ply"
    p.write_text("solid nothing\n")
    with pytest.raises(InputError, match="x.ply"):
        meshes.read_ply(p)


def _shells(*parts):
    """One mesh of several icospheres: (radius, centre, outward) each; faces reversed when inward."""
    from conftest import icosphere

    verts, faces = [], []
    for radius, centre, outward in parts:
        v, f = icosphere(radius, 3)
        faces.append((f if outward else f[:, ::-1]) + sum(len(x) for x in verts))
        verts.append(v + np.asarray(centre, float))
    return np.vstack(verts), np.vstack(faces)


def _solid_angle_winding(points, v, f):
    """The winding number by its definition: the triangles' signed solid angles over 4π (Van
    Oosterom and Strackee's formula), for comparison."""
    a, b, c = (v[f[:, k]][None] - points[:, None] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=2) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", a, c) * lb
           + np.einsum("pfi,pfi->pf", b, c) * la)
    return np.arctan2(det, den).sum(axis=1) / (2 * np.pi)


def test_winding_number_is_one_inside_zero_outside_and_changes_sign_with_the_orientation():
    v, f = _shells((10.0, (0, 0, 0), True))
    inside = np.array([[0.0, 0, 0], [9.0, 0, 0], [0, -5.0, 5.0]])
    outside = np.array([[11.0, 0, 0], [0, 40.0, 0], [-8.0, -8.0, 8.0]])
    assert mu.winding_numbers(inside, v, f).tolist() == [1, 1, 1]
    assert mu.winding_numbers(outside, v, f).tolist() == [0, 0, 0]
    assert mu.winding_numbers(inside, v, f[:, ::-1]).tolist() == [-1, -1, -1]
    # nested shells of both orientations, at random points and at the vertices of a voxel surface:
    # the count of the rays is the solid angles' sum
    nested_v, nested_f = _shells((20.0, (0, 0, 0), True), (6.0, (-8, 0, 0), False), (2.0, (-8, 0, 0), True),
                                 (5.0, (40, 0, 0), True))
    rng = np.random.default_rng(7)
    probe = rng.uniform((-25, -25, -25), (50, 25, 25), size=(300, 3))
    assert np.array_equal(mu.winding_numbers(probe, nested_v, nested_f),
                          np.round(_solid_angle_winding(probe, nested_v, nested_f)).astype(int))
    mask = np.zeros((9, 9, 9), bool)
    mask[1:8, 1:8, 1:8] = True
    mask[3:6, 3:6, 3:6] = False
    mask[4, 4, 4] = True  # a voxel in a cavity
    mv, mf = mu.marching_cubes(mask)
    at = np.vstack([mv + (0.11, 0.23, 0.07), mv - (0.11, 0.23, 0.07), np.argwhere(np.ones((9, 9, 9), bool)) + 0.01])
    assert np.array_equal(mu.winding_numbers(at, mv, mf), np.round(_solid_angle_winding(at, mv, mf)).astype(int))


def test_the_walls_of_internal_cavities_are_enclosed_a_second_part_and_an_island_in_a_cavity_are_not():
    # the object (r 20), two cavities in it (inward walls, as marching cubes writes holes), an island
    # inside the second cavity (outward), and a second part outside the first
    v, f = _shells((20.0, (0, 0, 0), True), (3.0, (8, 0, 0), False), (6.0, (-8, 0, 0), False),
                   (2.0, (-8, 0, 0), True), (5.0, (40, 0, 0), True))
    n = len(v) // 5
    enclosed = mu.enclosed_components(v, f)
    assert enclosed.reshape(5, n).all(axis=1).tolist() == [False, True, True, False, False]
    assert enclosed.reshape(5, n).any(axis=1).tolist() == [False, True, True, False, False]
    # the same whatever the orientation the tool wrote the file in
    assert np.array_equal(mu.enclosed_components(v, f[:, ::-1]), enclosed)
    kept, kept_faces, left_out = mu.outer_surface(v, f)
    assert left_out == {"components": 2, "vertices": 2 * n}
    assert np.array_equal(kept, v[~enclosed])
    assert np.array_equal(kept[kept_faces], v[f[~enclosed[f[:, 0]]]])  # the same triangles, re-indexed
    assert mu.connected_components(kept_faces, len(kept))[0] == 3
    # an open surface (a partial scan) encloses nothing: a closed part in its bowl stays
    cup_v, cup_f = _shells((20.0, (0, 0, 0), True))
    keep = cup_f[(cup_v[cup_f][:, :, 2] < 12.0).all(axis=1)]
    bowl_v = np.vstack([cup_v, _shells((3.0, (0, 0, 0), True))[0]])
    bowl_f = np.vstack([keep, _shells((3.0, (0, 0, 0), True))[1] + len(cup_v)])
    assert not mu.enclosed_components(bowl_v, bowl_f).any()
    # one closed surface has nothing enclosed and comes back as it was
    one, one_f, none = mu.outer_surface(*_shells((20.0, (0, 0, 0), True)))
    assert none == {"components": 0, "vertices": 0} and len(one) == n
