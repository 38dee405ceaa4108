"""Benchmark of segmenting an image (``ssm segment``): seconds per structure on one core.

Usage: ``.venv/bin/python tools/bench_segment.py [--work DIR] [--repeat 5]``

* synthetic: a bright bumped ellipsoid (642 model points, 14 modes) in a 1 mm image with
  noise, gradient evidence;
* verse005 (where ``../shared/data`` holds it): L3 from the leave-one-out lumbar model of
  ``tools/eval_segmentation.py`` (631 points, 8 modes; built into ``--work`` once), with the
  learned appearance and with the gradient, on the 1 mm CT and on its 3 mm version; and L1-L5
  jointly from L3's point, a joint model of verse004's vertebrae (6 subjects, built once).

Each case: the median wall time of ``--repeat`` runs of
:func:`ssm_addon.segmentation.segment_image` with BLAS on one thread, and its peak memory.
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "tools"))

from ssm_addon.base.params import SegmentParams  # noqa: E402
from ssm_addon.model.pca import build_model  # noqa: E402
from ssm_addon.segmentation import degrade_image, read_image, segment_image, start_pose, volume_centroid  # noqa: E402


def timed(fn, repeat):
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    tracemalloc.start()
    fn()
    peak = tracemalloc.get_traced_memory()[1] / 2**20
    tracemalloc.stop()
    return float(np.median(times)), peak


def joint_spine_model(folder: Path):
    """A joint L1-L5 model built once into ``folder`` from verse004's label map (6 subjects, each vertebra
    turned and moved by a known amount, ``tests/foreign_data.verse_spine_population``); None without it."""
    from conftest import VERSE_DIR, VERSE_FILE
    from foreign_data import verse_spine_population

    from ssm_addon.model.files import load_model
    from ssm_addon.pipeline.project import read_project
    from ssm_addon.pipeline.project_build import build

    if not VERSE_FILE.is_file():
        print(f"verse004 not found at {VERSE_FILE}: the joint spine case is skipped")
        return None
    if not (folder / "out" / "model.npz").is_file():
        labels = {"L1": 20, "L2": 21, "L3": 22, "L4": 23, "L5": 24}
        project, _moves = verse_spine_population(folder / "in", VERSE_FILE, VERSE_DIR / "landmarks", labels, n=6)
        build(read_project(project), folder / "out", jobs=2, log=None, blend=False)
    return load_model(folder / "out" / "model.npz")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=str(Path.home() / ".cache" / "ssm-bench-segment"))
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args(argv)
    rows = []
    with threadpool_limits(1):
        from test_segmentation import bumped_shapes, posed, synthetic_image

        shapes, faces = bumped_shapes()
        model = build_model(shapes[1:], faces, [f"s{i}" for i in range(1, len(shapes))], alignment="none")
        truth = posed(shapes[0])
        image, _ = synthetic_image(truth, faces)
        at = volume_centroid(truth, faces) + 4.0
        rows.append(("synthetic, gradient", *timed(lambda: segment_image(model, image, at=at), args.repeat)))
        data = ROOT.parent / "shared" / "data"
        if (data / "verse005" / "sub-verse005_ct.nii.gz").is_file():
            import eval_segmentation as ev

            from ssm_addon.formats.label_maps import read_label_map

            lumbar, appearance = ev.build_lumbar_model(data, Path(args.work) / "loo_L3", held="L3")
            ct = read_image(data / "verse005" / "sub-verse005_ct.nii.gz")
            thick = degrade_image(ct, slice_mm=3.0, noise_hu=30.0, seed=5)
            labels = read_label_map(data / "verse005" / "sub-verse005_seg-vert_msk.nii.gz")
            (start,) = ev.start_points(labels.labels == 22, labels.affine, 10.0, 1, seed=11)
            for name, img in (("1 mm", ct), ("3 mm", thick)):
                for evidence, app in (("learned", appearance), ("gradient", None)):
                    fn = lambda img=img, app=app: segment_image(lumbar, img, at=start, appearance=app,  # noqa: E731
                                                                 params=SegmentParams())
                    rows.append((f"verse005 L3, {name}, {evidence}", *timed(fn, args.repeat)))
            # a whole lumbar spine from one click: a joint L1-L5 model (verse004's vertebrae, each turned
            # and moved in 6 subjects), started at L3's point; the model's relative poses place the rest
            spine = joint_spine_model(Path(args.work) / "spine")
            if spine is not None:
                placed = start_pose(spine, named={"L3": start})
                fn = lambda: segment_image(spine, ct, pose=placed, params=SegmentParams())  # noqa: E731
                rows.append(("verse005 L1-L5 jointly, 1 mm, gradient", *timed(fn, max(1, args.repeat // 2))))
        else:
            print(f"verse005 not found under {data}: the real-CT cases are skipped")
    print(f"{'case':40s} {'median s':>9s} {'peak MB':>8s}")
    for name, sec, peak in rows:
        print(f"{name:40s} {sec:9.2f} {peak:8.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
