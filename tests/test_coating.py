"""Coating (paper section 4): landmark warp, sub-voxel projection, relaxation, batches."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from conftest import ellipsoid_landmarks
from scipy import ndimage

from ssm_addon import meshutil as mu
from ssm_addon.base import params as P
from ssm_addon.base.errors import InputError
from ssm_addon.coating import coating as C
from ssm_addon.coating import distance_map as DM
from ssm_addon.coating import registration as RG
from ssm_addon.coating import relaxation as RX
from ssm_addon.coating import warp as W
from ssm_addon.correspondence import proposal as PR
from ssm_addon.instances import importing as INS
from ssm_addon.instances.volume import ObjectFrame, ObjectVolume

try:  # the template stage (paper 3); the tests fall back to an icosphere until it exists
    from ssm_addon.template.template import TemplateParams, build_template
except ImportError:  # pragma: no cover - only while template.py is being written
    build_template = None


# ---------------------------------------------------------------------------------------
# synthetic shapes with known answers
# ---------------------------------------------------------------------------------------
def object_volume(inside, half_extent_mm, spacing_mm=1.0, source="synthetic") -> ObjectVolume:
    """An ObjectVolume (identity frame) of the implicit shape ``inside(points_object) -> bool``."""
    n = int(np.ceil(half_extent_mm / spacing_mm)) + 2
    ax = np.arange(-n, n + 1) * spacing_mm
    grid = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), axis=-1).reshape(-1, 3)
    mask = inside(grid).reshape(len(ax), len(ax), len(ax))
    return ObjectVolume(mask, spacing_mm, np.full(3, ax[0]), ObjectFrame(np.zeros(3), np.eye(3)), source)


def ellipsoid_volume(axes_mm, spacing_mm=1.0):
    axes_mm = np.asarray(axes_mm, float)
    return object_volume(lambda p: ((p / axes_mm) ** 2).sum(1) <= 1.0, axes_mm.max(), spacing_mm, f"ellipsoid {axes_mm}")


def icosphere(subdiv):
    t = (1 + 5**0.5) / 2
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
         [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6],
         [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10],
         [8, 6, 7], [9, 8, 1]])  # fmt: skip
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdiv):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        mid = v[ue].mean(1)
        mid /= np.linalg.norm(mid, axis=1, keepdims=True)
        m = inv.reshape(3, -1).T + len(v)
        v = np.vstack([v, mid])
        a, b, c = f.T
        ab, bc, ca = m.T
        f = np.vstack([np.c_[a, ab, ca], np.c_[b, bc, ab], np.c_[c, ca, bc], np.c_[ab, bc, ca]])
    return v, f


class _Mesh:
    def __init__(self, points, faces):
        self.points_object = points
        self.faces = faces


def make_template(ov: ObjectVolume, axes_mm=None):
    """The template of an instance: build_template (paper 3) when available."""
    if build_template is not None:
        return build_template(ov, TemplateParams())
    v, f = icosphere(subdivisions=3)  # 642 vertices
    dm = DM.DistanceMap.from_object_volume(ov)
    return _Mesh(dm.project(v * np.asarray(axes_mm, float), 3), f)


def displacement(points, amplitude_mm=2.0, wavelength_mm=40.0, seed=0):
    """A smooth random displacement field u (mm): three sine waves per axis."""
    rng = np.random.default_rng(seed)
    u = np.zeros_like(points)
    for axis in range(3):
        for _ in range(3):
            k = rng.normal(size=3)
            k *= 2 * np.pi / wavelength_mm / np.linalg.norm(k)
            u[:, axis] += amplitude_mm / 3 * np.sin(points @ k + rng.uniform(0, 2 * np.pi))
    return u


def inverse_displacement(points, **kw):
    """q with q + u(q) = p (fixed point; |grad u| < 1)."""
    q = np.array(points, float)
    for _ in range(60):
        q = points - displacement(q, **kw)
    return q


# ---------------------------------------------------------------------------------------
# 4.1 landmark warp
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("kernel", W.KERNELS)
def test_warp_hits_every_landmark(kernel):
    rng = np.random.default_rng(1)
    src = rng.uniform(-40, 40, (15, 3))
    dst = src + rng.normal(0, 5, (15, 3))
    tps = W.landmark_warp(src, dst, kernel=kernel)
    assert np.abs(tps(src) - dst).max() < 1e-6


@pytest.mark.parametrize("kernel", W.KERNELS)
def test_warp_reproduces_affine_map_exactly(kernel):
    rng = np.random.default_rng(2)
    src = rng.uniform(-30, 30, (12, 3))
    a = np.eye(3) + rng.normal(0, 0.3, (3, 3))
    b = rng.normal(0, 20, 3)
    tps = W.landmark_warp(src, src @ a.T + b, kernel=kernel)
    pts = rng.uniform(-60, 60, (500, 3))
    assert np.abs(tps(pts) - (pts @ a.T + b)).max() < 1e-6
    assert np.abs(tps.weights).max() < 1e-9


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.eye(3), "at least 4"),
        (np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0], [5, 3, 0]], float), "coplanar"),
        (np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]], float), "collinear"),
        (np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [10, 0, 0]], float), "same position"),
    ],
)
def test_warp_rejects_degenerate_landmarks(points, message):
    with pytest.raises(InputError, match=message):
        W.landmark_warp(points, points + 1.0)


def test_warp_rejects_mismatched_landmark_counts():
    with pytest.raises(InputError, match="landmarks"):
        W.landmark_warp(np.zeros((5, 3)), np.zeros((4, 3)))


# ---------------------------------------------------------------------------------------
# 4.2 distance map
# ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", [(2, 3, 4), (5, 7, 9), (31, 2, 40)])
@pytest.mark.parametrize("spacing", [1.0, 0.5, 0.3, 1.7])
def test_gradient_written_in_place_equals_numpy_gradient_bit_for_bit(shape, spacing):
    f = np.random.default_rng(7).normal(scale=10.0, size=shape)
    out = np.full((3, *shape), np.nan)
    assert DM.gradient_into(f, spacing, out) is out
    for mine, numpys in zip(out, np.gradient(f, spacing)):
        assert np.array_equal(mine, numpys)


def test_distance_map_fields_are_the_distance_and_its_numpy_gradient():
    g = np.mgrid[-9:10, -8:9, -7:8]
    ov = ObjectVolume((g[0] ** 2 / 49 + g[1] ** 2 / 25 + g[2] ** 2 / 16) <= 1, 0.8, np.array([-7.2, -6.4, -5.6]),
                      ObjectFrame(np.zeros(3), np.eye(3)))
    dm = DM.DistanceMap.from_object_volume(ov)
    fields = dm._fields_flat.reshape(4, *ov.mask.shape)
    assert np.shares_memory(dm.sdf_mm, dm._fields_flat) and np.array_equal(fields[0], dm.sdf_mm)
    for mine, numpys in zip(fields[1:], np.gradient(np.array(dm.sdf_mm), 0.8)):
        assert np.array_equal(mine, numpys)
    dm.smooth_normals(np.zeros((1, 3)), 2.0)
    smoothed = dm._smooth_cache[2.0].reshape(4, *ov.mask.shape)
    sm = ndimage.gaussian_filter(np.array(dm.sdf_mm), 2.0 / 0.8, mode="nearest")
    assert np.array_equal(smoothed[0], sm)
    for mine, numpys in zip(smoothed[1:], np.gradient(sm, 0.8)):
        assert np.array_equal(mine, numpys)


def _trilinear_per_point(dm, point):
    """Signed distance and gradient at one object point (mm) by the trilinear formula written
    out: the cell's corners lerped along z, then y, then x; outside the grid, the clamped
    point's value plus the distance out, its unit gradient plus the unit offset."""
    fields = dm._fields_flat.reshape(4, *dm.sdf_mm.shape)
    shape = np.array(dm.sdf_mm.shape)
    vox = (point - dm.origin_object) / dm.spacing_mm
    clamped = np.minimum(np.maximum(vox, 0.0), shape - 1.0)
    base = np.minimum(clamped.astype(np.int64), shape - 2)
    t = clamped - base
    x, y, z = base
    vals = np.empty(4)
    for f in range(4):
        c = fields[f, x:x + 2, y:y + 2, z:z + 2]
        cz = c[:, :, 0] + t[2] * (c[:, :, 1] - c[:, :, 0])
        cy = cz[:, 0] + t[1] * (cz[:, 1] - cz[:, 0])
        vals[f] = cy[0] + t[0] * (cy[1] - cy[0])
    d, g = vals[0], vals[1:]
    off = (vox - clamped) * dm.spacing_mm
    if np.any(off != 0.0):
        r = np.sqrt(np.add.reduce(off * off))  # the norms summed as over rows
        d, g = d + r, g / max(np.sqrt(np.add.reduce(g * g)), 1e-12) + off / r
    return d, g


