"""Benchmark of the coating stage (paper 4): time and peak memory per step, and CPD side by side.

Run: ``.venv/bin/python tools/bench_coating.py [--verse]``

* coating time per instance for a ~600- and a ~5,000-vertex template on the smooth
  random deformation test of ``tests/test_coating.py`` (ellipsoid 20×14×10 mm, 1 mm
  voxels, displacement of 2 mm amplitude / 40 mm wavelength, 14 landmarks);
* Coherent Point Drift (pycpd, deformable; a dev-only dependency) registering the same
  template onto the target's marching-cubes surface points, from the object-frame
  alignment and from the landmark warp: time ratio and correspondence error ratio;
* batch coating serial vs processes (spawn);
* with ``--verse``: the L1 template coated onto L2..L5 and T12 (needs template.py).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_coating import (  # noqa: E402
    displacement,
    ellipsoid_landmarks,
    ellipsoid_volume,
    inverse_displacement,
    object_volume,
)

from ssm_addon import meshutil as mu  # noqa: E402
from ssm_addon.coating import coating as C  # noqa: E402
from ssm_addon.coating import distance_map as DM  # noqa: E402
from ssm_addon.coating import registration as RG  # noqa: E402
from ssm_addon.coating import relaxation as RX  # noqa: E402
from ssm_addon.coating import warp as W  # noqa: E402
from ssm_addon.instances import importing as INS  # noqa: E402
from ssm_addon.template.template import Template  # noqa: E402


def geodesic_sphere(frequency: int):
    """Class-I geodesic sphere: 10 f² + 2 vertices, 20 f² triangles (outward)."""
    from test_coating import icosphere

    v0, f0 = icosphere(0)
    pts, tris = [], []
    n = frequency
    idx = {(i, j): k for k, (i, j) in enumerate((i, j) for i in range(n + 1) for j in range(n + 1 - i))}
    for a, b, c in f0:
        base = len(pts) and sum(len(p) for p in pts)
        grid = np.array([(i, j) for i in range(n + 1) for j in range(n + 1 - i)], float)
        w = np.c_[1 - (grid[:, 0] + grid[:, 1]) / n, grid[:, 0] / n, grid[:, 1] / n]
        pts.append(w @ v0[[a, b, c]])
        for i in range(n):
            for j in range(n - i):
                tris.append([base + idx[(i, j)], base + idx[(i + 1, j)], base + idx[(i, j + 1)]])
                if i + j < n - 1:
                    tris.append([base + idx[(i + 1, j)], base + idx[(i + 1, j + 1)], base + idx[(i, j + 1)]])
    p = np.vstack(pts)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    _, first, inverse = np.unique(np.round(p, 9), axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    verts = p[first[order]]
    faces = remap[inverse.ravel()][np.array(tris)]
    return verts, faces


def measure(label, fn, memory=True):
    """Time one untraced run; then (``memory``) the peak of a second run under tracemalloc."""
    t = time.perf_counter()
    out = fn()
    el = time.perf_counter() - t
    peak = ""
    if memory:
        tracemalloc.start()
        fn()
        peak = f"peak {tracemalloc.get_traced_memory()[1] / 2**20:7.1f} MiB"
        tracemalloc.stop()
    print(f"  {label:52s} {el:8.3f} s   {peak}", flush=True)
    return out, el


def deformation_case(frequency):
    a = np.array([20.0, 14.0, 10.0])
    ova = ellipsoid_volume(a)
    v, f = geodesic_sphere(frequency)
    pts = DM.DistanceMap.from_object_volume(ova).project(v * a, 3)
    template = Template(points_object=pts, faces=f, curvature=np.zeros(len(pts)), frame=ova.frame)
    target = object_volume(lambda y: (((y + displacement(y)) / a) ** 2).sum(1) <= 1.0, a.max() + 3, source="deformed")
    lm_src = ellipsoid_landmarks(a)
    return template, target, lm_src, inverse_displacement(lm_src), inverse_displacement(pts)


def run_cpd(source, target_points, max_iterations=150):
    from pycpd import DeformableRegistration

    if len(source) > 2000:  # pycpd 2.0 solves an M x M system per iteration (O(M^3)): cap the iterations
        max_iterations = 20
    reg = DeformableRegistration(
        X=target_points, Y=source, alpha=2.0, beta=2.0, max_iterations=max_iterations, tolerance=1e-5
    )
    ty, _ = reg.register()
    return ty


def bench_deformation(cpd_large=False):
    print("smooth random deformation (1 mm voxels)")
    for freq in (8, 22):
        template, target, lm_src, lm_dst, truth = deformation_case(freq)
        n = len(template.points_object)
        print(f" template {n} vertices, {len(template.faces)} triangles")
        dm, _ = measure("distance map", lambda: DM.DistanceMap.from_object_volume(target))  # noqa: B023
        res, t_coat = measure("coat (warp, registration, projection, relaxation)",
                              lambda: C.coat(template, lm_src, target, lm_dst))  # noqa: B023  # fmt: skip
        err = np.linalg.norm(res.points_object - truth, axis=1)
        wp = dm.project(res.warped_points_object, 3)
        err_wp = np.linalg.norm(wp - truth, axis=1)
        paper, _ = measure("coat, paper scheme (no registration)", lambda: C.coat(  # noqa: B023
            template, lm_src, target, lm_dst, params=C.CoatingParams(registration_sigmas_mm=())))  # noqa: B023  # fmt: skip
        e_paper = np.linalg.norm(paper.points_object - truth, axis=1)
        print(f"    paper scheme: corr. error mean {e_paper.mean():.3f} max {e_paper.max():.3f} mm")
        print(f"    coating: corr. error mean {err.mean():.3f} max {err.max():.3f} mm; warp+proj {err_wp.mean():.3f} / "
              f"{err_wp.max():.3f}; fit {res.fit.mean_distance_mm:.3f}/{res.fit.max_distance_mm:.3f} mm, "
              f"folds {res.fit.folded_before}->{res.fit.folded_after}, {res.fit.iterations} it")  # fmt: skip
        x = dm.surface_vertices
        if n > 2000 and not cpd_large:
            print("    CPD skipped for the large template (pycpd 2.0 is O(M^3) per iteration; --cpd-large runs 20 iterations)")
            continue
        for start, label in ((template.points_object, "object frames"), (res.warped_points_object, "landmark warp")):
            ty, t_cpd = measure(f"CPD from {label} ({len(x)} pts)", lambda: run_cpd(start, x), memory=False)  # noqa: B023
            e = np.linalg.norm(ty - truth, axis=1)
            ed = dm.surface_distance(ty)
            print(f"    CPD ({label}): corr. error mean {e.mean():.3f} max {e.max():.3f} mm, surface dist mean "
                  f"{ed.mean():.3f} max {ed.max():.3f}; time ratio CPD/coating {t_cpd / t_coat:.1f}, "
                  f"error ratio CPD/coating {e.mean() / err.mean():.2f}")  # fmt: skip


def bench_batch():
    print("batch: 4 ellipsoid targets, 642-vertex template")
    a = np.array([20.0, 14.0, 10.0])
    template, *_ = deformation_case(8)
    axes = [a * s for s in (np.array([1.1, 0.9, 1.0]), np.array([0.95, 1.05, 1.1]), np.array([1.05, 1.0, 0.9]),
                            np.array([0.9, 0.95, 1.05]))]  # fmt: skip
    targets = [ellipsoid_volume(x) for x in axes]
    lms = [ellipsoid_landmarks(a) * x / a for x in axes]
    serial, ts = measure("coat_all jobs=1", lambda: C.coat_all(template, ellipsoid_landmarks(a), targets, lms, jobs=1))
    par, tp = measure("coat_all jobs=2 (spawn)", lambda: C.coat_all(template, ellipsoid_landmarks(a), targets, lms, jobs=2),
                      memory=False)  # fmt: skip
    fs, tf = measure("coat_all jobs=2 (forkserver)", lambda: C.coat_all(
        template, ellipsoid_landmarks(a), targets, lms, jobs=2, start_method="forkserver"), memory=False)  # fmt: skip
    same = all(np.array_equal(s.points_object, p.points_object) and np.array_equal(s.points_object, q.points_object)
               for s, p, q in zip(serial, par, fs))  # fmt: skip
    print(f"    identical: {same}; per instance serial {ts / 4:.3f} s, spawn {tp / 4:.3f} s, forkserver {tf / 4:.3f} s")


def bench_verse():
    from conftest import VERSE_DIR, VERSE_FILE, VERSE_LABELS

    from ssm_addon.formats import landmarks as L
    from ssm_addon.template.template import TemplateParams, build_template

    print("VerSe: L1 template onto L2..L5, T12")
    names = ["L1", "L2", "L3", "L4", "L5", "T12"]
    obs = {k: INS.load_object(VERSE_FILE, label=VERSE_LABELS[k], spacing_mm=1.0) for k in names}
    lms = {k: obs[k].frame.to_object(L.read_landmarks(VERSE_DIR / "landmarks" / f"{k}.fcsv").points_world) for k in names}
    template, _ = measure("build_template L1", lambda: build_template(obs["L1"], TemplateParams()))
    print(f"    template {len(template.points_object)} vertices")
    for k in names[1:]:
        r, _ = measure(f"coat {k}", lambda: C.coat(template, lms["L1"], obs[k], lms[k], name=k))  # noqa: B023
        f = r.fit
        print(f"    {k}: mean {f.mean_distance_mm:.3f} max {f.max_distance_mm:.3f} mm, folds {f.folded_before}->"
              f"{f.folded_after}, {f.iterations} it, untangle {f.untangle_rounds} rounds, landmark residual max "
              f"{f.max_landmark_residual_mm:.2f} mm")  # fmt: skip
    bench_stages(template, lms["L1"], obs["L3"], lms["L3"])


def bench_stages(template, src, target, dst, params=None):
    """Time of each coating stage on one instance (what coat() does, step by step)."""
    params = params or C.CoatingParams()
    print(f"  stages of one coat() call ({target.source or 'target'}, {len(template.points_object)} vertices)")
    pts, faces = np.asarray(template.points_object, float), np.asarray(template.faces)
    tps, _ = measure("fold-free landmark warp", lambda: W.fold_free_warp(src, dst, pts), memory=False)
    warped = tps[0](pts)
    dm, _ = measure("distance map (EDT + marching cubes)", lambda: DM.DistanceMap.from_object_volume(target), memory=False)
    measure("smoothed normals for the fold test", lambda: dm.smooth_normals(pts, params.fold_normal_sigma_mm), memory=False)
    reg, _ = measure("register_to_surface", lambda: RG.register_to_surface(  # noqa: B023
        warped, faces, dm, params.registration_sigmas_mm, params.registration_iterations), memory=False)  # fmt: skip
    proj = dm.project(reg, params.projection_iterations)
    e = mu.edges(faces)
    d0 = np.linalg.norm(reg[e[:, 1]] - reg[e[:, 0]], axis=1)
    (relaxed, it, _), _ = measure("relax", lambda: RX.relax(proj, faces, d0, dm, params=params, edges=e), memory=False)
    relaxed = dm.project(relaxed, params.projection_iterations)
    measure(f"untangle ({it} relaxation steps before)", lambda: RX.untangle(relaxed, faces, dm, params=params, edges=e), memory=False)
    measure("fit figures (exact surface distances)", lambda: dm.surface_distance(relaxed), memory=False)


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--verse", action="store_true")
    ap.add_argument("--cpd-large", action="store_true")
    args = ap.parse_args()
    bench_deformation(args.cpd_large)
    bench_batch()
    if args.verse:
        bench_verse()


if __name__ == "__main__":
    main()
