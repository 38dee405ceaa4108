"""Benchmark of the model stage: build, metrics, files and the Blender model object.

Usage: ``.venv/bin/python tools/bench_model.py [--n 31 1000] [--points 5000] [--no-blender]``

Synthetic populations (a sphere of N points + 10 smooth displacement fields with
decreasing variances + 0.02 mm noise) of n instances. Per step: wall time and peak
memory as the growth of the process's resident set over the step (sampled every 5 ms;
it includes Blender's own allocations; memory the allocator reuses is not counted again).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def population(n: int, n_points: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    i = np.arange(n_points) + 0.5
    phi = np.arccos(1 - 2 * i / n_points)
    theta = np.pi * (1 + 5**0.5) * i
    unit = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)
    mean = 20.0 * unit
    fields = []
    for a in range(10):  # smooth fields: low-order polynomials of the unit vector times axes
        f = np.zeros_like(mean)
        f[:, a % 3] = unit[:, (a + 1) % 3] ** (1 + a // 3) + 0.3 * unit[:, a % 3]
        fields.append(f.ravel())
    q, _ = np.linalg.qr(np.stack(fields, axis=1))
    sd = 6.0 * 0.6 ** np.arange(10)
    b = rng.standard_normal((n, 10)) * sd
    shapes = mean.ravel()[None] + b @ q.T
    shapes += 0.02 * rng.standard_normal(shapes.shape)
    return shapes.reshape(n, n_points, 3)


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def step(label: str, fn, *args, **kwargs):
    """Run ``fn`` timing it; peak memory = max resident set growth sampled every 5 ms."""
    base = _rss_bytes()
    peak = [base]
    done = threading.Event()

    def sample():
        while not done.is_set():
            peak[0] = max(peak[0], _rss_bytes())
            done.wait(0.005)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    dt = time.perf_counter() - t0
    done.set()
    thread.join()
    peak[0] = max(peak[0], _rss_bytes())
    print(f"  {label:<44s} {dt:8.2f} s   peak +{(peak[0] - base) / 1e6:8.1f} MB RSS", flush=True)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, nargs="+", default=[31, 1000])
    ap.add_argument("--points", type=int, default=5000)
    ap.add_argument("--no-blender", action="store_true")
    ap.add_argument("--samples", type=int, default=300, help="specificity samples")
    args = ap.parse_args(argv)

    # matplotlib first, so its font cache lives in the real home (conftest moves HOME)
    import matplotlib.font_manager  # noqa: F401

    from ssm_addon.model import metrics
    from ssm_addon.model.files import load_npz, save_npz, save_statismo
    from ssm_addon.model.pca import build_model

    bpy = None
    if not args.no_blender:
        try:
            import conftest  # sets a temporary HOME for Blender before bpy is imported

            pkg = conftest.load_extension_package()
            import bpy  # noqa: F811

            pkg.register()
            from ssm.operators import model as opmodel
        except ImportError as err:
            print(f"(no Blender: {err})")
            bpy = None

    faces = np.array([[0, 1, 2]])
    for n in args.n:
        print(f"n = {n} instances x N = {args.points} points (3N = {3 * args.points})", flush=True)
        x = population(n, args.points)
        names = [f"i{i:04d}" for i in range(n)]
        model = step("build_model (Gram, eq. 4-6)", build_model, x, faces, names)
        print(f"    {model.n_modes} modes; first 10 carry {100 * model.variability_concentration()[9]:.2f} %")
        step("compactness", metrics.compactness, model)
        ks = list(range(1, 21))
        g = step("generalization k=1..20", metrics.generalization, x, ks=ks)
        print(f"    {g['method']}: G(10) = {g['mean_mm'][9]:.4f} ± {g['std_mm'][9]:.4f} mm")
        s = step(f"specificity k=1..20 ({args.samples} samples)", metrics.specificity, model, ks=ks, n_samples=args.samples)
        print(f"    S(10) = {s['mean_mm'][9]:.3f} ± {s['std_mm'][9]:.3f} mm")
        with tempfile.TemporaryDirectory() as tmp:
            step("save_npz", save_npz, model, Path(tmp) / "model.npz")
            step("load_npz", load_npz, Path(tmp) / "model.npz")
            step("save_statismo", save_statismo, model, Path(tmp) / "model.h5")
            print(f"    model.npz {Path(tmp, 'model.npz').stat().st_size / 1e6:.1f} MB, model.h5 {Path(tmp, 'model.h5').stat().st_size / 1e6:.1f} MB")
            step("plots (fig. 9)", metrics.write_plots, model, tmp)
        if bpy is not None:
            bpy.ops.wm.read_homefile(use_empty=True)
            obj = step(f"Blender model object ({model.n_modes} shape keys)", opmodel.create_model_object, bpy.context, model)
            print(f"    process max RSS so far {rss_mb():.0f} MB")
            step("model_from_object", opmodel.model_from_object, obj)
        del model, x
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