def test_distance_map_sampling_is_the_trilinear_formula_at_every_point():
    g = np.mgrid[-9:10, -8:9, -7:8]
    ov = ObjectVolume((g[0] ** 2 / 49 + g[1] ** 2 / 25 + g[2] ** 2 / 16) <= 1, 0.8, np.array([-7.2, -6.4, -5.6]),
                      ObjectFrame(np.zeros(3), np.eye(3)))
    dm = DM.DistanceMap.from_object_volume(ov)
    rng = np.random.default_rng(11)
    inside = rng.uniform([-7.2, -6.4, -5.6], [7.2, 6.4, 5.6], size=(300, 3))
    outside = rng.uniform(-12.0, 12.0, size=(300, 3))
    on_nodes = np.array([[-7.2, -6.4, -5.6], [7.2, 6.4, 5.6], [0.0, 0.0, 0.0]])  # t = 0 and the last cell's t = 1
    for pts in (inside, outside, on_nodes):
        d, grad = dm.sample(pts)
        for i, point in enumerate(pts):
            want_d, want_g = _trilinear_per_point(dm, point)
            assert d[i] == want_d and np.array_equal(grad[i], want_g)
    # a field linear in x, y, z is interpolated exactly: the sampled value is the plane's
    plane = DM.DistanceMap.__new__(DM.DistanceMap)
    plane.__dict__.update(dm.__dict__)
    nodes = np.stack(np.meshgrid(*[np.arange(n) * 0.8 + o for n, o in zip(dm.sdf_mm.shape, dm.origin_object)],
                                 indexing="ij"), axis=0)
    flat = np.concatenate([(nodes * np.array([0.5, -1.5, 2.0])[:, None, None, None]).sum(0)[None],
                           np.broadcast_to(np.array([0.5, -1.5, 2.0])[:, None, None, None], nodes.shape)]).reshape(4, -1)
    plane._fields_flat = np.ascontiguousarray(flat)
    d, grad = plane.sample(inside)
    assert np.allclose(d, inside @ np.array([0.5, -1.5, 2.0]), atol=1e-12)
    assert np.allclose(grad, [0.5, -1.5, 2.0], atol=1e-15)


def _ellipsoid_volume(shift=0.0, store=""):
    g = np.mgrid[-9:10, -8:9, -7:8]
    mask = ((g[0] - shift) ** 2 / 49 + g[1] ** 2 / 25 + g[2] ** 2 / 16) <= 1
    return ObjectVolume(mask, 0.8, np.array([-7.2, -6.4, -5.6]), ObjectFrame(np.zeros(3), np.eye(3)),
                        distance_map_store=str(store))


