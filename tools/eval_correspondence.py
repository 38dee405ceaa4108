"""Correspondence error against known truth: where the coating puts the template's points.

Populations with known dense correspondence:

* a folder of closed meshes sharing one connectivity (every file has the same vertex
  count and the identical face list, so vertex i is the same place on every instance):
  ``femur10`` (ten real femurs, ``../shared/data/femur10``), ``knee30-femur``,
  ``knee30-tibia``, ``knee30-patella`` (``../shared/data/knee30``), or any
  ``folder:PATH[:GLOB]``;
* ``deformed``: the verse004 vertebra L1 (or ``--label``) deformed by known smooth,
  invertible deformations (sums of Gaussian displacement bumps at several spatial
  scales, each kept below the fold limit), so every surface point's true place on
  every instance is known.

The template's points lie on its instance's surface; their true place on instance k is
the same surface point mapped by the known correspondence (the shared triangles; the
deformation). The error of a point is its distance, in world mm, from that true place:
not a surface distance. Landmarks are farthest-point samples of the template instance's
vertices at their true places on every instance (``--jitter`` adds Gaussian noise per
axis, not on the template instance); ``--on K`` puts them on the first K instances only.

Each run prints mean, 95th percentile and max (mm), the seconds, and the build's own
correspondence self-check (the landmark transfer error, ``ssm_addon.fitting``) with its
rank correlation against the true error across instances. ``--suite`` runs the issue's
matrix (single pass and model method at 15 and 6 landmarks, 15 jittered by 1.5 mm, and
the model method with landmarks on 3 instances) and prints one table; ``--json FILE``
appends every run's figures as JSON lines. ``--fit-projection`` also measures, for a
folder of meshes, the leave-one-out fit's points as correspondence: each non-template
instance's coating replaced by the model of the others fitted to it, projected onto the
coating's surface (and halfway between the two), against the truth.

Usage::

    python tools/eval_correspondence.py femur10 [--landmarks 15] [--on 10] [--jitter 0]
        [--method landmarks|model] [--landmark-noise MM] [--iterations 3] [--jobs 2]
    python tools/eval_correspondence.py knee30-tibia --suite --json runs.jsonl
    python tools/eval_correspondence.py folder:/data/femurs:*.ply --landmarks 6
    python tools/eval_correspondence.py deformed [--n 20] ...
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import ssm_addon.correspondence.rounds as corr  # noqa: E402
from ssm_addon.base import params as P  # noqa: E402
from ssm_addon.base.errors import InputError  # noqa: E402
from ssm_addon.base.params import TEMPLATE_CHOICES, CorrespondenceParams  # noqa: E402
from ssm_addon.formats.landmarks import LandmarkSet, read_landmarks, write_landmarks  # noqa: E402
from ssm_addon.formats.meshes import read_mesh  # noqa: E402
from ssm_addon.instances.importing import InstanceSpec  # noqa: E402
from ssm_addon.pipeline.runner import run  # noqa: E402
from ssm_addon.pipeline.study import Study  # noqa: E402

DATA = Path(os.environ.get("SSM_SHARED_DATA") or ROOT.parent / "shared" / "data")
MESH_SETS = {"femur10": ("femur10", "femur*.ply"), "knee30-femur": ("knee30", "*_Femur.ply"),
             "knee30-tibia": ("knee30", "*_Tibia.ply"), "knee30-patella": ("knee30", "*_Patella.ply")}


def farthest_points(points: np.ndarray, k: int, start: int) -> np.ndarray:
    """Indices of ``k`` farthest-point samples of ``points`` from ``start``."""
    chosen = [start]
    d = np.linalg.norm(points - points[start], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(points - points[i], axis=1))
    return np.array(chosen)


def mesh_population(population: str):
    """(files, [(vertices, faces)]) of a folder of meshes sharing one connectivity."""
    if population.startswith("folder:"):
        _, folder, *pattern = population.split(":")
        folder, pattern = Path(folder), (pattern[0] if pattern else "*.ply")
    else:
        sub, pattern = MESH_SETS[population]
        folder = DATA / sub
    files = sorted(folder.glob(pattern))
    if len(files) < 3:
        raise SystemExit(f"{population}: fewer than 3 meshes {pattern} under {folder}")
    meshes = [read_mesh(f) for f in files]
    f0 = meshes[0][1]
    for f, (v, faces) in zip(files, meshes):
        if len(v) != len(meshes[0][0]) or faces.shape != f0.shape or not np.array_equal(faces, f0):
            raise SystemExit(f"{f}: not the connectivity of {files[0].name} (the truth needs shared vertices)")
    return files, meshes


def random_pose(rng: np.random.Generator, shift_mm: float = 200.0) -> tuple[np.ndarray, np.ndarray]:
    """A rotation drawn uniformly from the rotation group (any axis, any angle up to 180°) and a
    shift (mm, per axis)."""
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return rot, rng.uniform(-shift_mm, shift_mm, size=3)


def scanner_poses(files, meshes, seed: int, folder: Path):
    """Each mesh moved by its own :func:`random_pose` and written as a 3D Slicer PLY (LPS, says so)
    into ``folder``; the moved vertices are the truth's (shared faces). Returns (files, meshes)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from foreign_data import slicer_ply

    rng = np.random.default_rng(seed)
    out_files, out_meshes = [], []
    for f, (v, faces) in zip(files, meshes):
        rot, shift = random_pose(rng)
        moved = v @ rot.T + shift
        out_files.append(slicer_ply(folder / f.name, moved, faces))
        out_meshes.append((moved, faces))
    return out_files, out_meshes


