"""Benchmark of the template stage (paper 3.1, 3.3): time and peak memory per step.

Usage: ``.venv/bin/python tools/bench_template.py [--label 20] [--spacing 1.0 0.5] [--repeat 1]``.

For VerSe L1 (``../shared/data/verse004`` or ``$SSM_SHARED_DATA``) at each spacing:
topology cleaning, surface geometry (normals, curvature), point density reduction,
triangulation, then the whole :func:`build_template` once more end to end. Peak memory
is the tracemalloc peak of each step (numpy buffers are traced). Targets (issue 3): the
whole template at 1 mm < 2 s, at 0.5 mm < 10 s on 2 cores.
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

from ssm_addon import meshutil as mu  # noqa: E402
from ssm_addon import surface  # noqa: E402
from ssm_addon.formats import label_maps as IO  # noqa: E402
from ssm_addon.instances import frame as FR  # noqa: E402
from ssm_addon.instances import resampling as RS  # noqa: E402
from ssm_addon.instances import volume as V  # noqa: E402
from ssm_addon.template import template as T  # noqa: E402


def step(name: str, fn, note=lambda r: ""):
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    result = fn()
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    print(f"  {name:<28s} {dt:8.2f} s {peak / 2**20:9.1f} MB  {note(result)}", flush=True)
    return result, dt


def bench(ov: V.ObjectVolume, params: T.TemplateParams) -> None:
    h = ov.spacing_mm
    print(f"{ov.source} at {h} mm: grid {ov.mask.shape}, {int(ov.mask.sum())} object voxels")
    mask, t1 = step("topology (clean_topology)", lambda: T.clean_topology(ov.mask, params.closing_radius_mm / h),
                    lambda m: f"{int(m.sum())} voxels")
    geo, t2 = step("surface geometry", lambda: surface.surface_geometry(
        mask, params.normal_radius_mm / h, params.patch_radius_mm / h, params.curvature_form),
        lambda g: f"{len(g.voxels)} surface voxels")

    def reduce():
        r = T.reduction_radii(geo.c, params.r_min_mm / h, params.r_max_mm / h, params.p, params.curvature_percentiles)
        return T.reduce_points(geo.graph, r, curvature=geo.c, selection=params.selection, seed=params.seed)

    sel, t3 = step("point density reduction", reduce, lambda s: f"{len(s)} points")
    tri, t4 = step("triangulation", lambda: T.triangulate(mask, geo.voxels[sel], max_refinements=params.max_refinements),
                   lambda t: f"{len(t.seeds)} vertices, {len(t.faces)} triangles, genus {t.genus}, "
                             f"{t.refinements} refinements")
    print(f"  {'sum of stages':<28s} {t1 + t2 + t3 + t4:8.2f} s")
    tpl, dt = step("build_template (end to end)", lambda: T.build_template(ov, params),
                   lambda t: f"{len(t.points_object)} points, {len(t.faces)} triangles, "
                             f"genus {mu.genus(len(t.points_object), t.faces)}")
    vol = mu.signed_volume(tpl.points_object, tpl.faces)
    print(f"  template volume / voxel volume = {vol / ov.volume_mm3:.3f}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--label", type=int, default=20, help="VerSe label (20 = L1)")
    parser.add_argument("--spacing", type=float, nargs="+", default=[1.0, 0.5])
    args = parser.parse_args(argv)
    data = Path(os.environ.get("SSM_SHARED_DATA", ROOT.parent / "shared" / "data"))
    path = data / "verse004" / "sub-verse004_seg-vert_msk.nii.gz"
    if not path.exists():
        print(f"VerSe data not found at {path}")
        return 1
    lm = IO.read_label_map(path)
    vol = IO.select_label(lm, args.label)
    frame = FR.object_frame(vol)
    print(f"{os.cpu_count()} CPUs, numpy {np.__version__}")
    for h in args.spacing:
        ov = RS.resample(vol, frame, h)
        bench(ov, T.TemplateParams(spacing_mm=h))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