def _same_map(a, b):
    assert np.array_equal(a._fields_flat, b._fields_flat) and np.array_equal(a.sdf_mm, b.sdf_mm)
    assert np.array_equal(a.surface_vertices, b.surface_vertices) and np.array_equal(a.surface_faces, b.surface_faces)
    pts = np.random.default_rng(3).uniform(-8, 8, size=(200, 3))
    for x, y in zip(a.sample(pts), b.sample(pts)):
        assert np.array_equal(x, y)
    assert np.array_equal(a.surface_distance(pts), b.surface_distance(pts))
    assert np.array_equal(a.smooth_normals(pts, 2.0), b.smooth_normals(pts, 2.0))


def test_a_stored_distance_map_is_read_back_as_the_same_arrays(tmp_path, monkeypatch):
    built = []
    real_build = DM.DistanceMap._build.__func__
    monkeypatch.setattr(DM.DistanceMap, "_build", classmethod(lambda cls, ov, band: built.append(1) or
                                                            real_build(cls, ov, band)))
    plain = DM.DistanceMap.from_object_volume(_ellipsoid_volume())
    first = DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path))
    assert len(built) == 2 and len(list(tmp_path.iterdir())) == 1
    again = DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path))
    assert len(built) == 2  # read, not built
    _same_map(plain, first)
    _same_map(plain, again)
    # another mask, another grid or another band: another map
    DM.DistanceMap.from_object_volume(_ellipsoid_volume(shift=1.0, store=tmp_path))
    DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path), band_vox=1.5)
    assert len(built) == 4 and len(list(tmp_path.iterdir())) == 3


def test_a_distance_map_store_that_is_absent_full_or_damaged_changes_only_the_time(tmp_path, monkeypatch):
    plain = DM.DistanceMap.from_object_volume(_ellipsoid_volume())
    # a folder this machine does not have (a Dask worker elsewhere): built, nothing written
    _same_map(plain, DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path / "elsewhere")))
    assert not (tmp_path / "elsewhere").exists()
    # a full store: built, not kept
    monkeypatch.setattr(DM, "STORE_BUDGET_BYTES", plain._fields_flat.nbytes // 2)
    _same_map(plain, DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path)))
    assert not any(tmp_path.iterdir())
    monkeypatch.undo()
    # a damaged file (cut short, or another array): built again and the same
    DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path))
    (kept,) = tmp_path.glob("*.npy")
    whole = kept.read_bytes()
    for damaged in (whole[: len(whole) // 2], whole[:200], b""):
        kept.write_bytes(damaged)
        _same_map(plain, DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path)))
    with open(kept, "wb") as f:  # a map of another grid under this name
        for a in (np.zeros((4, 7)), plain.surface_vertices, plain.surface_faces):
            np.save(f, a)
    _same_map(plain, DM.DistanceMap.from_object_volume(_ellipsoid_volume(store=tmp_path)))


def test_registration_does_not_leave_exact_ties_to_the_k_d_tree(monkeypatch):
    # a mesh on a 2 mm lattice registered to a surface sampled on a 1 mm lattice: 968 of the
    # 2,054 surface points are exactly as near two vertices as one; the first step's pull must
    # not depend on which of them the k-d tree's traversal meets first
    fine, coarse = ellipsoid_volume([14.0, 10.0, 8.0], 1.0), ellipsoid_volume([14.0, 10.0, 8.0], 2.0)
    dm, cm = DM.DistanceMap.from_object_volume(fine), DM.DistanceMap.from_object_volume(coarse)
    args = (cm.surface_vertices, cm.surface_faces, dm)
    balanced = RG.register_to_surface(*args, sigmas_mm=(8.0, 4.0), iterations=3)

    class OtherTree(RG.cKDTree):  # another tree over the same points: another traversal order
        def __init__(self, data, leafsize=16, **_kw):
            super().__init__(data[::-1], leafsize=3, balanced_tree=False, compact_nodes=False)
            self.flip = len(data) - 1

        def query(self, x, k=1, **kw):
            d, i = super().query(x, k=k, **kw)
            return d, np.where(i < self.n, self.flip - i, i)

    monkeypatch.setattr(RG, "cKDTree", OtherTree)
    assert np.array_equal(RG.register_to_surface(*args, sigmas_mm=(8.0, 4.0), iterations=3), balanced)


def _ellipsoid_with_rod(rod_mm, radius_mm=3.0, axes_mm=(20.0, 12.0, 10.0)):
    """An ellipsoid with a round process along +x, ``rod_mm`` beyond its tip (identity frame, 1 mm)."""
    axes = np.asarray(axes_mm)

    def inside(p):
        rod = (np.hypot(p[:, 1], p[:, 2]) <= radius_mm) & (p[:, 0] >= 0) & (p[:, 0] <= axes[0] + rod_mm)
        return (((p / axes) ** 2).sum(1) <= 1.0) | rod

    return object_volume(inside, axes.max() + rod_mm + 2, 1.0, f"ellipsoid with a {rod_mm} mm rod")


@pytest.mark.skipif(build_template is None, reason="needs the template stage")
def test_the_reach_extends_the_coating_into_a_process_longer_than_the_templates():
    # the template's process is 4 mm long, the instance's 12 mm: the registration's pull
    # along the normals leaves the coating's tip 4.9 mm short of the instance's; the reach
    # (far parts of the object pull in full) brings it to within the 3 mm the input-surface check allows
    template = build_template(_ellipsoid_with_rod(4.0), TemplateParams())
    target = _ellipsoid_with_rod(12.0)
    dm = DM.DistanceMap.from_object_volume(target)
    samples, _normals = dm.surface_samples(1)

    def coated(reach_mm):
        result = C.coat_from_start(template, target, params=P.CoatingParams(reach_mm=reach_mm), distance_map=dm)
        return mu.MeshLocator(result.points_object, template.faces).query(samples, k=12)[1], result.fit

    short, _fit = coated(0.0)
    reached, fit = coated(2.5)
    assert short.max() > 4.0 and (short > 3.0).sum() > 40
    assert reached.max() < 3.5 and (reached > 3.0).sum() <= 5
    assert fit.folded_after == 0 and fit.mean_distance_mm < 0.3