def mirror_half(files, meshes, folder: Path):
    """Every second mesh (the 2nd, 4th, ...) mirrored through the world's x = 0 plane (left <-> right),
    its triangles turned to face outwards, written into ``folder``; the mirrored vertices are the
    truth's (the same vertex order). Returns (files, meshes)."""
    from ssm_addon.formats.meshes import write_ply

    out_files, out_meshes = [], []
    for i, (f, (v, faces)) in enumerate(zip(files, meshes)):
        if i % 2:
            v, faces = v * np.array([-1.0, 1.0, 1.0]), faces[:, ::-1]
            f = folder / f"{f.stem}_mirrored.ply"
            write_ply(f, v, faces, space="RAS")
        out_files.append(f)
        out_meshes.append((v, faces))
    return out_files, out_meshes


def self_check(study) -> dict:
    """The build's own correspondence check per instance (mm), if it made one."""
    check = getattr(study, "correspondence_check", None)
    return dict(check.instance_mm) if check is not None else {}


def loo_reconstruction(study) -> dict:
    """Each instance's coated points against the model of the others (every mode), mean mm:
    the leave-one-out reconstruction error (paper 6's generalization, per instance)."""
    names = list(study.names)
    P = np.stack([study.coatings[n].points_object for n in names]).reshape(len(names), -1)
    out = {}
    for k, n in enumerate(names):
        others = np.delete(P, k, axis=0)
        mu = others.mean(axis=0)
        _u, _s, vt = np.linalg.svd(others - mu, full_matrices=False)
        r = P[k] - mu
        r = r - vt.T @ (vt @ r)
        out[n] = float(np.linalg.norm(r.reshape(-1, 3), axis=1).mean())
    return out


def rank_correlation(true: dict, check: dict, skip: str) -> float:
    from scipy.stats import spearmanr

    names = [n for n in true if n in check and n != skip]
    if len(names) < 3:
        return float("nan")
    return float(spearmanr([true[n] for n in names], [check[n] for n in names])[0])


def truth_errors(study, truth: dict):
    """A function of coated points (object frames, by instance) -> their distances (mm, world)
    from ``truth`` (the template points' true places on each instance, world mm)."""
    def error_of(points: dict) -> dict:
        return {n: np.linalg.norm(study.frame(n).to_world(points[n]) - truth[n], axis=1) for n in truth if n in points}

    return error_of


