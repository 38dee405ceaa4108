"""Builds of data as other tools write it against the same data as the project holds it.

Usage::

    python tools/eval_foreign.py verse [--alignment none|rigid|similarity] [--format ply|stl|obj]
    python tools/eval_foreign.py knee30-tibia [--n 30] [--alignment ...] [--max-turn 180]
    python tools/eval_foreign.py knee30-femur --method model   # the model method (its template choice printed)

``verse``: the nine VerSe vertebrae of sub-verse004 from their label map (the reference) and
as 3D Slicer exports them (LPS meshes saying so, Scalismo landmark JSON in the meshes' frame,
``tests/foreign_data.py``); ``knee30-<bone>``: the bones in the data set's poses (the
reference) and each moved by its own random rigid transform (scanner coordinates), plain PLY
and Scalismo landmarks. Each build uses the project's defaults except ``--alignment`` and
``--method`` (``[correspondence] method``). Prints,
per build: mode 1's share of the variance, generalization and specificity at 1–3 modes (mm),
the frame findings and the seconds; then the relative differences of the foreign build.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import numpy as np  # noqa: E402
from foreign_data import knee30_in_scanner_poses, verse_slicer_meshes  # noqa: E402

from ssm_addon.base.params import CORRESPONDENCE_METHODS  # noqa: E402
from ssm_addon.formats.meshes import read_mesh  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402

DATA = Path(os.environ.get("SSM_SHARED_DATA") or ROOT.parent / "shared" / "data")
VERSE = {"T9": 16, "T10": 17, "T11": 18, "T12": 19, "L1": 20, "L2": 21, "L3": 22, "L4": 23, "L5": 24}


def with_tables(path: Path, alignment: str | None, template: str | None = None, method: str | None = None) -> Path:
    text = path.read_text()
    if template:
        text = f'[template]\ninstance = "{template}"\n\n' + text
    if method:
        text += f'\n[correspondence]\nmethod = "{method}"\n'
    if alignment:
        text += f'\n[model]\nalignment = "{alignment}"\n'
    path.write_text(text)
    return path


def figures(label: str, project: Path, out: Path, jobs: int) -> dict:
    t0 = time.perf_counter()
    result = build(read_project(project), out, jobs=jobs, log=None)
    seconds = time.perf_counter() - t0
    m = result.report["metrics"]
    share = result.report["model"]["variances_mm2"][0] / result.report["model"]["total_variance_mm2"]
    gen = m["generalization"]["mean_mm"][:3]
    spe = m["specificity"]["mean_mm"][:3]
    frames = [f for f in result.report["quality"]["findings"] if f["gate"] == "frame"]
    print(f"{label:28s} mode 1 {100 * share:5.1f} %  generalization {' '.join(f'{g:.3f}' for g in gen)} mm  "
          f"specificity {' '.join(f'{s:.3f}' for s in spe)} mm  frame findings {len(frames)}  {seconds:.0f} s")
    choice = result.report.get("correspondence", {}).get("template_choice") or {}
    if choice:
        print(f"{'':28s} template from {result.report['correspondence'].get('template_instance')}: "
              f"{ {k: v for k, v in choice.items() if k in ('given', 'medoid', 'by', 'confirmed', 'kept')} }")
    surf = {n: d["input_surface_mm"] for n, d in result.report["instances"].items() if "input_surface_mm" in d}
    if surf:
        to_in = [d["to_input"]["mean_mm"] for d in surf.values()]
        from_in = [d["from_input"]["max_mm"] for d in surf.values()]
        gated = [f["instance"] for f in result.report["quality"]["findings"] if f["gate"] == "input_surface"]
        print(f"{'':28s} against the input meshes: coating to mesh mean {min(to_in):.2f}-{max(to_in):.2f} mm; mesh to "
              f"coating max {min(from_in):.2f}-{max(from_in):.2f} mm; input_surface findings {len(gated)} {gated}")
    return {"share": share, "gen": np.array(gen), "spe": np.array(spe), "frames": len(frames)}


def compare(ref: dict, other: dict) -> None:
    print(f"{'':28s} differences: mode 1 share {100 * (other['share'] / ref['share'] - 1):+.2f} %, generalization "
          + " ".join(f"{100 * d:+.2f} %" for d in other["gen"] / ref["gen"] - 1)
          + ", specificity " + " ".join(f"{100 * d:+.2f} %" for d in other["spe"] / ref["spe"] - 1))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("population")
    ap.add_argument("--alignment", default=None, help="[model] alignment (default: the project default)")
    ap.add_argument("--format", default="ply", choices=("ply", "stl", "obj"))
    ap.add_argument("--n", type=int, default=30)
    ap.add_argument("--max-turn", type=float, default=180.0)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--method", choices=CORRESPONDENCE_METHODS, default=None,
                    help="[correspondence] method (default: the project default)")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.population == "verse":
            lines = ['[template]', 'instance = "L1"', ""]
            for name, label in VERSE.items():
                lines += ["[[instances]]", f'name = "{name}"', f'volume = "{DATA / "verse004" / "sub-verse004_seg-vert_msk.nii.gz"}"',
                          f"label = {label}", f'landmarks = "{DATA / "verse004" / "landmarks" / f"{name}.fcsv"}"', ""]
            ref_project = tmp / "labelmap.toml"
            ref_project.write_text("\n".join(lines))
            with_tables(ref_project, args.alignment, method=args.method)
            ref = figures("label map", ref_project, tmp / "ref", args.jobs)
            foreign = verse_slicer_meshes(tmp / "slicer", DATA / "verse004" / "sub-verse004_seg-vert_msk.nii.gz", VERSE,
                                          DATA / "verse004" / "landmarks", fmt=args.format)
            other = figures(f"Slicer {args.format.upper()} (LPS), Scalismo", with_tables(foreign, args.alignment, "L1", args.method),
                            tmp / "out", args.jobs)
        else:
            bone = args.population.split("-")[1].capitalize()
            files = sorted((DATA / "knee30").glob(f"*_{bone}.ply"))[: args.n]
            meshes = [read_mesh(f) for f in files]
            names = [f.stem for f in files]
            vertices, faces = np.stack([v for v, _ in meshes]), meshes[0][1]
            ref_project, _ = knee30_in_scanner_poses(tmp / "ref_in", names, vertices, faces, move=False)
            ref = figures("data set's poses", with_tables(ref_project, args.alignment, method=args.method), tmp / "ref",
                          args.jobs)
            foreign, _ = knee30_in_scanner_poses(tmp / "moved_in", names, vertices, faces, max_turn_deg=args.max_turn)
            other = figures(f"random poses (≤ {args.max_turn:g}°)", with_tables(foreign, args.alignment, method=args.method),
                            tmp / "out", args.jobs)
        compare(ref, other)


if __name__ == "__main__":
    main()