@pytest.mark.skipif(build_template is None, reason="needs the template stage")
def test_the_reach_follows_a_fin_a_voxel_thick_and_leaves_the_templates_own_instance_alone():
    # a fin one voxel thick standing 5 mm out of the ellipsoid, which the template lacks:
    # without the reach its edge lies beyond the 3 mm the input-surface check allows; the
    # reach pulls the mesh into it (a part of the object, if a thin one) without folding it
    # and moves only vertices near it; on the template's own instance, where nothing lies
    # far from the mesh, the points are those without the reach
    axes = np.array([20.0, 12.0, 10.0])

    def ellipsoid(p):
        return ((p / axes) ** 2).sum(1) <= 1.0

    def with_fin(p):
        return ellipsoid(p) | ((np.abs(p[:, 2]) <= 0.5) & (np.abs(p[:, 0]) <= 6) & (p[:, 1] >= 0) & (p[:, 1] <= 17))

    own = object_volume(ellipsoid, 22, 1.0)
    template = build_template(own, TemplateParams())
    dm = DM.DistanceMap.from_object_volume(own)
    off, on = (C.coat_from_start(template, own, params=P.CoatingParams(reach_mm=r), distance_map=dm)
               for r in (0.0, 2.5))
    assert np.array_equal(off.points_object, on.points_object)

    fin = object_volume(with_fin, 22, 1.0)
    dm = DM.DistanceMap.from_object_volume(fin)
    samples, _normals = dm.surface_samples(1)
    off, on = (C.coat_from_start(template, fin, params=P.CoatingParams(reach_mm=r), distance_map=dm)
               for r in (0.0, 2.5))
    far_off, far_on = (mu.MeshLocator(c.points_object, template.faces).query(samples, k=12)[1] for c in (off, on))
    assert far_off.max() > 3.0 and far_on.max() < 3.0
    assert on.fit.folded_after == 0 and on.fit.mean_distance_mm < 0.1
    moved = np.linalg.norm(on.points_object - off.points_object, axis=1) > 1e-9
    assert moved.any()
    near_fin = RG.cKDTree(samples[far_off > 2.5]).query(off.points_object[moved])[0]
    assert near_fin.max() < 5.0


@pytest.mark.skipif(build_template is None, reason="needs the template stage")
def test_the_reach_stops_when_cancelled():
    from ssm_addon.base.errors import Cancelled

    template = build_template(_ellipsoid_with_rod(4.0), TemplateParams())
    dm = DM.DistanceMap.from_object_volume(_ellipsoid_with_rod(12.0))
    calls = []

    def cancelled():  # cancelled at the reach's second check: after its first round of steps began
        calls.append(1)
        return len(calls) > 1

    with pytest.raises(Cancelled):
        RG.reach_far_parts(template.points_object, template.faces, dm, cancelled=cancelled)
    assert len(calls) == 2


def test_projection_lands_on_marching_cubes_surface_at_subvoxel_accuracy():
    axes = np.array([18.0, 12.0, 9.0])
    ov = ellipsoid_volume(axes)
    dm = DM.DistanceMap.from_object_volume(ov)
    rng = np.random.default_rng(3)
    u = rng.normal(size=(2000, 3))
    on = u / np.sqrt(((u / axes) ** 2).sum(1, keepdims=True))
    pts = on + rng.normal(0, 1.5, on.shape)
    exact = dm.surface_distance(pts)
    inside = ((pts / axes) ** 2).sum(1) < 0.9
    assert np.all(dm.distance(pts[inside]) < 0)
    assert np.abs(np.abs(dm.distance(pts)) - exact).mean() < 0.1  # voxel = 1 mm
    projected = dm.project(pts, 3)
    after = dm.surface_distance(projected)
    assert after.mean() < 0.05 and after.max() < 0.3
    # points outside the grid are pulled in
    far = np.array([[60.0, 0, 0], [0, -70.0, 5.0]])
    assert dm.surface_distance(dm.project(far, 3)).max() < 0.3


# ---------------------------------------------------------------------------------------
# coating with known answers
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ellipsoid_pair():
    a, b = np.array([20.0, 14.0, 10.0]), np.array([24.0, 12.0, 11.0])
    ova = ellipsoid_volume(a)
    template = make_template(ova, a)
    return a, b, ova, ellipsoid_volume(b), template


def test_ellipsoid_coating_follows_axis_scaling(ellipsoid_pair):
    a, b, _, ovb, template = ellipsoid_pair
    result = C.coat(template, ellipsoid_landmarks(a), ovb, ellipsoid_landmarks(a) * b / a)
    truth = np.asarray(template.points_object) * b / a
    err = np.linalg.norm(result.points_object - truth, axis=1)
    print(f"ellipsoid: correspondence error mean {err.mean():.3f} max {err.max():.3f} voxel; {result.fit}")
    assert err.mean() < 0.5 and err.max() < 1.5
    assert result.fit.folded_after == 0
    assert result.fit.max_distance_mm < 0.5


def _quality(points, faces):
    q = mu.triangle_quality(points, faces)
    return q.mean(), q.min()


@pytest.fixture(scope="module")
def deformed_pair():
    a = np.array([20.0, 14.0, 10.0])
    ova = ellipsoid_volume(a)
    template = make_template(ova, a)
    target = object_volume(lambda y: (((y + displacement(y)) / a) ** 2).sum(1) <= 1.0, a.max() + 3, source="deformed")
    lm_src = ellipsoid_landmarks(a)
    return ova, template, target, lm_src, inverse_displacement(lm_src)