def report_run(label: str, errors: dict, study, seconds: float, args, error_of=None) -> dict:
    allv = np.concatenate(list(errors.values()))
    truth_rounds = []
    if error_of is not None:
        for r, state in zip(getattr(study, "correspondence_rounds", ()), ROUND_STATES):
            if len(next(iter(state.values()))) != len(next(iter(errors.values()))):
                print(f"  round {r.round}: of the template before its refinement (another point count), not scored")
                continue
            e = np.concatenate(list(error_of(state).values()))
            noise = r.landmark_noise
            truth_rounds.append({"round": r.round, "kept": r.kept, "true_mean_mm": float(e.mean()),
                                 "true_p95_mm": float(np.percentile(e, 95)),
                                 "transfer_before_mm": r.transfer_before_mm, "transfer_after_mm": r.transfer_after_mm,
                                 "click_mm": noise.click_mm, "model_mm": noise.model_mm, "shrink": noise.shrink})
            print(f"  round {r.round} ({'kept' if r.kept else 'dropped'}): true error {e.mean():.3f} / "
                  f"{np.percentile(e, 95):.2f} mm (start {allv.mean() if not r.kept else float('nan'):.3f}); "
                  f"transfer {r.transfer_before_mm:.3f} -> {r.transfer_after_mm:.3f} mm; landmarks "
                  f"{noise.click_mm:.2f} mm off (model {noise.model_mm:.2f}), moved {noise.shrink:.0%}")
    before = {}
    if error_of is not None and BEFORE_OPTIMISATION:
        b = np.concatenate(list(error_of(BEFORE_OPTIMISATION).values()))
        opt = study.optimisation
        before = {"mean_mm": float(b.mean()), "p95_mm": float(np.percentile(b, 95)), "max_mm": float(b.max()),
                  "optimisation_seconds": study.timings_s.get("optimisation"), "iterations": opt.iterations,
                  "stop": opt.stop}
        print(f"  before the optimisation: {b.mean():.3f} / {np.percentile(b, 95):.2f} / {b.max():.1f} mm; "
              f"optimisation {opt.iterations} iteration(s), {opt.stop}, {before['optimisation_seconds']:.1f} s")
    per = {n: float(e.mean()) for n, e in errors.items()}
    check = self_check(study)
    rho = rank_correlation(per, check, study.template_instance)
    recon = loo_reconstruction(study)
    rho_recon = rank_correlation(per, recon, study.template_instance)
    for name, e in errors.items():
        c = (f", self-check {check[name]:.2f}" if name in check else "") + f", reconstruction {recon[name]:.2f}"
        print(f"  {name}: mean {e.mean():.2f}, 95th {np.percentile(e, 95):.2f}, worst {e.max():.1f} mm, "
              f"folds {study.coatings[name].fit.folded_after}{c}")
    rounds = [(r.round, r.kept) for r in getattr(study, "correspondence_rounds", ()) if hasattr(r, "kept")]
    stop = getattr(getattr(study, "correspondence_check", None), "stop", "")
    row = {"population": args.population, "pose_seed": getattr(args, "pose_seed", None), "method": args.method, "landmarks": args.landmarks, "on": args.on,
           "jitter": args.jitter, "landmark_noise": args.landmark_noise, "optimise": OPTIMISE[0] or {},
           "mean_mm": float(allv.mean()),
           "p95_mm": float(np.percentile(allv, 95)), "max_mm": float(allv.max()), "seconds": seconds,
           "self_check_mm": float(np.mean(list(check.values()))) if check else None, "rank_correlation": rho,
           "rounds": rounds, "truth_rounds": truth_rounds, "stop": stop, "reconstruction_mm": float(np.mean(list(recon.values()))),
           "rank_correlation_reconstruction": rho_recon, "before_optimisation": before, "coating": list(getattr(args, "coating", []) or []),
           "folded_after": int(sum(c.fit.folded_after for c in study.coatings.values())),
           "not_converged": int(sum(not c.fit.converged for c in study.coatings.values()))}
    print(f"{label}: mean {row['mean_mm']:.3f} mm, 95th {row['p95_mm']:.2f} mm, worst {row['max_mm']:.1f} mm "
          f"({seconds:.0f} s; self-check {row['self_check_mm'] or float('nan'):.2f} mm, rank correlation "
          f"{rho:.2f}; leave-one-out reconstruction {row['reconstruction_mm']:.2f} mm, rank correlation "
          f"{rho_recon:.2f}; {stop or 'single pass'})", flush=True)
    if args.json:
        import json

        with open(args.json, "a") as fh:
            fh.write(json.dumps(row) + "\n")
    return row


