"""Correspondence error against known truth: where the coating puts the template's points.

Populations with known dense correspondence:

* ``femur10``: ten real femurs sharing one connectivity (``../shared/data/femur10``).
* ``deformed``: the verse004 vertebra L1 (or ``--label``) deformed by known smooth,
  invertible deformations (sums of Gaussian displacement bumps at several spatial
  scales, each kept below the fold limit), so every surface point's true place on
  every instance is known.

The template's points lie on its instance's surface; their true place on instance k is
the same surface point mapped by the known correspondence (the shared triangles of
femur10; the deformation of the deformed population). The error of a point is its
distance, in world mm, from that true place: not a surface distance.

Usage::

    python tools/eval_correspondence.py femur10 [--landmarks 15] [--on 10] [--jitter 0]
        [--method landmarks|model] [--exact-landmarks] [--iterations 3] [--jobs 2]
    python tools/eval_correspondence.py deformed [--n 20] ...
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks  # noqa: E402
from ssm_addon.instances.importing import InstanceSpec  # noqa: E402
from ssm_addon.meshutil import locate_on_mesh, read_mesh  # noqa: E402
from ssm_addon.pipeline.params import CorrespondenceParams  # noqa: E402
from ssm_addon.pipeline.study import Study, run  # noqa: E402

DATA = ROOT.parent / "shared" / "data"


def farthest_points(points: np.ndarray, k: int, start: int) -> np.ndarray:
    """Indices of ``k`` farthest-point samples of ``points`` from ``start``."""
    chosen = [start]
    d = np.linalg.norm(points - points[start], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return np.array(chosen)


def femur_population():
    """(names, [(vertices, faces)], correspondence) of femur10; truth by shared vertices."""
    files = sorted((DATA / "femur10").glob("femur*.ply"))
    if not files:
        raise SystemExit(f"no femur10 data under {DATA / 'femur10'}")
    meshes = [read_mesh(f) for f in files]
    return [f.stem for f in files], meshes


def deformation_field(rng, centre: np.ndarray, size: float, scales=(0.6, 0.3, 0.15), amplitude=0.35):
    """A smooth invertible displacement u(x) (mm -> mm): Gaussian bumps at several scales.

    Each bump of width s has its largest gradient ~ a/s * 0.61; keeping the summed
    gradient below 1 keeps x + u(x) invertible (no folds)."""
    bumps = []
    per_scale_limit = 0.8 / len(scales)
    for frac in scales:
        s = frac * size
        n = max(2, int(round(1.5 / frac)))
        for _ in range(n):
            c = centre + rng.uniform(-0.5, 0.5, 3) * size
            a = rng.normal(size=3)
            a *= min(amplitude * s, per_scale_limit * s / 0.61 / n ** 0.5) / np.linalg.norm(a)
            bumps.append((c, s, a))

    def u(x):
        x = np.asarray(x, float)
        out = np.zeros_like(x)
        for c, s, a in bumps:
            w = np.exp(-((x - c) ** 2).sum(axis=1) / (2 * s * s))
            out += w[:, None] * a
        return out

    return u


def invert(u, y: np.ndarray, iterations: int = 60) -> np.ndarray:
    """x with x + u(x) = y (fixed point; converges as |grad u| < 1)."""
    x = y.copy()
    for _ in range(iterations):
        x = y - u(x)
    return x


def deformed_population(n: int, label: int, seed: int, workdir: Path):
    """verse004 ``label`` deformed n-1 times (instance 0 undeformed): NIfTI files + truth maps."""
    import nibabel as nib

    src = DATA / "verse004" / "sub-verse004_seg-vert_msk.nii.gz"
    if not src.exists():
        raise SystemExit(f"no verse004 data at {src}")
    img = nib.load(str(src))
    data = np.asarray(img.dataobj)
    mask = data == label
    idx = np.argwhere(mask)
    lo, hi = idx.min(axis=0) - 20, idx.max(axis=0) + 21
    lo = np.maximum(lo, 0)
    sub = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    affine = img.affine.copy()
    affine[:3, 3] = img.affine[:3, :3] @ lo + img.affine[:3, 3]
    pts = np.argwhere(sub) @ affine[:3, :3].T + affine[:3, 3]
    centre, size = pts.mean(axis=0), float(np.ptp(pts, axis=0).max())
    rng = np.random.default_rng(seed)
    grid = np.stack(np.meshgrid(*[np.arange(s) for s in sub.shape], indexing="ij"), -1).reshape(-1, 3)
    world = grid @ affine[:3, :3].T + affine[:3, 3]
    from scipy.ndimage import map_coordinates

    inv_aff = np.linalg.inv(affine)
    names, files, maps = [], [], []
    for k in range(n):
        if k == 0:
            u = lambda x: np.zeros_like(np.asarray(x, float))  # noqa: E731
        else:
            amplitude = 0.35
            u = deformation_field(rng, centre, size, amplitude=amplitude)
            while jacobian_min(u, pts[::5]) < 0.4:  # keep it invertible with margin
                amplitude *= 0.7
                u = deformation_field(rng, centre, size, amplitude=amplitude)
        path = workdir / f"def{k:02d}.nii.gz"
        names.append(f"def{k:02d}")
        files.append(path)
        maps.append(u)
        if path.exists():  # cached (same seed, same deformation)
            continue
        # target voxel y holds the source value at x = phi^-1(y)
        x = invert(u, world)
        ijk = x @ inv_aff[:3, :3].T + inv_aff[:3, 3]
        vals = map_coordinates(sub.astype(np.float32), ijk.T, order=1, mode="constant", cval=0.0)
        out = (vals.reshape(sub.shape) >= 0.5).astype(np.uint8)
        nib.save(nib.Nifti1Image(out, affine), str(path))
    return names, files, maps


LANDMARK_WEIGHT = [None]
EXACT_LANDMARKS = [False]


def run_study(specs, template_name: str, method: str, iterations: int, jobs: int, spacing: float | None = None):
    study = Study(instances=specs, template_instance=template_name)
    if spacing:
        study.template_params = replace(study.template_params, spacing_mm=spacing)
    extra = {} if LANDMARK_WEIGHT[0] is None else {"landmark_weight": LANDMARK_WEIGHT[0]}
    extra["exact_landmarks"] = EXACT_LANDMARKS[0]
    study.correspondence_params = CorrespondenceParams(method=method, iterations=iterations, **extra)
    t0 = time.perf_counter()
    say = lambda m: print("  " + m, flush=True)  # noqa: E731
    run(study, stages=("import", "template"), jobs=jobs, log=say)
    template_points = study.template.points_object.copy()
    run(study, stages=("coating",), jobs=jobs, log=say)
    return study, template_points, time.perf_counter() - t0


def summarise(errors: dict, label: str):
    allv = np.concatenate(list(errors.values()))
    print(f"{label}: mean {allv.mean():.3f} mm, 95th {np.percentile(allv, 95):.2f} mm, worst {allv.max():.1f} mm "
          f"(points {allv.size})", flush=True)
    return allv


def eval_femur(args):
    names, meshes = femur_population()
    v0, f0 = meshes[0]
    lm_idx = farthest_points(v0, args.landmarks, int(np.argmax(v0[:, 2])))
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        specs = []
        for i, (name, (v, _f)) in enumerate(zip(names, meshes)):
            lm = None
            if i < args.on:
                pts = v[lm_idx] + rng.normal(scale=args.jitter, size=(len(lm_idx), 3)) * (i > 0 or args.jitter_template)
                lm = Path(tmp) / f"{name}.csv"
                write_landmarks(lm, LandmarkSet(tuple(f"L{j:02d}" for j in range(len(lm_idx))), pts, name))
            specs.append(InstanceSpec(name=name, mesh=DATA / "femur10" / f"{name}.ply", landmarks=lm,
                                      landmark_set=read_landmarks(lm) if lm else None))
        study, template_points, seconds = run_study(specs, names[0], args.method, args.iterations, args.jobs)
    # point i of every coating is template point i, which lies on femur00's surface
    loc = locate_on_mesh(v0, f0, study.frame(names[0]).to_world(template_points))
    errors = {}
    got = {n: study.frame(n).to_world(study.coatings[n].points_object) for n in names}
    for name, (v, _f) in zip(names, meshes):
        errors[name] = np.linalg.norm(got[name] - loc.evaluate(v, f0), axis=1)
    # consensus: every coating pulled back to femur00 through the known correspondence;
    # their mean is the consensus place of each point, pushed forward to every femur
    pulled = np.mean([locate_on_mesh(v, f0, got[n]).evaluate(v0, f0) for n, (v, _f) in zip(names, meshes)], axis=0)
    cons = locate_on_mesh(v0, f0, pulled)
    consensus = {n: np.linalg.norm(got[n] - cons.evaluate(v, f0), axis=1) for n, (v, _f) in zip(names, meshes)}
    for name in names:
        e = errors[name]
        print(f"  {name}: mean {e.mean():.2f}, 95th {np.percentile(e, 95):.2f}, worst {e.max():.1f} mm, "
              f"folds {study.coatings[name].fit.folded_after}")
    label = f"femur10 {args.method} landmarks={args.landmarks} on={args.on} jitter={args.jitter} ({seconds:.0f} s)"
    summarise(errors, label + " against the template's points")
    summarise(consensus, label + " against the consensus")


def jacobian_min(u, pts: np.ndarray, h: float = 0.5) -> float:
    """Smallest det(I + du/dx) over ``pts`` (central differences, mm)."""
    J = np.zeros((len(pts), 3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        J[:, :, a] = (u(pts + e) - u(pts - e)) / (2 * h)
    return float(np.linalg.det(J + np.eye(3)).min())


def eval_deformed(args):
    label_names = {20: "L1", 21: "L2", 22: "L3", 23: "L4", 24: "L5"}
    given = read_landmarks(DATA / "verse004" / "landmarks" / f"{label_names[args.label]}.fcsv")
    keep = list(range(len(given)))
    if args.landmarks < len(given):
        keep = list(farthest_points(given.points_world, args.landmarks, 0))
    given = LandmarkSet(tuple(given.names[i] for i in keep), given.points_world[keep], given.source)
    rng = np.random.default_rng(args.seed + 1)
    cache = Path(tempfile.gettempdir()) / f"ssm-deformed-{args.label}-{args.n}-{args.seed}"
    cache.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        names, files, maps = deformed_population(args.n, args.label, args.seed, cache)
        specs = []
        for i, (name, f, u) in enumerate(zip(names, files, maps)):
            lm = None
            if i < args.on:
                pts = given.points_world + u(given.points_world)
                if i > 0 or args.jitter_template:
                    pts = pts + rng.normal(scale=args.jitter, size=pts.shape)
                lm = Path(tmp) / f"{name}.fcsv"
                write_landmarks(lm, LandmarkSet(given.names, pts, name))
            specs.append(InstanceSpec(name=name, volume=f, label=1, landmarks=lm,
                                      landmark_set=read_landmarks(lm) if lm else None))
        study, template_points, seconds = run_study(specs, names[0], args.method, args.iterations, args.jobs)
    p0 = study.frame(names[0]).to_world(template_points)
    got = {n: study.frame(n).to_world(study.coatings[n].points_object) for n in names}
    errors = {n: np.linalg.norm(got[n] - (p0 + u(p0)), axis=1) for n, u in zip(names, maps)}
    # consensus: every coating pulled back through its inverse deformation, averaged
    pulled = np.mean([invert(u, got[n]) for n, u in zip(names, maps)], axis=0)
    consensus = {n: np.linalg.norm(got[n] - (pulled + u(pulled)), axis=1) for n, u in zip(names, maps)}
    for name in names:
        e = errors[name]
        print(f"  {name}: mean {e.mean():.2f}, 95th {np.percentile(e, 95):.2f}, worst {e.max():.1f} mm, "
              f"folds {study.coatings[name].fit.folded_after}")
    label = (f"deformed-{label_names[args.label]} n={args.n} {args.method} landmarks={len(given)} "
             f"on={min(args.on, args.n)} jitter={args.jitter} ({seconds:.0f} s)")
    summarise(errors, label + " against the template's points")
    summarise(consensus, label + " against the consensus")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("population", choices=("femur10", "deformed"))
    ap.add_argument("--landmarks", type=int, default=15)
    ap.add_argument("--on", type=int, default=1000, help="landmarks on the first ON instances only")
    ap.add_argument("--jitter", type=float, default=0.0, help="landmark jitter per axis, mm (not the template's)")
    ap.add_argument("--jitter-template", action="store_true")
    ap.add_argument("--method", default="landmarks", choices=("landmarks", "model"))
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--label", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--landmark-weight", type=float, default=None)
    ap.add_argument("--exact-landmarks", action="store_true",
                    help="[correspondence] exact_landmarks = true (the model method keeps given landmarks)")
    args = ap.parse_args(argv)
    LANDMARK_WEIGHT[0] = args.landmark_weight
    EXACT_LANDMARKS[0] = args.exact_landmarks
    if args.population == "femur10":
        eval_femur(args)
    else:
        eval_deformed(args)


if __name__ == "__main__":
    main()