def test_smooth_deformation_is_recovered(deformed_pair):
    _, template, target, lm_src, lm_dst = deformed_pair
    pts, faces = np.asarray(template.points_object), np.asarray(template.faces)
    truth = inverse_displacement(pts)
    result = C.coat(template, lm_src, target, lm_dst)
    dm = DM.DistanceMap.from_object_volume(target)
    warp_proj = dm.project(result.warped_points_object, 3)
    rows = []
    for label, p in (("warp + projection", warp_proj), ("full coating", result.points_object)):
        err = np.linalg.norm(p - truth, axis=1)
        folds = int(RX.folded_triangles(p, faces, dm).sum())
        qm, qmin = _quality(p, faces)
        rows.append((label, err.mean(), err.max(), folds, qm, qmin))
        print(f"{label:18s} corr. error mean {err.mean():.3f} max {err.max():.3f} voxel, folds {folds}, "
              f"triangle quality mean {qm:.3f} min {qmin:.3f}")  # fmt: skip
    err_full = rows[1][1]
    assert dm.surface_distance(result.points_object).max() < 0.5
    assert result.fit.folded_after == 0
    assert err_full < 1.0
    # relaxation must not make correspondence worse than warp + projection
    assert err_full <= rows[0][1] + 0.05


def _brute_force_distance(points: np.ndarray, verts: np.ndarray, faces: np.ndarray, k: int = 40) -> np.ndarray:
    """Exact distance (mm) of each point to a triangle mesh, by another route than the package's
    locator: each of the ``k`` triangles with the nearest centroids, its plane when the foot
    falls inside, else its three edges as segments."""
    from scipy.spatial import cKDTree

    tri = verts[faces]
    _, idx = cKDTree(tri.mean(axis=1)).query(points, k=k)
    A, B, C = (tri[idx][:, :, j] for j in range(3))
    P = points[:, None, :]
    n = np.cross(B - A, C - A)
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    h = ((P - A) * n).sum(axis=2)
    foot = P - h[..., None] * n
    inside = np.ones(h.shape, bool)
    for U, V in ((A, B), (B, C), (C, A)):
        inside &= (np.cross(V - U, foot - U) * n).sum(axis=2) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    for U, V in ((A, B), (B, C), (C, A)):
        e = V - U
        t = np.clip(((P - U) * e).sum(axis=2) / (e * e).sum(axis=2), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(P - (U + t[..., None] * e), axis=2))
    return best.min(axis=1)


def test_fit_figures_are_measured_against_the_surface(ellipsoid_pair):
    """The figures are distances in mm to the target's surface as the coating sees it (the
    0.5 isosurface of its mask), checked by brute force on scikit-image's own marching
    cubes of the mask; and within the voxel's reach of the analytic ellipsoid."""
    from skimage.measure import marching_cubes as skimage_marching_cubes

    a, b, _, ovb, template = ellipsoid_pair
    result = C.coat(template, ellipsoid_landmarks(a), ovb, ellipsoid_landmarks(a) * b / a)
    verts, faces, _n, _v = skimage_marching_cubes(np.pad(np.asarray(ovb.mask, np.float32), 1), 0.5)
    verts = (verts - 1.0) * ovb.spacing_mm + np.asarray(ovb.origin_object, float)
    d = _brute_force_distance(np.asarray(result.points_object, float), verts, faces)
    assert result.fit.mean_distance_mm == pytest.approx(d.mean(), rel=1e-6, abs=1e-9)
    assert result.fit.max_distance_mm == pytest.approx(d.max(), rel=1e-6, abs=1e-9)
    # the analytic ellipsoid (semi-axes b mm) lies within a voxel of that surface
    p = np.asarray(result.points_object, float)
    radial = 1.0 - 1.0 / np.sqrt(((p / b) ** 2).sum(axis=1))  # fraction of the radius outside the ellipsoid
    assert np.abs(radial * np.linalg.norm(p, axis=1)).max() < ovb.spacing_mm
    assert len(result.fit.landmark_residuals_mm) == 14
    assert C.FitFigures.from_json(result.fit.to_json()) == result.fit


# ---------------------------------------------------------------------------------------
# batches
# ---------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def batch(ellipsoid_pair):
    a, _, _, _, template = ellipsoid_pair
    axes = [np.array([22.0, 13.0, 10.0]), np.array([19.0, 15.0, 11.0]), np.array([21.0, 14.0, 9.0])]
    return a, template, [ellipsoid_volume(x) for x in axes], [ellipsoid_landmarks(a) * x / a for x in axes]


def test_batch_results_identical_serial_and_parallel(batch, monkeypatch):
    from ssm_addon.base import compute

    a, template, targets, lms = batch
    serial = C.coat_all(template, ellipsoid_landmarks(a), targets, lms, jobs=1)
    # two worker processes even on a one-core runner (where --jobs 2 would be capped to one) and
    # after a Blender test imported bpy in this process (where processes would run serially)
    monkeypatch.setattr(compute, "usable_cores", lambda: 2)
    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    with compute.Executor("processes", jobs=2) as executor:
        assert executor.jobs == 2 and executor.describe() == "2 local processes"
        parallel = C.coat_all(template, ellipsoid_landmarks(a), targets, lms, jobs=2, executor=executor)
    for s, p in zip(serial, parallel):
        assert np.array_equal(s.points_object, p.points_object)
        assert s.fit.iterations == p.fit.iterations


@pytest.mark.parametrize("jobs", [1, 2])
def test_cancelling_keeps_finished_instances(batch, jobs):
    a, template, targets, lms = batch
    finished = []

    def progress(fraction, message):
        if message.startswith("coated"):
            finished.append(message)

    with pytest.raises(C.CoatingCancelled) as info:
        C.coat_all(template, ellipsoid_landmarks(a), targets, lms, jobs=jobs, progress=progress,
                   cancelled=lambda: len(finished) >= 1)  # fmt: skip
    results = info.value.results
    done = [r for r in results if r is not None]
    assert 1 <= len(done) < len(targets)
    from ssm_addon.base.compute import run_one_thread  # batches run each instance with one BLAS thread

    reference = run_one_thread(lambda _: C.coat(template, ellipsoid_landmarks(a), targets[0], lms[0]), None)
    assert results[0] is not None and np.array_equal(results[0].points_object, reference.points_object)