def eval_meshes(args) -> dict:
    from ssm_addon.meshutil import MeshLocation, MeshLocator

    files, meshes = mesh_population(args.population)
    if args.template_instance:  # that instance first: the template's (and the landmarks' first) instance
        stems = [f.stem for f in files]
        if args.template_instance not in stems:
            raise SystemExit(f"--template-instance {args.template_instance}: not one of {', '.join(stems)}")
        first = stems.index(args.template_instance)
        files, meshes = files[first:] + files[:first], meshes[first:] + meshes[:first]
    names = [f.stem for f in files]
    v0, f0 = meshes[0]
    lm_idx = farthest_points(v0, max(args.landmarks, 1), int(np.argmax(v0[:, 2])))
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as tmp:
        if args.mirror_half:  # every second instance (not the template's) its own mirror image: a right bone
            files, meshes = mirror_half(files, meshes, Path(tmp))
        if args.pose_seed is not None:  # every mesh in a random scanner pose, as 3D Slicer writes it (LPS PLY)
            files, meshes = scanner_poses(files, meshes, args.pose_seed, Path(tmp))
        specs = []
        for i, (name, f, (v, _f)) in enumerate(zip(names, files, meshes)):
            lm = None
            if i < args.on and args.landmarks > 0:
                pts = v[lm_idx] + rng.normal(scale=args.jitter, size=(len(lm_idx), 3)) * (i > 0 or args.jitter_template)
                lm = Path(tmp) / f"{name}.csv"
                write_landmarks(lm, LandmarkSet(tuple(f"L{j:02d}" for j in range(len(lm_idx))), pts, name))
            specs.append(InstanceSpec(name=name, mesh_path=f, landmarks_path=lm, landmarks=read_landmarks(lm) if lm else None))
        study, template_points, seconds = run_study(specs, names[0], args.method, args.iterations, args.jobs)
    # point i of every coating is template point i, which lies on the template instance's
    # surface: its true place on instance k is the same place of k's mesh (shared faces)
    t = names.index(study.template_instance)  # the model method may build its template from another instance
    _c, _d, tri, bary = MeshLocator(meshes[t][0], f0).query(study.frame(names[t]).to_world(template_points), k=12)
    loc = MeshLocation(tri, bary)
    error_of = truth_errors(study, {n: loc.evaluate(v, f0) for n, (v, _f) in zip(names, meshes)})
    errors = error_of({n: study.coatings[n].points_object for n in names})
    label = (f"{args.population} {args.method} landmarks={args.landmarks} on={min(args.on, len(names))} "
             f"jitter={args.jitter}" + (f" poses={args.pose_seed}" if args.pose_seed is not None else ""))
    if args.fit_projection:
        fit_projection(study, names, error_of)
    return report_run(label, errors, study, seconds, args, error_of)


def fit_projection(study, names, error_of) -> dict:
    """True error (mean mm over the non-template instances) of the coatings, of the
    leave-one-out fit's points projected onto each coating's surface, and of the point
    halfway between fit and coating projected likewise. The fit is the model method's own
    (:func:`ssm_addon.correspondence.rounds.landmark_transfer`, the build's fit params)."""
    from ssm_addon.meshutil import MeshLocator

    faces = np.asarray(study.template.faces)
    locations = study.template.landmark_locations
    fit = corr.correspondence_fit_params(study.params.correspondence)
    P = np.stack([study.coatings[n].points_object for n in names])
    found = {"coating": {}, "fit projected": {}, "halfway projected": {}}
    for i, n in enumerate(names):
        if n == study.template_instance:
            continue
        result, _predicted, _d = corr.landmark_transfer(np.delete(P, i, axis=0), faces, P[i], locations, {}, fit=fit)
        locator = MeshLocator(P[i], faces)
        found["coating"][n] = P[i]
        found["fit projected"][n] = locator.query(result.points, k=12)[0]
        found["halfway projected"][n] = locator.query(0.5 * (result.points + P[i]), k=12)[0]
    out = {what: float(np.mean([e.mean() for e in error_of(points).values()])) for what, points in found.items()}
    print("  leave-one-out fit as correspondence: " + ", ".join(f"{k} {v:.3f} mm" for k, v in out.items()), flush=True)
    return out


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


