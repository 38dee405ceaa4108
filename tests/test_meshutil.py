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