def test_landmarks_proposed_by_coating_without_landmarks(ellipsoid_pair):
    a, _, _, _, template = ellipsoid_pair
    b = a * np.array([1.08, 0.95, 1.05])
    target = ellipsoid_volume(b)
    proposed = PR.propose_landmarks_by_coating(template, ellipsoid_landmarks(a), target)
    truth = ellipsoid_landmarks(a) * b / a  # the axis scaling is the true correspondence
    err = np.linalg.norm(proposed - truth, axis=1)
    naive = np.linalg.norm(ellipsoid_landmarks(a) - truth, axis=1)
    print(f"proposed landmarks: error mean {err.mean():.3f} max {err.max():.3f} mm (unmoved: {naive.mean():.3f})")
    assert err.max() < 1.5 and err.mean() < naive.mean()


def test_warped_rest_lengths_keep_correspondence_better_than_template_scaled(ellipsoid_pair):
    """The default rest lengths ("warped") against the paper's scaled template lengths."""
    a, b, _, ovb, template = ellipsoid_pair
    truth = np.asarray(template.points_object) * b / a
    errors = {}
    for rest in P.REST_LENGTHS:
        params = C.CoatingParams(rest_lengths=rest)
        result = C.coat(template, ellipsoid_landmarks(a), ovb, ellipsoid_landmarks(a) * b / a, params=params)
        errors[rest] = np.linalg.norm(result.points_object - truth, axis=1).mean()
    print(f"rest lengths: correspondence error {errors}")
    assert errors["warped"] < errors["template-scaled"]


@pytest.mark.slow
def test_verse_l1_template_coated_onto_l2_to_l5_and_t12(verse_dir):
    """Real data: every coated vertex within one voxel of the raw surface, no fold left."""
    from conftest import VERSE_FILE, VERSE_LABELS

    from ssm_addon.formats import landmarks as L

    names = ["L1", "L2", "L3", "L4", "L5", "T12"]
    obs = {k: INS.load_object(VERSE_FILE, label=VERSE_LABELS[k], spacing_mm=1.0) for k in names}
    lms = {
        k: obs[k].frame.to_object(L.read_landmarks(verse_dir / "landmarks" / f"{k}.fcsv").points_world) for k in names
    }
    template = build_template(obs["L1"], TemplateParams())
    faces = np.asarray(template.faces)
    results = C.coat_all(template, lms["L1"], [obs[k] for k in names[1:]], [lms[k] for k in names[1:]], jobs=2,
                         names=names[1:])  # fmt: skip
    for k, r in zip(names[1:], results):
        dm = DM.DistanceMap.from_object_volume(obs[k])
        paper = dm.project(W.landmark_warp(lms["L1"], lms[k])(template.points_object), 3)
        folds_paper = int(RX.folded_triangles(paper, faces, dm).sum())
        print(f"{k}: {r.fit.mean_distance_mm:.3f}/{r.fit.max_distance_mm:.3f} mm, folds {r.fit.folded_after} of "
              f"{len(faces)} (warp + projection: {folds_paper}), {r.fit.iterations} it, {r.fit.time_s:.1f} s")  # fmt: skip
        assert r.fit.max_distance_mm < obs[k].spacing_mm
        assert r.fit.folded_after < folds_paper
        assert r.fit.folded_after == 0
    # L5's and T12's extremal-point landmarks mis-map whole parts of L1 (> 5 % folded after
    # registration from the landmark warp): those two start from the object frames
    starts = {k: r.fit.start for k, r in zip(names[1:], results)}
    print(starts)
    assert starts["L2"] == "landmark warp" and starts["L5"] == "object frames"


def test_verse_template_on_its_own_surface_has_no_fold(verse_dir):
    """Fold test calibration: the L1 template on L1's (raw, uncleaned) surface is not folded,
    although triangles that span thin processes flip the raw gradient at their centroid."""
    from conftest import VERSE_FILE, VERSE_LABELS


    ov = INS.load_object(VERSE_FILE, label=VERSE_LABELS["L1"], spacing_mm=1.0)
    template = build_template(ov, TemplateParams(max_distance_mm=None))  # eq. 1: triangles that span processes
    pts, faces = np.asarray(template.points_object), np.asarray(template.faces)
    dm = DM.DistanceMap.from_object_volume(ov)
    assert RX.folded_triangles(pts, faces, dm).sum() == 0
    raw = int(RX.folded_triangles(pts, faces, dm, normal_sigma_mm=0.0).sum())
    print(f"L1 template on L1: folds with the raw gradient {raw}, with the 3 mm smoothed normal 0")
    # the default tolerance template (1,462 points), whose topology cleaning keeps the notches: 2 of its
    # 2,924 triangles turn more than 90 degrees from the raw gradient (spanning thin parts), 9 from the 3 mm
    # smoothed normal (on the walls of the narrowest notches), none from both: the fold test's rule
    dense = build_template(ov, TemplateParams())
    by_raw = int(RX.folded_triangles(dense.points_object, dense.faces, dm, normal_sigma_mm=0.0).sum())
    flagged = int(RX.folded_triangles(dense.points_object, dense.faces, dm).sum())
    print(f"tolerance template on L1: {flagged} of {len(dense.faces)} flagged, {by_raw} by the raw gradient")
    assert flagged == 0 < by_raw


