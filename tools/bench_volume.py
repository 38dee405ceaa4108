"""Benchmark of the import stage (paper section 2): time and peak memory per step.

Usage: ``.venv/bin/python tools/bench_volume.py [--no-synthetic]``.

* the real VerSe label map (``../shared/data/verse004`` or ``$SSM_SHARED_DATA``), all
  nine vertebrae: read, then per label select + object frame + resample at 1 mm
  (+ the display surface, reported separately);
* a synthetic 512 x 512 x 400 label map (uint8, 0.7 x 0.7 x 1.0 mm, five ellipsoidal
  blobs) written as .nii.gz: read, label counts, per label select + frame + resample.

Peak memory is the tracemalloc peak of each step (numpy buffers are traced), plus the
process's maximum resident set size at the end.
"""

from __future__ import annotations

import os
import resource
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_addon.formats import label_maps as IO  # noqa: E402
from ssm_addon.instances import frame as FR  # noqa: E402
from ssm_addon.instances import resampling as RS  # noqa: E402
from ssm_addon.instances import volume as V  # noqa: E402

ROWS: list[tuple[str, float, float, str]] = []


def step(name: str, fn, note=lambda r: ""):
    tracemalloc.start()
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    result = fn()
    dt = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    ROWS.append((name, dt, peak / 2**20, note(result)))
    print(f"  {name:<44s} {dt:8.2f} s {peak / 2**20:9.1f} MB  {note(result)}", flush=True)
    return result


def import_all(path, labels=None):
    lm = step(f"read {Path(path).name}", lambda: IO.read_label_map(path), lambda r: f"{r.labels.shape} {r.labels.dtype}")
    counts = step("label counts", lambda: IO.label_counts(lm), lambda r: f"{len(r)} labels")
    total = 0.0
    for label in labels or sorted(counts):

        def one(label=label):
            vol = IO.select_label(lm, label)
            frame = FR.object_frame(vol)
            return vol, RS.resample(vol, frame, 1.0)

        t0 = time.perf_counter()
        vol, ov = step(
            f"label {label}: select + frame + resample 1 mm",
            one,
            lambda r: (
                f"{r[0].volume_mm3:9.0f} -> {r[1].volume_mm3:9.0f} mm3 ({r[1].volume_mm3 / r[0].volume_mm3 - 1:+.2%})"
            ),
        )
        total += time.perf_counter() - t0
        step(f"label {label}: display surface", lambda vol=vol: V.display_surface(vol), lambda r: f"{len(r[1])} faces")
    print(f"  {'all labels (select+frame+resample)':<44s} {total:8.2f} s", flush=True)
    return total


def synthetic(path: Path):
    shape = (512, 512, 400)
    affine = np.diag([0.7, 0.7, 1.0, 1.0])
    labels = np.zeros(shape, np.uint8)
    rng = np.random.default_rng(0)
    for label in range(1, 6):
        centre = rng.uniform([80, 80, 60], [432, 432, 340])
        semi = rng.uniform(25, 70, size=3)
        lo = np.maximum(np.floor(centre - semi).astype(int), 0)
        hi = np.minimum(np.ceil(centre + semi).astype(int) + 1, shape)
        grid = np.ogrid[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
        inside = sum(((g - c) / s) ** 2 for g, c, s in zip(grid, centre, semi)) <= 1
        labels[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]][inside] = label
    IO.write_label_map(path, labels, affine)


def main(argv):
    verse = Path(os.environ.get("SSM_SHARED_DATA", ROOT.parent / "shared" / "data")) / "verse004"
    verse_file = verse / "sub-verse004_seg-vert_msk.nii.gz"
    print(f"{'step':<46s} {'time':>10s} {'peak':>12s}")
    if verse_file.exists():
        print(f"VerSe ({verse_file.name}), nine vertebrae:")
        import_all(verse_file)
    else:
        print(f"VerSe data not found at {verse}; skipped")
    if "--no-synthetic" not in argv:
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "synthetic_512x512x400.nii.gz"
            t0 = time.perf_counter()
            synthetic(path)
            print(
                f"synthetic 512x512x400 uint8 label map, five blobs "
                f"(written in {time.perf_counter() - t0:.1f} s, {path.stat().st_size / 2**20:.1f} MB):"
            )
            import_all(path)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"max resident set size of the process: {rss:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