def deformations(n: int, seed: int, points_world: np.ndarray) -> list:
    """The ``n`` displacements of :func:`deformed_population` (the first zero) for a shape whose
    voxel centres are ``points_world`` (world mm): each scaled down until det(I + du/dx) >= 0.4
    over the points, so it stays invertible with a margin."""
    pts = np.asarray(points_world, float)
    centre, size = pts.mean(axis=0), float(np.ptp(pts, axis=0).max())
    rng = np.random.default_rng(seed)
    maps = []
    for k in range(n):
        if k == 0:
            maps.append(lambda x: np.zeros_like(np.asarray(x, float)))
            continue
        amplitude = 0.35
        u = deformation_field(rng, centre, size, amplitude=amplitude)
        while jacobian_min(u, pts[::5]) < 0.4:
            amplitude *= 0.7
            u = deformation_field(rng, centre, size, amplitude=amplitude)
        maps.append(u)
    return maps


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
    grid = np.stack(np.meshgrid(*[np.arange(s) for s in sub.shape], indexing="ij"), -1).reshape(-1, 3)
    world = grid @ affine[:3, :3].T + affine[:3, 3]
    from scipy.ndimage import map_coordinates

    inv_aff = np.linalg.inv(affine)
    names, files, maps = [], [], []
    for k, u in enumerate(deformations(n, seed, pts)):
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
ROUND_TEMPLATE = [None]
TEMPLATE_CHOICE = [None]
ROUND_STATES: list = []  # the model method's re-sampled coatings of every round (object frames)
LANDMARK_NOISE = [None]
COATING = [None]  # the [coating] parameters, with the --coating-* options given
TEMPLATE = [{}]  # the [template] keys given with --template-*
OPTIMISE = [None]  # the correspondence optimisation's [correspondence] keys, with --optimise
BEFORE_OPTIMISATION: dict = {}  # the coatings the optimisation started from (object frames)


def run_study(specs, template_name: str, method: str, iterations: int, jobs: int, spacing: float | None = None):
    study = Study(instances=specs, template_instance=template_name)
    if spacing or TEMPLATE[0]:
        table = {**P.to_table(study.params.template), **TEMPLATE[0], **({"spacing": spacing} if spacing else {})}
        study.params = study.params.replace(template=P.from_table(P.TemplateParams, table, where="--template-*"))
    extra = {} if LANDMARK_WEIGHT[0] is None else {"landmark_weight": LANDMARK_WEIGHT[0]}
    if ROUND_TEMPLATE[0] is not None:
        extra["round_template"] = ROUND_TEMPLATE[0]
    if LANDMARK_NOISE[0] is not None:
        extra["landmark_noise_mm"] = LANDMARK_NOISE[0]
    if TEMPLATE_CHOICE[0] is not None:
        extra["template_choice"] = TEMPLATE_CHOICE[0]
    extra.update(OPTIMISE[0] or {})
    study.params = study.params.replace(correspondence=CorrespondenceParams(method=method, iterations=iterations, **extra))
    if COATING[0] is not None:
        study.params = study.params.replace(coating=COATING[0])
    t0 = time.perf_counter()
    say = lambda m: print("  " + m, flush=True)  # noqa: E731
    ROUND_STATES.clear()
    real = corr._finish_round

    def spy(study_, names, points, resampled, *args, **kwargs):  # every round's re-sampled coatings, for the truth
        ROUND_STATES.append({n: c.points_object.copy() for n, c in zip(names, resampled)})
        return real(study_, names, points, resampled, *args, **kwargs)

    corr._finish_round = spy
    run(study, stages=("import", "template"), jobs=jobs, log=say)
    template_points = study.template.points_object.copy()
    run(study, stages=("coating",), jobs=jobs, log=say)
    BEFORE_OPTIMISATION.clear()
    if study.params.correspondence.optimise:  # the coatings before, for the truth of both in one run
        BEFORE_OPTIMISATION.update({n: c.points_object.copy() for n, c in study.coatings.items()})
        run(study, stages=("optimisation",), jobs=jobs, log=say)
    if not study.template.is_mean_shape:  # the template's own points (another instance's, when the medoid's)
        template_points = study.template.points_object.copy()
    elif len(template_points) != len(study.template.points_object):  # the model method's template refined where
        # coatings cut off parts ([template] refine_where_cut_off): its instance's coating stands for its points
        template_points = study.coatings[study.template_instance].points_object.copy()
    return study, template_points, time.perf_counter() - t0