def _relax_per_axis(points, faces, rest_lengths, dm, params):
    """Eq. (3) integrated as :func:`relax` documents it, each force summed one axis at a time,
    the masks applied to every vertex (the reference the vectorised steps must equal)."""
    p = np.array(points, dtype=float)
    e = mu.edges(faces)
    n = len(p)
    v = np.zeros_like(p)
    i0, i1 = e[:, 0], e[:, 1]
    deg = np.maximum(np.bincount(e.ravel(), minlength=n), 1).astype(float)
    surface_on = np.ones(n, dtype=bool)
    it, converged = 0, False
    for it in range(1, params.max_iterations + 1):
        folding = it <= params.fold_iterations
        if it == params.fold_iterations + 1:
            surface_on = np.ones(n, dtype=bool)
        vec = p[i1] - p[i0]
        length = np.linalg.norm(vec, axis=1)
        unit = vec / np.maximum(length, 1e-12)[:, None]
        stretch = length - rest_lengths
        if params.springs == "tension":
            stretch = np.maximum(stretch, 0.0)
        fe = (params.k1 * stretch)[:, None] * unit
        force = np.empty_like(p)
        for k in range(3):
            force[:, k] = np.bincount(i0, fe[:, k], minlength=n) - np.bincount(i1, fe[:, k], minlength=n)
        d, g = dm.sample(p)
        nrm = g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)
        if folding and (it - 1) % params.fold_check_interval == 0:
            folded = RX.folded_triangles(p, faces, dm, params.fold_angle_deg, params.fold_normal_sigma_mm)
            surface_on = np.ones(n, dtype=bool)
            surface_on[faces[folded].ravel()] = False
        k_smooth = params.k3 + params.fold_smoothing * ~surface_on
        if np.any(k_smooth > 0):
            nsum = np.empty_like(p)
            for k in range(3):
                nsum[:, k] = np.bincount(i0, p[i1, k], minlength=n) + np.bincount(i1, p[i0, k], minlength=n)
            force += k_smooth[:, None] * (nsum / deg[:, None] - p)
        if params.tangential_springs:
            force -= np.einsum("ij,ij->i", force, nrm)[:, None] * nrm * surface_on[:, None]
        force += (params.k2 * -d * surface_on)[:, None] * nrm
        v += params.dt * (force - params.damping * v) / params.mass
        p += params.dt * v
        if float(np.sqrt((v * v).sum(1).max())) < params.velocity_tol_mm:
            converged = True
            break
    return p, it, converged


@pytest.mark.parametrize("changes", [{}, {"springs": "linear"}, {"tangential_springs": True, "k3": 0.1}])
def test_relaxation_equals_eq3_summed_axis_by_axis_bit_for_bit(ellipsoid_pair, changes):
    """The relaxation's vectorised step (one force sum per edge end over vertex and axis, no
    mask once every vertex is on the surface) gives the positions of eq. (3) summed one axis
    at a time, to the last bit, through the fold steps and the settling."""
    _a, _, ova, _, template = ellipsoid_pair
    pts, faces = np.asarray(template.points_object, float), np.asarray(template.faces)
    dm = DM.DistanceMap.from_object_volume(ova)
    on = dm.project(pts, 3)
    rest = mu.edge_lengths(on, mu.edges(faces))
    start = on + np.random.default_rng(5).normal(scale=1.2, size=on.shape)  # off the surface, some triangles folded
    params = P.CoatingParams(max_iterations=400, **changes)
    assert RX.folded_triangles(start, faces, dm).any()
    got = RX.relax(start, faces, rest, dm, params=params)
    want = _relax_per_axis(start, faces, rest, dm, params)
    assert got[1] == want[1] > params.fold_iterations and got[2] == want[2]
    assert np.array_equal(got[0], want[0])


def test_untangle_removes_a_fold_and_leaves_the_rest(ellipsoid_pair):
    a, _, ova, _, template = ellipsoid_pair
    pts, faces = np.asarray(template.points_object, float), np.asarray(template.faces)
    dm = DM.DistanceMap.from_object_volume(ova)
    on = dm.project(pts, 3)
    assert RX.folded_triangles(on, faces, dm).sum() == 0
    # drag one vertex across its neighbours along the surface: its fan folds over
    e = mu.edges(faces)
    i = int(np.argmax(on[:, 0]))
    nb = np.unique(e[(e == i).any(axis=1)])
    j = nb[nb != i][0]
    bad = on.copy()
    bad[i] = on[i] + 2.5 * (on[j] - on[i])
    bad[i] = dm.project(bad[i][None], 3)[0]
    assert RX.folded_triangles(bad, faces, dm).sum() > 0
    fixed, rounds = RX.untangle(bad, faces, dm)
    assert RX.folded_triangles(fixed, faces, dm).sum() == 0 and rounds >= 1
    assert dm.surface_distance(fixed).max() < 0.5
    far = np.linalg.norm(on - on[i], axis=1) > 25.0
    assert np.array_equal(fixed[far], bad[far])


def test_untangle_puts_back_a_region_whose_folds_it_cannot_remove(ellipsoid_pair):
    """With a fold test no mesh can pass (every triangle counts as folded at a 1° angle),
    every region fails: the points come back exactly as they went in."""
    from dataclasses import replace as dc_replace

    from ssm_addon.base.params import CoatingParams

    a, _, ova, _, template = ellipsoid_pair
    pts, faces = np.asarray(template.points_object, float), np.asarray(template.faces)
    dm = DM.DistanceMap.from_object_volume(ova)
    on = dm.project(pts, 3)
    strict = dc_replace(CoatingParams(), fold_angle_deg=1.0, untangle_iterations=30)
    assert RX.folded_triangles(on, faces, dm, strict.fold_angle_deg).sum() > 0.9 * len(faces)
    back, rounds = RX.untangle(on, faces, dm, params=strict)
    assert rounds == 30 and np.array_equal(back, on)


def test_projection_along_the_normal_stays_on_its_side_of_a_thin_plate():
    """A point just past the middle of a 3 mm plate, normal towards the far face: the
    gradient projection takes it to the near face, the projection along the normal to
    the face the normal points at (the mask's faces lie half a voxel beyond its centres)."""
    from ssm_addon.instances.volume import ObjectFrame, ObjectVolume

    mask = np.zeros((24, 24, 12), bool)
    mask[2:-2, 2:-2, 4:7] = True  # voxel centres z = 4, 5, 6 mm: faces at 3.5 and 6.5 mm
    ov = ObjectVolume(mask, 1.0, np.zeros(3), ObjectFrame(np.zeros(3), np.eye(3)))
    dm = DM.DistanceMap.from_object_volume(ov)
    p = np.array([[12.0, 12.0, 5.3]])
    assert abs(dm.project(p, 3)[0, 2] - 6.5) < 0.1
    down = dm.project_along(p, np.array([[0.0, 0.0, -1.0]]))
    assert abs(down[0, 2] - 3.5) < 0.1 and np.allclose(down[0, :2], 12.0)


