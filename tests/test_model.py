"""The statistical model of paper section 5: eqs. 4-8, Procrustes, model.npz and statismo files."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from conftest import FACES, names, random_rotation, sphere_points, synthetic_population

from ssm_addon.base.errors import InputError
from ssm_addon.model.files import load_npz, load_statismo, save_npz, save_statismo
from ssm_addon.model.pca import ShapeModel, build_model, generalized_procrustes


def small_random(n=7, n_points=12, seed=0):
    rng = np.random.default_rng(seed)
    base = sphere_points(n_points, 10.0)
    return base[None] + rng.normal(scale=[2.0, 1.0, 0.5], size=(n, n_points, 3))


# ---------------------------------------------------------------------------------------
# eqs. 4-6
# ---------------------------------------------------------------------------------------
def test_modes_and_eigenvalues_equal_explicit_covariance_eq5():
    x = small_random()
    n = len(x)
    model = build_model(x, FACES, names(n))
    p = x.reshape(n, -1)
    mean = p.mean(axis=0)
    s = (p - mean).T @ (p - mean) / n  # eq. 5, 36 x 36
    w, v = np.linalg.eigh(s)
    w, v = w[::-1], v[:, ::-1]
    assert model.n_modes == n - 1
    np.testing.assert_allclose(model.mean.ravel(), mean, atol=1e-12)  # eq. 4
    np.testing.assert_allclose(model.variances, w[: n - 1], rtol=1e-10)
    np.testing.assert_allclose(w[n - 1 :], 0, atol=1e-10)
    cos = np.abs(np.einsum("kj,jk->k", model.modes.reshape(n - 1, -1), v[:, : n - 1]))
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)


def test_modes_are_orthonormal_and_eigenvalues_descending_nonnegative():
    x = synthetic_population(n=25, noise_mm=0.3)[0]
    model = build_model(x, FACES, names(25))
    q = model.basis()
    np.testing.assert_allclose(q.T @ q, np.eye(model.n_modes), atol=1e-12)
    assert np.all(np.diff(model.variances) <= 0)
    assert np.all(model.variances > 0)
    assert model.n_modes == 24  # at most n - 1 non-zero modes


def test_all_modes_reconstruct_every_training_shape():
    x = synthetic_population(n=20, noise_mm=0.5)[0]
    model = build_model(x, FACES, names(20))
    for shape in x:
        assert np.abs(model.reconstruct(shape) - shape).max() < 1e-8
    # the scores are the projections
    np.testing.assert_allclose(model.scores()[3], model.project(x[3]), atol=1e-12)


def test_zero_modes_are_dropped_for_rank_deficient_data():
    shapes, mean, fields, lam = synthetic_population(n=12, noise_mm=0.0)
    model = build_model(shapes, FACES, names(12))
    assert model.n_modes == 3
    np.testing.assert_allclose(model.variances, lam, rtol=1e-10)


def test_sign_convention_largest_component_positive():
    model = build_model(small_random(), FACES, names(7))
    flat = model.modes.reshape(model.n_modes, -1)
    assert np.all(flat[np.arange(len(flat)), np.abs(flat).argmax(axis=1)] > 0)


def test_ddof_one_scales_eigenvalues_by_n_over_n_minus_1():
    x = small_random()
    a = build_model(x, FACES, names(7))
    b = build_model(x, FACES, names(7), ddof=1)
    np.testing.assert_allclose(b.variances, a.variances * 7 / 6, rtol=1e-12)
    np.testing.assert_allclose(b.point_variance, a.point_variance * 7 / 6, rtol=1e-12)


def test_n_modes_truncates_but_keeps_total_variance():
    x = small_random()
    full = build_model(x, FACES, names(7))
    two = build_model(x, FACES, names(7), n_modes=2)
    assert two.n_modes == 2
    np.testing.assert_allclose(two.variances, full.variances[:2], rtol=1e-12)
    assert two.total_variance == pytest.approx(full.total_variance)
    assert two.variability_concentration()[-1] < 1.0


# ---------------------------------------------------------------------------------------
# eq. 7 and eq. 8
# ---------------------------------------------------------------------------------------
def test_generated_shapes_obey_eq7():
    model = build_model(small_random(), FACES, names(7))
    b = np.array([1.5, -0.7, 0.2])
    expected = model.mean.copy()
    for k, bk in enumerate(b):
        expected += bk * model.modes[k]
    np.testing.assert_allclose(model.generate(b), expected, atol=1e-12)
    np.testing.assert_allclose(model.project(model.generate(b))[:3], b, atol=1e-12)
    z = np.array([2.0, -1.0])
    np.testing.assert_allclose(model.generate_sd(z), model.generate(z * np.sqrt(model.variances[:2])), atol=1e-12)
    with pytest.raises(InputError, match="weight vector"):
        model.generate(np.ones(model.n_modes + 1))


def test_samples_have_the_model_variances():
    shapes = synthetic_population(n=30, noise_mm=0.0)[0]
    model = build_model(shapes, FACES, names(30))
    s = model.sample(4000, seed=3)
    b = np.array([model.project(p) for p in s[:2000]])
    np.testing.assert_allclose(b.var(axis=0), model.variances, rtol=0.1)


def test_eigen_concentration_dominates_coordinate_concentration_eq8():
    model = build_model(synthetic_population(n=30, noise_mm=0.2)[0], FACES, names(30))
    eig = model.variability_concentration("eigen")
    coord = model.variability_concentration("coordinate")
    assert eig[-1] == pytest.approx(1.0)
    assert coord[-1] == pytest.approx(1.0)
    assert coord.shape == (3 * model.n_points,)
    # Ky Fan: the k largest eigenvalues carry at least as much as any k diagonal entries
    assert np.all(eig >= coord[: len(eig)] - 1e-12)


def test_point_variance_is_trace_of_point_covariance_block():
    x = small_random()
    model = build_model(x, FACES, names(7))
    direct = x.var(axis=0).sum(axis=1)
    np.testing.assert_allclose(model.point_variance, direct, rtol=1e-12)
    from_modes = np.tensordot(model.variances, model.modes**2, axes=1).sum(axis=1)
    np.testing.assert_allclose(model.point_variance, from_modes, rtol=1e-9)


# ---------------------------------------------------------------------------------------
# known generating modes
# ---------------------------------------------------------------------------------------
def test_model_recovers_known_generating_modes_and_variances():
    shapes, mean, fields, lam = synthetic_population(n=60, noise_mm=0.02)
    model = build_model(shapes, FACES, names(60))
    for k in range(3):
        cos = abs(np.dot(model.modes[k].ravel(), fields[k].ravel()))
        assert cos > 0.95, (k, cos)
        assert model.variances[k] == pytest.approx(lam[k], rel=0.1)
    assert np.abs(model.mean - mean).max() < 0.1
    assert model.variability_concentration()[2] >= 0.99


# ---------------------------------------------------------------------------------------
# Procrustes
# ---------------------------------------------------------------------------------------
def test_rigid_procrustes_removes_random_rigid_transforms():
    rng = np.random.default_rng(5)
    shapes = synthetic_population(n=15, noise_mm=0.1)[0]
    moved = np.stack([s @ random_rotation(rng).T + rng.normal(scale=30.0, size=3) for s in shapes])
    ref = build_model(shapes, FACES, names(15), alignment="rigid")
    model = build_model(moved, FACES, names(15), alignment="rigid")
    plain = build_model(moved, FACES, names(15))
    assert model.params["alignment_info"]["converged"]
    np.testing.assert_allclose(model.variances, ref.variances, rtol=1e-6)
    assert plain.total_variance > 10 * model.total_variance
    # aligned instances agree with those of the untransformed population up to one rigid motion
    a = model.instance_points.reshape(-1, 3)
    b = ref.instance_points.reshape(-1, 3)
    from ssm_addon.model.pca import procrustes_fit

    s, rot, t = procrustes_fit(a[None], b, scale=False)
    assert np.abs(a @ rot[0].T + t[0] - b).max() < 1e-6
    # projection aligns a moved shape first: a moved training shape reconstructs exactly
    q = random_rotation(rng)
    back = model.reconstruct(moved[2] @ q.T + 5.0)
    assert np.abs(back - (moved[2] @ q.T + 5.0)).max() < 1e-6


def test_similarity_procrustes_removes_scale():
    rng = np.random.default_rng(2)
    shapes = synthetic_population(n=10, noise_mm=0.05)[0]
    ref = build_model(shapes, FACES, names(10), alignment="similarity")
    scaled = np.stack([rng.uniform(0.7, 1.4) * (s @ random_rotation(rng).T) for s in shapes])
    model = build_model(scaled, FACES, names(10), alignment="similarity")
    assert model.params["alignment_info"]["converged"]
    # equal up to one global scale: the same spectrum shape, the same aligned shapes
    np.testing.assert_allclose(model.variances / model.total_variance, ref.variances / ref.total_variance, rtol=1e-5)
    from ssm_addon.model.pca import procrustes_fit

    a, b = model.instance_points.reshape(-1, 3), ref.instance_points.reshape(-1, 3)
    s, rot, t = procrustes_fit(a[None], b, scale=True)
    assert np.abs(s[0] * a @ rot[0].T + t[0] - b).max() < 1e-5
    # rigid alignment cannot remove the scale
    rigid = build_model(scaled, FACES, names(10), alignment="rigid")
    assert rigid.total_variance > 5 * model.total_variance


def test_generalized_procrustes_keeps_identical_shapes_in_place():
    base = sphere_points(50) * [1.0, 0.7, 0.4]
    aligned, info = generalized_procrustes(np.stack([base, base]), scale=True)
    assert info["converged"]
    np.testing.assert_allclose(aligned, np.stack([base, base]), atol=1e-9)


# ---------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------
def _model_with_world():
    x = small_random()
    world = x + np.array([100.0, -50.0, 20.0])
    return build_model(x, FACES, names(7), instance_points_world=world, params={"template": {"spacing_mm": 1.5}})


def assert_models_equal(a: ShapeModel, b: ShapeModel, rtol=0.0, atol=0.0):
    for key in ("mean", "modes", "variances", "instance_points", "instance_points_world"):
        np.testing.assert_allclose(getattr(b, key), getattr(a, key), rtol=rtol, atol=atol, err_msg=key)
    np.testing.assert_array_equal(b.faces, a.faces)
    assert list(b.instance_names) == list(a.instance_names)


def test_npz_round_trip_is_exact_and_needs_no_pickle(tmp_path):
    model = _model_with_world()
    path = save_npz(model, tmp_path / "model.npz")
    with np.load(path, allow_pickle=False) as data:
        assert set(data.files) == {
            "mean",
            "faces",
            "modes",
            "variances",
            "instance_names",
            "instance_points",
            "instance_points_world",
            "params_json",
        }
        assert data["instance_names"].dtype.kind == "U"
        assert json.loads(str(data["params_json"]))["template"]["spacing_mm"] == 1.5
    back = load_npz(path)
    assert_models_equal(model, back)
    assert back.params == model.params


def test_load_npz_reports_bad_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_npz(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(InputError, match="junk.npz"):
        load_npz(tmp_path / "junk.npz")
    model = _model_with_world()
    good = dict(np.load(save_npz(model, tmp_path / "m.npz")))
    np.savez(tmp_path / "missing.npz", **{k: v for k, v in good.items() if k != "modes"})
    with pytest.raises(InputError, match=r"missing.npz.*'modes'"):
        load_npz(tmp_path / "missing.npz")
    bad = dict(good)
    bad["modes"] = good["modes"][:, :5]
    np.savez(tmp_path / "shape.npz", **bad)
    with pytest.raises(InputError, match=r"shape.npz: 'modes' has shape"):
        load_npz(tmp_path / "shape.npz")
    bad = dict(good)
    bad["instance_names"] = np.array([object()] * 7, dtype=object)
    np.savez(tmp_path / "pickled.npz", **bad)
    with pytest.raises(InputError, match="pickled.npz"):
        load_npz(tmp_path / "pickled.npz")


def test_statismo_file_has_statismo_layout(tmp_path):
    model = _model_with_world()
    path = save_statismo(model, tmp_path / "model.h5")
    n3, k = 3 * model.n_points, model.n_modes
    with h5py.File(path, "r") as f:
        assert int(f["version/majorVersion"][()]) == 0 and int(f["version/minorVersion"][()]) == 9
        assert f["model/mean"].shape == (n3,) and f["model/mean"].dtype == np.float32
        assert f["model/pcaBasis"].shape == (n3, k)
        assert f["model/pcaVariance"].shape == (k,)
        assert f["model/noiseVariance"].shape == ()
        rep = f["representer"]
        assert rep.attrs["datasetType"] == "POLYGON_MESH"
        assert rep.attrs["name"] == "itkStandardMeshRepresenter"
        assert rep["points"].shape == (3, model.n_points)
        assert rep["cells"].shape == (3, len(model.faces))
        assert "build-time" in f["modelinfo"]
        assert f["modelinfo/scores"].shape == (k, model.n_instances)
        assert "parameters" in f["modelinfo/modelBuilder-0"]
        basis = f["model/pcaBasis"][()].astype(float)
        # version 0.9: the basis is orthonormal (not scaled by sqrt(lambda))
        np.testing.assert_allclose(basis.T @ basis, np.eye(k), atol=1e-5)
        np.testing.assert_allclose(f["representer/points"][()].T, model.mean, rtol=1e-6)


def test_statismo_round_trip_equal_to_float32(tmp_path):
    model = _model_with_world()
    back = load_statismo(save_statismo(model, tmp_path / "model.h5"))
    assert_models_equal(model, back, rtol=1e-6, atol=1e-5)
    np.testing.assert_array_equal(back.instance_points, model.instance_points)
    assert back.params == model.params


def test_load_statismo_reads_old_scaled_basis(tmp_path):
    model = _model_with_world()
    path = save_statismo(model, tmp_path / "old.h5")
    with h5py.File(path, "r+") as f:
        f["version/minorVersion"][()] = 8
        scaled = f["model/pcaBasis"][()] * np.sqrt(f["model/pcaVariance"][()])[None]
        f["model/pcaBasis"][...] = scaled
        del f["ssm"]
    back = load_statismo(path)
    np.testing.assert_allclose(back.modes, model.modes, atol=1e-5)
    assert back.n_instances == 0
    with pytest.raises(InputError, match="not found"):
        load_statismo(tmp_path / "none.h5")


def test_build_model_rejects_bad_input():
    x = small_random()
    with pytest.raises(InputError, match="at least 2"):
        build_model(x[:1], FACES, names(1))
    with pytest.raises(InputError, match="names"):
        build_model(x, FACES, names(3))
    with pytest.raises(InputError, match="alignment"):
        build_model(x, FACES, names(7), alignment="affine")
    bad = x.copy()
    bad[4, 0, 0] = np.nan
    with pytest.raises(InputError, match=r"instances \[4\]"):
        build_model(bad, FACES, names(7))
    with pytest.raises(InputError, match="faces"):
        build_model(x, [[0, 1, 99]], names(7))


def test_modes_stay_orthonormal_over_a_wide_eigenvalue_range():
    # eigenvalues spanning 9 decades: the Gram route alone loses orthogonality for the small ones
    shapes, mean, fields, _ = synthetic_population(n=30, variances=(1e4, 1.0, 1e-3), noise_mm=1e-3)
    model = build_model(shapes, FACES, names(30))
    q = model.basis()
    np.testing.assert_allclose(q.T @ q, np.eye(model.n_modes), atol=1e-12)
    assert model.variances[0] / model.variances[-1] > 1e8
    assert model.params["reorthonormalised"]  # the correction was needed and applied
    for shape in shapes[:5]:
        assert np.abs(model.reconstruct(shape) - shape).max() < 1e-8


def test_randomized_solver_agrees_with_exact():
    """Above the size threshold 'auto' uses the randomized SVD; its leading modes equal the exact ones."""
    from ssm_addon.model.pca import RANDOMIZED_MIN_ELEMENTS

    rng = np.random.default_rng(4)
    n, npts, k = 400, 700, 6
    basis = np.linalg.qr(rng.standard_normal((npts * 3, k)))[0].T
    sd = np.array([20.0, 12.0, 8.0, 5.0, 3.0, 2.0])
    x = (rng.standard_normal((n, k)) * sd) @ basis + 0.05 * rng.standard_normal((n, npts * 3))
    x = x.reshape(n, npts, 3)
    assert x.size < RANDOMIZED_MIN_ELEMENTS  # forced here; 'auto' switches above the threshold
    exact = build_model(x, np.zeros((0, 3), int), [str(i) for i in range(n)], n_modes=k, solver="exact")
    fast = build_model(x, np.zeros((0, 3), int), [str(i) for i in range(n)], n_modes=k, solver="randomized")
    assert fast.params["eigensolver"].startswith("randomized")
    np.testing.assert_allclose(fast.variances, exact.variances, rtol=1e-9)
    m_exact, m_fast = exact.modes.reshape(k, -1), fast.modes.reshape(k, -1)
    np.testing.assert_allclose(np.abs(np.sum(m_exact * m_fast, axis=1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(m_fast @ m_fast.T, np.eye(k), atol=1e-12)
    np.testing.assert_array_equal(fast.mean, exact.mean)
    # a variance fraction keeps the fewest leading modes reaching it, with either solver
    frac = float(np.cumsum(exact.variances)[2] / exact.total_variance) - 1e-6
    for solver in ("exact", "randomized"):
        m = build_model(x, np.zeros((0, 3), int), [str(i) for i in range(n)], variance_fraction=frac, solver=solver)
        assert m.n_modes == 3, solver
    f32 = build_model(x, np.zeros((0, 3), int), [str(i) for i in range(n)], n_modes=k, precision="float32")
    assert f32.instance_points.dtype == np.float32
    np.testing.assert_allclose(f32.variances, exact.variances, rtol=1e-5)


def test_more_instances_than_coordinates_uses_the_covariance_and_equals_the_gram_route():
    # 150 shapes of 12 points (36 coordinates): eq. 5's 36 × 36 covariance, not a 150 × 150 Gram matrix
    shapes, _mean, _fields, variances = synthetic_population(n=150, n_points=12, variances=(25.0, 9.0, 4.0),
                                                              noise_mm=0.01, seed=3)
    auto = build_model(shapes, FACES, names(150))
    gram = build_model(shapes, FACES, names(150), solver="exact")
    assert auto.params["eigensolver"].startswith("covariance") and gram.params["eigensolver"].startswith("Gram")
    assert auto.n_modes == gram.n_modes == 36  # rank min(n - 1, 3N)
    np.testing.assert_allclose(auto.variances, gram.variances, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(auto.variances[:3], variances, rtol=1e-3)  # the population's, plus 0.01 mm noise
    np.testing.assert_allclose(auto.modes[:3], gram.modes[:3], atol=1e-8)  # the same signs (largest component +)
    m = auto.modes.reshape(auto.n_modes, -1)
    np.testing.assert_allclose(m @ m.T, np.eye(auto.n_modes), atol=1e-12)
    for shape in shapes[:5]:  # every mode: the training shapes themselves
        assert np.abs(auto.reconstruct(shape) - shape).max() < 1e-8


@pytest.mark.parametrize("alignment", ["none", "rigid", "similarity"])
def test_projecting_many_shapes_at_once_equals_projecting_each(alignment, monkeypatch):
    """``project_all`` (one product per block of shapes, blocks smaller than the study here)
    gives each shape's ``project``, turned and moved shapes aligned alike."""
    import ssm_addon.model.pca as pca

    shapes, *_ = synthetic_population(n=12, n_points=40, noise_mm=0.5, seed=8)
    m = build_model(shapes, np.zeros((0, 3), int), names(12), alignment=alignment)
    rng = np.random.default_rng(2)
    others = np.stack([s @ random_rotation(rng).T + rng.normal(size=3) * 20 for s in shapes[:5]])
    test = np.concatenate([m.instance_points, others if alignment != "none" else shapes[:5]])
    monkeypatch.setattr(pca, "PROJECT_BLOCK", 5)
    together = m.project_all(test)
    each = np.stack([m.project(p) for p in test])
    np.testing.assert_allclose(together, each, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(m.project_all(test, k=3), each[:, :3], rtol=1e-10, atol=1e-9)
    with pytest.raises(InputError, match="expected"):
        m.project_all(test[0])