def scanner_pose_volumes(files, maps, seed: int, folder: Path):
    """Each label map's affine moved by its own :func:`random_pose` (written into ``folder``), and
    each known displacement composed with it: x -> T(x + u(x)) - x, world mm. Returns (files,
    maps, poses as (rotation, shift))."""
    import nibabel as nib

    rng = np.random.default_rng(seed)
    out_files, out_maps, poses = [], [], []
    for f, u in zip(files, maps):
        rot, shift = random_pose(rng)
        img = nib.load(str(f))
        move = np.eye(4)
        move[:3, :3], move[:3, 3] = rot, shift
        path = folder / Path(f).name
        nib.save(nib.Nifti1Image(np.asarray(img.dataobj), move @ img.affine), str(path))
        out_files.append(path)
        out_maps.append(lambda x, u=u, rot=rot, shift=shift: (np.asarray(x, float) + u(x)) @ rot.T + shift - x)
        poses.append((rot, shift))
    return out_files, out_maps, poses


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
        unmoved, poses = list(maps), [(np.eye(3), np.zeros(3))] * len(maps)
        if args.pose_seed is not None:  # each label map in a random scanner pose (its affine moved)
            files, maps, poses = scanner_pose_volumes(files, maps, args.pose_seed, Path(tmp))
        specs = []
        for i, (name, f, u) in enumerate(zip(names, files, maps)):
            lm = None
            if i < args.on and args.landmarks > 0:
                pts = given.points_world + u(given.points_world)
                if i > 0 or args.jitter_template:
                    pts = pts + rng.normal(scale=args.jitter, size=pts.shape)
                lm = Path(tmp) / f"{name}.fcsv"
                write_landmarks(lm, LandmarkSet(given.names, pts, name))
            specs.append(InstanceSpec(name=name, volume_path=f, label=1, landmarks_path=lm,
                                      landmarks=read_landmarks(lm) if lm else None))
        study, template_points, seconds = run_study(specs, names[0], args.method, args.iterations, args.jobs)
    t = names.index(study.template_instance)  # the model method may build its template from another instance
    rot, shift = poses[t]  # the template's points, undeformed and unmoved
    p0 = invert(unmoved[t], (study.frame(names[t]).to_world(template_points) - shift) @ rot)
    error_of = truth_errors(study, {n: p0 + u(p0) for n, u in zip(names, maps)})
    errors = error_of({n: study.coatings[n].points_object for n in names})
    label = (f"deformed-{label_names[args.label]} n={args.n} {args.method} landmarks={len(given) if args.landmarks else 0} "
             f"on={min(args.on, args.n)} jitter={args.jitter}" + (f" poses={args.pose_seed}" if args.pose_seed is not None else ""))
    return report_run(label, errors, study, seconds, args, error_of)


SUITE = (("landmarks", 15, 1000, 0.0), ("model", 15, 1000, 0.0), ("landmarks", 6, 1000, 0.0), ("model", 6, 1000, 0.0),
         ("landmarks", 15, 1000, 1.5), ("model", 15, 1000, 1.5), ("model", 15, 3, 0.0))


def evaluate(args) -> dict:
    return eval_deformed(args) if args.population == "deformed" else eval_meshes(args)


def suite(args) -> None:
    """The issue's matrix on one population, one table at the end."""
    rows = []
    for method, landmarks, on, jitter in SUITE:
        rows.append(evaluate(replace_args(args, method=method, landmarks=landmarks, on=on, jitter=jitter)))
    print(f"\n{args.population}: method, landmarks, on, jitter -> mean / p95 / max mm, seconds, self-check, rho")
    for r in rows:
        on = "all" if r["on"] >= 1000 else r["on"]
        print(f"  {r['method']:9s} {r['landmarks']:3d} on {on:>3} jitter {r['jitter']:.1f}: {r['mean_mm']:.3f} / "
              f"{r['p95_mm']:.2f} / {r['max_mm']:.1f}  {r['seconds']:5.0f} s  check {r['self_check_mm'] or float('nan'):.2f}"
              f"  rho {r['rank_correlation']:.2f}  recon {r['reconstruction_mm']:.2f} rho {r['rank_correlation_reconstruction']:.2f}"
              f"  {r['stop']}")


