"""Benchmark the surface stage (paper 3.1–3.2): time and peak memory per step.

Usage: ``.venv/bin/python tools/bench_surface.py [--repeat N]``

Cases: a voxel sphere of radius 30, and VerSe L1 (label 20) resampled into its
object frame at 1 mm and 0.5 mm (``ssm_addon.instances.volume.load_object``; skipped when the
data in ``../shared/data/verse004`` or ``$SSM_SHARED_DATA/verse004`` is absent).
Radii follow the defaults in mm (normal sphere 5 mm, patch 7 mm) divided by the
spacing. Peak memory is the ``tracemalloc`` peak of the step (numpy arrays included).
Timings are the best of ``--repeat`` runs (default 3): the machine is shared.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_addon import surface  # noqa: E402
from ssm_addon.instances import importing as INS  # noqa: E402

NORMAL_RADIUS_MM = 5.0
PATCH_RADIUS_MM = 7.0


def shared_data_dir() -> Path:
    env = os.environ.get("SSM_SHARED_DATA")
    return Path(env) if env else ROOT.parent / "shared" / "data"


def sphere_mask(radius: float) -> np.ndarray:
    n = int(2 * radius + 8)
    centre = n / 2 + np.array([0.3, 0.17, 0.41])
    g = np.indices((n, n, n), dtype=np.float32)
    return ((g - centre[:, None, None, None].astype(np.float32)) ** 2).sum(0) <= radius * radius


def measure(fn, repeat):
    best = np.inf
    result = None
    tracemalloc.start()
    tracemalloc.reset_peak()
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - t0)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return result, best, peak / 2**20


def bench(name: str, mask: np.ndarray, spacing_mm: float, repeat: int) -> None:
    nr = NORMAL_RADIUS_MM / spacing_mm
    pr = PATCH_RADIUS_MM / spacing_mm
    print(f"\n{name}: mask {mask.shape}, {int(mask.sum())} voxels, normal radius {nr:g} vox, patch radius {pr:g} vox")
    rows = []
    vox, t, mem = measure(lambda: surface.surface_voxels(mask), repeat)
    rows.append(("surface_voxels", t, mem))
    _, t, mem = measure(lambda: surface.surface_graph(vox), repeat)
    rows.append(("surface_graph", t, mem))
    normals, t, mem = measure(lambda: surface.surface_normals(mask, vox, nr), repeat)
    rows.append(("surface_normals", t, mem))
    curv, t, mem = measure(lambda: surface.surface_curvature(mask, vox, normals, pr, normal_radius_vox=nr), repeat)
    rows.append(("surface_curvature (incl. sub-voxel points)", t, mem))
    geo, t, mem = measure(lambda: surface.surface_geometry(mask, nr, pr), repeat)
    rows.append(("surface_geometry (all of the above)", t, mem))
    print(f"  {len(vox)} surface voxels; c per mm: median {np.median(geo.c) / spacing_mm:.4f}, "
          f"p10 {np.percentile(geo.c, 10) / spacing_mm:.4f}, p90 {np.percentile(geo.c, 90) / spacing_mm:.4f}")
    for step, t, mem in rows:
        print(f"  {step:45s} {t:7.3f} s  {mem:8.1f} MB peak")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    bench("sphere R=30 (1 mm)", sphere_mask(30.0), 1.0, args.repeat)
    verse = shared_data_dir() / "verse004" / "sub-verse004_seg-vert_msk.nii.gz"
    if not verse.exists():
        print(f"\nVerSe data not found at {verse}: skipping L1")
        return 0

    for spacing in (1.0, 0.5):
        t0 = time.perf_counter()
        ov = INS.load_object(verse, label=20, spacing_mm=spacing)
        print(f"\n(load_object L1 at {spacing} mm: {time.perf_counter() - t0:.2f} s)")
        bench(f"VerSe L1 at {spacing} mm", ov.mask, spacing, args.repeat)
    return 0


if __name__ == "__main__":
    sys.exit(main())