def test_fold_free_warp_smooths_inconsistent_landmarks_until_no_fold(ellipsoid_pair):
    """An extremal landmark that jumps across the shape makes the exact warp fold space."""
    a, _, _, _, template = ellipsoid_pair
    src = ellipsoid_landmarks(a)
    dst = src.copy()
    dst[0] = [-5.0, 0.0, 0.0]  # "right" landmark pulled through the object
    pts = np.asarray(template.points_object)
    exact = W.landmark_warp(src, dst)
    assert W.warp_jacobian_det(exact, pts).min() <= 0
    tps, lam = W.fold_free_warp(src, dst, pts)
    assert lam > 0 and W.warp_jacobian_det(tps, pts).min() > 0
    # consistent landmarks keep the exact warp
    tps, lam = W.fold_free_warp(src, src * 1.1, pts)
    assert lam == 0 and np.abs(tps(src) - src * 1.1).max() < 1e-6


@pytest.mark.slow
def test_default_relaxation_converges_on_every_verse_vertebra_without_folds(verse_dir):
    """With the default parameters the relaxation settles by its velocity tolerance (not by
    its step limit) on T9..L5 from the L1 template and leaves no folded triangle on all but
    one (T10 keeps 12 of 1,262, 1 %, which the folds gate reports); the previous 25-step
    pass (linear springs, warped rest lengths) converged on none.

    Folds left depend chaotically on the template's triangulation: with the triangulations
    scipy 1.15's and 1.17's own tie orders gave, none was left from L1 (but 67 from L3); with
    the library-independent one, 12 from L1, 0 from T12 and 53 from L3 (67 → 65 in all)."""
    from conftest import VERSE_FILE, VERSE_LABELS

    from ssm_addon.base.params import CoatingParams
    from ssm_addon.formats import landmarks as L

    obs = {k: INS.load_object(VERSE_FILE, label=v, spacing_mm=1.0) for k, v in VERSE_LABELS.items()}
    lms = {k: obs[k].frame.to_object(L.read_landmarks(verse_dir / "landmarks" / f"{k}.fcsv").points_world)
           for k in VERSE_LABELS}
    template = build_template(obs["L1"], TemplateParams())
    others = [k for k in VERSE_LABELS if k != "L1"]
    defaults = CoatingParams()
    results = C.coat_all(template, lms["L1"], [obs[k] for k in others], [lms[k] for k in others], jobs=2,
                         names=others)
    folded = {}
    for k, r in zip(others, results):
        print(f"{k}: converged {r.fit.converged} in {r.fit.iterations} steps, folds {r.fit.folded_after}")
        assert r.fit.converged and r.fit.iterations < defaults.max_iterations, k
        assert r.fit.folded_after <= 0.015 * len(template.faces), k
        assert r.fit.max_distance_mm < obs[k].spacing_mm
        if r.fit.folded_after:
            folded[k] = r.fit.folded_after
    assert len(folded) <= 1, folded
    paper_pass = CoatingParams(max_iterations=25, springs="linear", rest_lengths="warped")
    previous = C.coat(template, lms["L1"], obs["L5"], lms["L5"], params=paper_pass)
    assert not previous.fit.converged and previous.fit.iterations == 25


@pytest.mark.slow
def test_default_relaxation_converges_without_folds_on_the_demo(tmp_path):
    """The 24-instance demo population (the README's build): every instance converges by
    tolerance and no triangle is left folded."""
    from ssm_addon.cli import demo
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.runner import run
    from ssm_addon.pipeline.study import Study

    study = Study.from_project(read_project(demo.make_demo_population(tmp_path / "demo", n=24, seed=0)))
    run(study, stages=("import", "template", "coating"), jobs=2)
    fits = {n: c.fit for n, c in study.coatings.items()}
    assert len(fits) == 24
    assert all(f.converged and f.iterations < study.params.coating.max_iterations for f in fits.values()), fits
    assert sum(f.folded_after for f in fits.values()) == 0


def test_a_triangle_turned_over_is_folded_by_the_raw_and_the_smoothed_normal_alike():
    """The fold test's rule: folded when a triangle turns from both the raw and the smoothed
    surface normal. On the wall of a slot 3 voxels wide (the raw normal across the slot, the
    3 mm smoothed one tilted 32 degrees towards its mouth) the wall's own triangle is not folded
    by either, the same triangle turned over is folded by each and by both."""
    m = np.zeros((44, 40, 30), bool)
    m[5:35, 5:35, 5:25] = True
    m[18:21, 5:35, 12:25] = False
    dm = DM.DistanceMap.from_object_volume(ObjectVolume(m, 1.0, np.zeros(3), ObjectFrame(np.zeros(3), np.eye(3))))
    wall = np.array([[17.5, 19.0, 19.0], [17.5, 21.0, 19.0], [17.5, 20.0, 21.0]])  # normal +x, out of the material
    faces = np.array([[0, 1, 2]])
    for sigma in (0.0, 3.0):
        assert not RX.folded_triangles(wall, faces, dm, normal_sigma_mm=sigma).any()
        assert RX.folded_triangles(wall, faces[:, ::-1], dm, normal_sigma_mm=sigma).all()
    smooth = dm.smooth_normals(wall.mean(axis=0)[None], 3.0)[0]
    assert 0.5 < smooth[0] < 0.95 and smooth[2] > 0.3  # tilted towards the mouth (+z), still on the wall's side