def replace_args(args, **changes):
    out = argparse.Namespace(**vars(args))
    for k, v in changes.items():
        setattr(out, k, v)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("population", help="femur10, knee30-femur, knee30-tibia, knee30-patella, deformed or "
                                       "folder:PATH[:GLOB]")
    ap.add_argument("--landmarks", type=int, default=15)
    ap.add_argument("--on", type=int, default=1000, help="landmarks on the first ON instances only")
    ap.add_argument("--jitter", type=float, default=0.0, help="landmark jitter per axis, mm (not the template's)")
    ap.add_argument("--jitter-template", action="store_true")
    ap.add_argument("--method", default="landmarks", choices=("landmarks", "model"))
    ap.add_argument("--iterations", type=int, default=3)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--n", type=int, default=20)
    ap.add_argument("--template-instance", default=None,
                    help="the instance (file stem) whose template is coated onto the others (default: the first)")
    ap.add_argument("--label", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--pose-seed", type=int, default=None,
                    help="put every instance into a random scanner pose (any axis, 0-180 degrees; meshes written "
                         "as 3D Slicer LPS PLY, label maps with their affine moved), drawn from this seed")
    ap.add_argument("--mirror-half", action="store_true",
                    help="every second mesh mirrored left <-> right (a mixed-side set; meshes only)")
    ap.add_argument("--landmark-weight", type=float, default=None)
    ap.add_argument("--landmark-noise", type=float, default=None,
                    help="[correspondence] landmark_noise_mm (default: estimated; 0: exact landmarks)")
    ap.add_argument("--round-template", choices=("instance", "mean"), default=None,
                    help="[correspondence] round_template (default: the method's default)")
    ap.add_argument("--template-choice", choices=TEMPLATE_CHOICES, default=None,
                    help="[correspondence] template_choice (default: the method's default)")
    ap.add_argument("--suite", action="store_true", help="the issue's matrix of settings, one table")
    ap.add_argument("--fit-projection", action="store_true",
                    help="also measure the leave-one-out fit's points as correspondence (folders of meshes)")
    ap.add_argument("--json", default=None, help="append each run's figures to this JSON-lines file")
    ap.add_argument("--optimise", action=argparse.BooleanOptionalAction, default=None,
                    help="the correspondence optimisation after the coating ([correspondence] optimise; default: "
                         "the parameter's default); the truth is measured before and after it")
    ap.add_argument("--population-weight", type=float, default=None, help="[correspondence] population_weight")
    ap.add_argument("--landmark-hold", type=float, default=None, help="[correspondence] landmark_hold")
    ap.add_argument("--min-variance", type=float, default=None, help="[correspondence] min_variance")
    ap.add_argument("--optimise-iterations", type=int, default=None, help="[correspondence] optimise_iterations")
    ap.add_argument("--optimise-tolerance-mm", type=float, default=None,
                    help="[correspondence] optimise_tolerance_mm")
    P.add_arguments(ap.add_argument_group("[coating] values other than the defaults (as ssm build takes them)"),
                    P.CoatingParams, prefix="coating")
    P.add_arguments(ap.add_argument_group("[template] values other than the defaults (as ssm build takes them)"),
                    P.TemplateParams, prefix="template")
    args = ap.parse_args(argv)
    if args.population not in MESH_SETS and args.population != "deformed" and not args.population.startswith("folder:"):
        ap.error(f"unknown population {args.population!r}")
    LANDMARK_WEIGHT[0] = args.landmark_weight
    ROUND_TEMPLATE[0] = args.round_template
    TEMPLATE_CHOICE[0] = args.template_choice
    LANDMARK_NOISE[0] = args.landmark_noise
    OPTIMISE[0] = {k: getattr(args, k) for k in ("optimise",
        "population_weight", "landmark_hold", "min_variance", "optimise_iterations", "optimise_tolerance_mm") if getattr(args, k) is not None}
    try:
        COATING[0] = P.from_arguments(args, P.CoatingParams, prefix="coating")
    except InputError as err:
        ap.error(str(err))
    try:
        TEMPLATE[0] = P.to_table(P.from_arguments(args, P.TemplateParams, prefix="template"), only_changed=True)
    except InputError as err:
        ap.error(str(err))
    args.coating = [f"{k}={v}" for k, v in P.to_table(COATING[0], only_changed=True).items()]  # the JSON rows'
    if args.suite:
        suite(args)
    else:
        evaluate(args)


if __name__ == "__main__":
    main()
