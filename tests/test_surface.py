"""Surface voxels, surface graph, normals and curvature (paper sections 3.1–3.2)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import ndimage

from ssm_addon.base.errors import InputError
from ssm_addon.instances import importing as INS
from ssm_addon.template import surface

# --------------------------------------------------------------------------- shapes


def sphere(radius: float, offset=(0.3, 0.17, 0.41)):
    """Voxel ball of ``radius`` voxels (centres inside), centre off the grid."""
    n = int(2 * radius + 8)
    centre = n / 2 + np.asarray(offset)
    g = np.indices((n, n, n), dtype=float)
    return ((g - centre[:, None, None, None]) ** 2).sum(0) <= radius * radius, centre


def cube(side: int = 30, margin: int = 4):
    mask = np.zeros((side + 2 * margin,) * 3, bool)
    mask[margin : margin + side, margin : margin + side, margin : margin + side] = True
    lo = margin - 0.5
    hi = margin + side - 0.5
    corners = np.array(list(itertools.product((lo, hi), repeat=3)))
    return mask, corners, (lo, hi)


def cylinder(radius: float, length: int = 70, offset=(0.23, 0.37)):
    """Solid cylinder along axis 0 with flat caps."""
    n = int(2 * radius + 8)
    centre = n / 2 + np.asarray(offset)
    g = np.indices((length + 8, n, n), dtype=float)
    mask = ((g[1] - centre[0]) ** 2 + (g[2] - centre[1]) ** 2 <= radius * radius) & (g[0] >= 4) & (g[0] < length + 4)
    return mask, centre


def saddle(radius: float, half: int = 28, thickness: int = 14):
    """Slab whose top is z = z0 + (x^2 - y^2) / (2 R), x, y centred on the array."""
    n = 2 * half + 1
    depth = thickness + 2 * int(np.ceil(half**2 / (2 * radius))) + 8
    g = np.indices((n, n, depth), dtype=float)
    x = g[0] - half
    y = g[1] - half
    z0 = depth / 2 + 0.31
    top = z0 + (x**2 - y**2) / (2 * radius)
    mask = (g[2] <= top) & (g[2] >= top - thickness)
    return mask, (half, half, z0)


def brute_surface(mask):
    """Object voxels with a background voxel among the 26 neighbours (outside = background)."""
    padded = np.pad(mask, 1)
    has_bg = np.zeros(mask.shape, bool)
    for off in itertools.product((-1, 0, 1), repeat=3):
        sl = tuple(slice(1 + o, 1 + o + s) for o, s in zip(off, mask.shape))
        has_bg |= ~padded[sl]
    return np.argwhere(mask & has_bg)


# --------------------------------------------------------------------------- voxels and graph


def test_surface_voxels_of_3x3x3_cube_are_the_26_outer_voxels():
    mask = np.zeros((5, 5, 5), bool)
    mask[1:4, 1:4, 1:4] = True
    vox = surface.surface_voxels(mask)
    assert vox.shape == (26, 3) and vox.dtype == np.int64
    assert not any((v == (2, 2, 2)).all() for v in vox)


def test_surface_voxels_are_exactly_those_with_a_background_26_neighbour():
    rng = np.random.default_rng(3)
    ball, _ = sphere(5.5)
    blob = ndimage.binary_opening(rng.random((14, 15, 13)) < 0.6)
    # the blob touches the array border: the outside counts as background
    for mask in (ball, blob):
        vox = surface.surface_voxels(mask)
        np.testing.assert_array_equal(vox, brute_surface(mask))
        assert np.all(np.diff(vox[:, 0] * 10**6 + vox[:, 1] * 10**3 + vox[:, 2]) > 0)  # lexicographic order


def test_full_array_has_its_border_as_surface_and_empty_mask_has_none():
    full = np.ones((4, 5, 6), bool)
    assert len(surface.surface_voxels(full)) == 4 * 5 * 6 - 2 * 3 * 4
    assert surface.surface_voxels(np.zeros((3, 3, 3), bool)).shape == (0, 3)


def test_surface_graph_is_symmetric_26_neighbour_with_manhattan_lengths():
    mask, _ = sphere(6.0)
    vox = surface.surface_voxels(mask)
    rng = np.random.default_rng(0)
    shuffled = vox[rng.permutation(len(vox))]  # order must not matter
    g = surface.surface_graph(shuffled)
    assert g.shape == (len(vox), len(vox))
    assert abs(g - g.T).max() == 0
    assert set(np.unique(g.data)) <= {1.0, 2.0, 3.0}
    diff = shuffled[:, None, :] - shuffled[None, :, :]
    cheb = np.abs(diff).max(-1)
    expected = np.where(cheb == 1, np.abs(diff).sum(-1), 0)
    np.testing.assert_array_equal(g.toarray(), expected)


def test_surface_graph_of_3x3x3_cube_shell():
    mask = np.zeros((5, 5, 5), bool)
    mask[1:4, 1:4, 1:4] = True
    g = surface.surface_graph(surface.surface_voxels(mask))
    # the centre is not a surface voxel: a corner of the shell reaches 3 voxels by face
    # steps (length 1) and 3 by edge steps (length 2); an edge voxel 10, a face centre 16
    assert sorted(np.diff(g.indptr)) == sorted([6] * 8 + [10] * 12 + [16] * 6)
    corner = np.flatnonzero(np.diff(g.indptr) == 6)
    assert np.all(np.asarray(g[corner].sum(1)).ravel() == 3 * 1 + 3 * 2)


# --------------------------------------------------------------------------- normals


@pytest.mark.parametrize("radius", [15, 20, 30])
def test_normals_of_sphere_are_radial_within_3_degrees(radius):
    mask, centre = sphere(radius)
    vox = surface.surface_voxels(mask)
    normals = surface.surface_normals(mask, vox, surface.DEFAULT_NORMAL_RADIUS_VOX)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-12)
    radial = vox - centre
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    angle = np.degrees(np.arccos(np.clip((normals * radial).sum(1), -1.0, 1.0)))
    assert angle.mean() < 3.0
    assert angle.max() < 10.0


def test_ball_sums_by_runs_and_by_fft_equal_brute_force():
    rng = np.random.default_rng(5)
    mask = ndimage.binary_opening(rng.random((16, 14, 15)) < 0.6)  # touches the border
    vox = surface.surface_voxels(mask)
    radius = 3.5
    offs = np.array([o for o in itertools.product(range(-3, 4), repeat=3) if np.dot(o, o) <= radius**2])
    pos = vox[:, None, :] + offs[None]
    inside = np.all((pos >= 0) & (pos < mask.shape), axis=2)
    hit = np.zeros(inside.shape, bool)
    hit[inside] = mask[tuple(pos[inside].T)]
    count = hit.sum(1)
    moment = (hit[:, :, None] * offs[None]).sum(1)
    for method in ("runs", "fft"):
        c, mo = surface.ball_sums(mask, vox, radius, method=method)
        np.testing.assert_allclose(c, count, atol=1e-3)
        np.testing.assert_allclose(mo, moment, atol=1e-3)


def test_normals_of_cube_faces_are_axis_aligned_and_outward():
    mask, _, (lo, hi) = cube(20)
    vox = surface.surface_voxels(mask)
    normals = surface.surface_normals(mask, vox, 4)
    mid = (lo + hi) / 2
    on_face = np.abs(vox - mid) <= (hi - lo) / 2 - 5  # away from edges in two axes
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        sel = on_face[:, others].all(1)
        expected = np.sign(vox[sel, axis] - mid)
        np.testing.assert_allclose(normals[sel, axis], expected, atol=1e-9)


def test_surface_points_lie_on_the_sphere_within_a_fraction_of_a_voxel():
    mask, centre = sphere(20)
    vox = surface.surface_voxels(mask)
    points, _ = surface.surface_points(mask, vox, 5)
    dist_vox = np.linalg.norm(vox - centre, axis=1) - 20
    dist_pts = np.linalg.norm(points - centre, axis=1) - 20
    # voxel centres scatter over about a voxel; the sub-voxel points much less
    assert np.std(dist_pts) < 0.3 * np.std(dist_vox)
    assert abs(np.median(dist_pts)) < 0.4  # about r^2 / (4 R) = 0.31 inside (see module docstring)


# --------------------------------------------------------------------------- curvature


@pytest.mark.parametrize("radius", [15, 20, 30])
def test_curvature_of_sphere_is_sqrt2_over_r(radius):
    mask, _ = sphere(radius)
    geo = surface.surface_geometry(mask)  # default radii: normal 5, patch 7 voxels
    truth = np.sqrt(2.0) / radius
    ratio = geo.c / truth
    assert abs(np.median(ratio) - 1.0) < 0.05
    assert np.mean(np.abs(ratio - 1.0) < 0.2) >= 0.8
    assert np.all(geo.k1 >= geo.k2)
    assert abs(np.median(geo.k1) * radius - 1.0) < 0.05 and abs(np.median(geo.k2) * radius - 1.0) < 0.05


def test_paper_form_at_voxel_centres_has_median_near_truth_but_wide_spread():
    """The paper's fit (z = a x^2 + 2 b x y + c y^2 through the voxel centre) is right on
    the median but noisy on a staircase surface; the quadric on sub-voxel points is not."""
    radius = 20
    mask, _ = sphere(radius)
    vox = surface.surface_voxels(mask)
    normals = surface.surface_normals(mask, vox, 5)
    truth = np.sqrt(2.0) / radius
    paper = surface.surface_curvature(mask, vox, normals, 7, form="paper", points=vox).c / truth
    quadric = surface.surface_curvature(mask, vox, normals, 7, form="quadric", normal_radius_vox=5).c / truth
    assert abs(np.median(paper) - 1.0) < 0.15
    p10, p90 = np.percentile(paper, [10, 90])
    q10, q90 = np.percentile(quadric, [10, 90])
    assert p90 - p10 > 5 * (q90 - q10)
    assert q90 - q10 < 0.15


def test_curvature_of_cube_is_largest_at_corners_and_near_zero_on_faces():
    mask, corners, (lo, hi) = cube(30)
    geo = surface.surface_geometry(mask)
    d_corner = np.linalg.norm(geo.voxels[:, None, :] - corners[None], axis=2).min(1)
    mid = (lo + hi) / 2
    centre_dist = np.sort(np.abs(geo.voxels - mid), axis=1)  # per voxel: two in-face offsets, then the normal one
    face_centre = centre_dist[:, 1] <= 4
    assert np.median(geo.c[face_centre]) < 0.02
    assert d_corner[np.argmax(geo.c)] < 3.0
    near_corner = d_corner < 3.0
    assert geo.c[near_corner].min() > np.percentile(geo.c[~near_corner], 95)
    # edges (away from corners) are curved in one direction only: k1 > 0, k2 ~ 0
    edge = (centre_dist[:, 1] > (hi - lo) / 2 - 1.5) & (centre_dist[:, 0] < 4)
    assert np.median(geo.k1[edge]) > 5 * abs(np.median(geo.k2[edge]))


@pytest.mark.parametrize("radius", [12, 20])
def test_curvature_of_cylinder_mantle_is_one_over_r_and_zero(radius):
    mask, centre = cylinder(radius)
    geo = surface.surface_geometry(mask)
    mantle = (geo.voxels[:, 0] > 4 + 15) & (geo.voxels[:, 0] < mask.shape[0] - 4 - 15)
    assert abs(np.median(geo.k1[mantle]) * radius - 1.0) < 0.1
    assert abs(np.median(geo.k2[mantle]) * radius) < 0.1


def test_curvature_of_saddle_is_plus_and_minus_one_over_r():
    radius = 20.0
    mask, (cx, cy, _) = saddle(radius)
    geo = surface.surface_geometry(mask)
    x = geo.voxels[:, 0] - cx
    y = geo.voxels[:, 1] - cy
    top = geo.normals[:, 2] > 0.5
    sel = top & (np.abs(x) <= 6) & (np.abs(y) <= 6)
    # principal curvatures of the graph z = (x^2 - y^2) / (2 R) with the normal up
    fx, fy, fxx, fyy = x / radius, -y / radius, 1.0 / radius, -1.0 / radius
    w = 1 + fx**2 + fy**2
    gauss = fxx * fyy / w**2
    mean = ((1 + fy**2) * fxx + (1 + fx**2) * fyy) / (2 * w**1.5)
    disc = np.sqrt(np.maximum(mean**2 - gauss, 0))
    k1_true = -(mean - disc)  # convex (bending away from the normal) is positive
    k2_true = -(mean + disc)
    assert abs(np.median(geo.k1[sel] / k1_true[sel]) - 1.0) < 0.1
    assert abs(np.median(geo.k2[sel] / k2_true[sel]) - 1.0) < 0.1
    assert np.mean(geo.k1[sel] > 0) > 0.95 and np.mean(geo.k2[sel] < 0) > 0.95


def test_curvature_at_inner_equator_of_torus_is_plus_and_minus_one_over_r():
    """A saddle whose normal sections are circles: the inner equator of a torus with
    tube radius r and hole radius r has k1 = +1/r (around the tube), k2 = -1/r."""
    r = 20.0
    ring = 2 * r
    xs = np.arange(r - 8, r + 22) + 0.27
    ys = np.arange(-22, 23) + 0.13
    zs = np.arange(-22, 23) + 0.41
    gx, gy, gz = np.meshgrid(xs, ys, zs, indexing="ij")
    mask = (np.hypot(gx, gy) - ring) ** 2 + gz**2 <= r * r  # a piece of the torus around (r, 0, 0)
    geo = surface.surface_geometry(mask)
    pos = np.stack([xs[geo.voxels[:, 0]], ys[geo.voxels[:, 1]], zs[geo.voxels[:, 2]]], axis=1)
    sel = np.linalg.norm(pos - (r, 0, 0), axis=1) <= 4
    assert sel.sum() > 30
    assert abs(np.median(geo.k1[sel]) * r - 1.0) < 0.1
    assert abs(np.median(geo.k2[sel]) * r + 1.0) < 0.1


@pytest.mark.parametrize("thickness", [3, 6, 10])
def test_flat_faces_of_thin_plates_have_zero_curvature(thickness):
    """The far side of a plate thinner than the patch diameter must not bend the fit."""
    mask = np.zeros((50, 50, 30), bool)
    mask[5:45, 5:45, 12 : 12 + thickness] = True
    geo = surface.surface_geometry(mask)
    face = (np.abs(geo.voxels[:, 0] - 25) < 8) & (np.abs(geo.voxels[:, 1] - 25) < 8)
    assert np.all(np.abs(np.abs(geo.normals[face, 2]) - 1) < 1e-9)
    assert np.abs(geo.c[face]).max() < 1e-6


def _brute_force_fit(points, normals, vox, i, radius, form):
    """The coordinate transformation method for one voxel with np.linalg.lstsq."""
    near = np.linalg.norm(vox - vox[i], axis=1) <= radius
    # the far side of a thin structure (opposite dominant normal direction) is left out
    axis = np.argmax(np.abs(normals), axis=1)
    sign = np.sign(normals[np.arange(len(normals)), axis])
    near &= ~((axis == axis[i]) & (sign != sign[i]))
    d = points[near] - points[i]
    n = normals[i]
    t1 = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    x, y, z = d @ t1, d @ t2, d @ n
    cols = [x * x, 2 * x * y, y * y] + ([x, y, np.ones_like(x)] if form == "quadric" else [])
    coef = np.linalg.lstsq(np.stack(cols, 1), z, rcond=None)[0]
    a, b, c = coef[:3]
    hess = 2 * np.array([[a, b], [b, c]])
    if form == "quadric":
        g = np.array(coef[3:5])
        first = np.eye(2) + np.outer(g, g)
        hess = np.linalg.solve(first, hess / np.sqrt(1 + g @ g))
    ev = np.sort(np.linalg.eigvals(hess).real)
    return -ev[0], -ev[1]


@pytest.mark.parametrize("form", ["paper", "quadric"])
def test_vectorised_fit_equals_per_voxel_least_squares(form):
    g = np.indices((30, 26, 22), dtype=float)
    mask = ((g[0] - 15.2) / 11) ** 2 + ((g[1] - 13.1) / 9) ** 2 + ((g[2] - 11.3) / 4) ** 2 <= 1
    vox = surface.surface_voxels(mask)
    points, normals = surface.surface_points(mask, vox, 4)
    curv = surface.surface_curvature(mask, vox, normals, 5, form=form, points=points, block=1, bias_correction=False)
    for i in np.random.default_rng(1).choice(len(vox), 25, replace=False):
        k1, k2 = _brute_force_fit(points, normals, vox, i, 5, form)
        np.testing.assert_allclose([curv.k1[i], curv.k2[i]], [k1, k2], rtol=1e-6, atol=1e-9)


def test_surface_geometry_is_deterministic_and_consistent():
    mask, _ = sphere(12)
    a = surface.surface_geometry(mask, normal_radius_vox=4, patch_radius_vox=6)
    b = surface.surface_geometry(mask, normal_radius_vox=4, patch_radius_vox=6)
    for field in ("voxels", "normals", "k1", "k2", "c", "points"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    np.testing.assert_array_equal(a.voxels, surface.surface_voxels(mask))
    np.testing.assert_allclose(a.c, np.hypot(a.k1, a.k2))
    assert (a.graph != b.graph).nnz == 0


def test_bad_inputs_raise_input_error_naming_the_problem():
    mask, _ = sphere(6)
    vox = surface.surface_voxels(mask)
    normals = surface.surface_normals(mask, vox, 3)
    with pytest.raises(InputError, match="3D"):
        surface.surface_voxels(np.ones((4, 4), bool))
    with pytest.raises(InputError, match="form"):
        surface.surface_curvature(mask, vox, normals, 5, form="cubic")
    with pytest.raises(InputError, match="patch radius"):
        surface.surface_curvature(mask, vox, normals, 0.5)
    with pytest.raises(InputError, match="normal radius"):
        surface.surface_normals(mask, vox, 0)
    with pytest.raises(InputError, match="normals"):
        surface.surface_curvature(mask, vox, normals[:-1], 5)
    with pytest.raises(InputError, match="empty"):
        surface.surface_geometry(np.zeros((5, 5, 5), bool))


# --------------------------------------------------------------------------- real data


def test_normals_point_out_of_a_real_vertebra(verse_dir):
    from conftest import VERSE_FILE, VERSE_LABELS


    ov = INS.load_object(VERSE_FILE, label=VERSE_LABELS["L1"], spacing_mm=1.0)
    geo = surface.surface_geometry(ov.mask, normal_radius_vox=5, patch_radius_vox=7)
    assert len(geo.voxels) > 5000
    outside = np.rint(geo.voxels + 2 * geo.normals).astype(int)
    inside = np.rint(geo.voxels - 2 * geo.normals).astype(int)
    pad = np.pad(ov.mask, 3)
    assert np.mean(~pad[tuple((outside + 3).T)]) > 0.9
    assert np.mean(pad[tuple((inside + 3).T)]) > 0.8
    assert np.all(np.isfinite(geo.c))
    # a vertebra has thin processes and sharp rims: curvature spans an order of magnitude
    assert np.percentile(geo.c, 95) > 3 * np.percentile(geo.c, 5)
