"""``python -m ssm_addon``: the headless command line (also ``blender -b --command ssm …``).

Subcommands
-----------
``info VOLUME``
    Labels with voxel counts, spacing, shape and affine of a label map.
``template VOLUME [--label L] [--spacing MM] [template options] --out TEMPLATE.ply``
    Build a template (paper 3) and write it as PLY in world mm; prints vertices, faces,
    Euler characteristic and genus.
``build PROJECT.toml --out DIR [--jobs N] [--no-blend]``
    The whole pipeline from a project file (see :mod:`ssm_addon.project`).
``demo --out DIR [--n N] [--jobs N] [--seed S] [--no-blend]``
    Generate the synthetic demo population (:mod:`ssm_addon.demo`) and build it.

Errors in the input print one message (no traceback) and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .errors import Cancelled, SSMError

EXIT_INPUT = 2
EXIT_CANCELLED = 130


def _print_progress():
    state = {"last": None}

    def progress(fraction: float, message: str) -> None:
        if message != state["last"]:
            state["last"] = message
            print(f"[{fraction * 100:5.1f} %] {message}", flush=True)

    return progress


def _template_param_fields():
    try:
        from .project import params_schema
        from .template import TemplateParams
    except ImportError:  # the template stage is missing: no options
        return None, {}
    return TemplateParams, params_schema(TemplateParams)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m ssm_addon",
        description="SSM Builder: point-based 3D statistical shape models from segmented volumes (headless).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="{info,template,build,demo}")

    p = sub.add_parser("info", help="labels, voxel counts, spacing and affine of a label map")
    p.add_argument("volume", help="label map (NIfTI, NRRD, MetaImage, .npz)")

    p = sub.add_parser("template", help="build a template from one object (paper 3) and write it as PLY")
    p.add_argument("volume", help="label map or closed mesh (STL/PLY/OBJ)")
    p.add_argument("--label", type=int, default=None, help="label to use (default: all non-zero voxels)")
    p.add_argument("--spacing", type=float, default=1.0, help="isotropic resampling spacing in mm (default 1.0)")
    p.add_argument("--frame", choices=("auto", "patient", "moments"), default="auto", help="object frame method")
    p.add_argument("--out", required=True, help="output PLY (vertices in world mm)")
    _, schema = _template_param_fields()
    group = p.add_argument_group("template parameters (TemplateParams; lengths in mm)")
    for name, kind in schema.items():
        if name == "spacing_mm":  # that is --spacing
            continue
        flag = "--" + name.replace("_", "-")
        if kind == "bool":
            group.add_argument(flag, dest=f"tp_{name}", action=argparse.BooleanOptionalAction, default=None)
        elif kind in ("int", "float", "str"):
            group.add_argument(flag, dest=f"tp_{name}", type={"int": int, "float": float, "str": str}[kind], default=None)

    p = sub.add_parser("build", help="build a shape model from a project file")
    p.add_argument("project", help="project file (TOML)")
    p.add_argument("--out", required=True, help="output folder (written atomically)")
    p.add_argument("--jobs", type=int, default=1, help="parallel workers for the per-instance work (default 1)")
    p.add_argument("--no-blend", action="store_true", help="do not write model.blend / modes.png even if bpy is available")

    p = sub.add_parser("demo", help="generate the synthetic demo population and build its model")
    p.add_argument("--out", required=True, help="output folder: population in OUT/population, model in OUT/model")
    p.add_argument("--n", type=int, default=24, help="number of instances (default 24)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the population (default 0)")
    p.add_argument("--jobs", type=int, default=2, help="parallel workers (default 2)")
    p.add_argument("--no-blend", action="store_true", help="do not write model.blend / modes.png")
    return parser


def cmd_info(args) -> int:
    import numpy as np

    from . import volume as vol

    lm = vol.read_label_map(args.volume)
    spacing = np.linalg.norm(lm.affine[:3, :3], axis=0)
    print(f"file:    {lm.path}")
    print(f"shape:   {' x '.join(str(s) for s in lm.labels.shape)} voxels")
    print(f"spacing: {' x '.join(f'{s:g}' for s in spacing)} mm")
    print("affine (voxel -> world RAS mm):")
    for row in lm.affine:
        print("   " + " ".join(f"{v:10.4f}" for v in row))
    counts = vol.label_counts(lm)
    voxel_mm3 = float(abs(np.linalg.det(lm.affine[:3, :3])))
    print(f"labels:  {len(counts)} (background 0 not listed)")
    for label, count in counts.items():
        print(f"  {label:6d}: {count:9d} voxels  {count * voxel_mm3 / 1000:9.2f} cm³")
    return 0


def cmd_template(args) -> int:
    from . import volume as vol
    from .meshutil import euler_characteristic, genus, write_ply
    from .template import build_template

    TemplateParams, schema = _template_param_fields()
    options = {name: getattr(args, f"tp_{name}") for name in schema if getattr(args, f"tp_{name}", None) is not None}
    if "spacing_mm" in schema:
        options["spacing_mm"] = args.spacing
    try:
        params = TemplateParams(**options)
    except (TypeError, ValueError) as err:
        raise SSMError(f"template parameters: {err}") from None
    progress = _print_progress()
    t0 = time.perf_counter()
    ov = vol.load_object(args.volume, label=args.label, spacing_mm=args.spacing, frame_method=args.frame,
                         progress=progress)
    template = build_template(ov, params, progress=progress)
    n_v, faces = len(template.points_object), template.faces
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_ply(out, template.points_world, faces)
    print(f"vertices: {n_v}")
    print(f"faces:    {len(faces)}")
    print(f"Euler characteristic: {euler_characteristic(n_v, faces)}")
    print(f"genus:    {genus(n_v, faces)}")
    print(f"written:  {out} (world mm) in {time.perf_counter() - t0:.2f} s")
    return 0


def _run_build(project_path, out, jobs: int, blend: bool, in_blender: bool) -> int:
    from . import _blender
    from .project import build, read_project

    project = read_project(project_path)
    hook = None
    if blend and project.output_options.get("blend", True) and (in_blender or _blender.bpy_available()):
        hook = _blender.write_blend_outputs
    elif blend and not in_blender:
        print("bpy is not importable: skipping model.blend and modes.png (pip install bpy==5.0.1)", flush=True)
    print(f"project: {project.path} ({len(project.instances)} instances, {len(project.landmark_names)} landmarks)",
          flush=True)
    result = build(project, out, jobs=jobs, progress=_print_progress(), log=lambda m: print(m, flush=True),
                   blender_hook=hook)
    t = result.timings_s
    print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()), flush=True)
    print(f"outputs in {result.out_dir}:")
    for key in ("npz", "statismo", "report", "blend", "picture"):
        if key in result.files:
            print(f"  {key:9s} {result.files[key]}")
    for f in result.files.get("plots", []):
        print(f"  {'plot':9s} {f}")
    if "coated" in result.files:
        print(f"  {'coated':9s} {result.files['coated']}/<name>.ply")
    return 0


def cmd_build(args, in_blender: bool) -> int:
    return _run_build(args.project, args.out, args.jobs, not args.no_blend, in_blender)


def cmd_demo(args, in_blender: bool) -> int:
    from .demo import make_demo_population

    out = Path(args.out)
    t0 = time.perf_counter()
    project = make_demo_population(out / "population", n=args.n, seed=args.seed)
    print(f"demo population: {args.n} synthetic vertebrae in {out / 'population'} ({time.perf_counter() - t0:.1f} s)",
          flush=True)
    return _run_build(project, out / "model", args.jobs, not args.no_blend, in_blender)


def main(argv=None, in_blender: bool = False) -> int:
    """Run a subcommand; returns the exit status (0 ok, 2 bad input, 130 cancelled).

    Parameters
    ----------
    argv : list of str, optional
        Arguments after ``python -m ssm_addon`` (default ``sys.argv[1:]``).
    in_blender : bool
        True when called by ``blender -b --command ssm …`` (operators/cli.py): the
        running ``bpy`` writes ``model.blend``.
    """
    try:
        args = _parser().parse_args(sys.argv[1:] if argv is None else list(argv))
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2); never exit Blender
        return exc.code if isinstance(exc.code, int) else EXIT_INPUT
    try:
        if args.command == "info":
            return cmd_info(args)
        if args.command == "template":
            return cmd_template(args)
        if args.command == "build":
            return cmd_build(args, in_blender)
        if args.command == "demo":
            return cmd_demo(args, in_blender)
    except Cancelled as err:
        print(f"cancelled: {err}", file=sys.stderr)
        return EXIT_CANCELLED
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return EXIT_CANCELLED
    except SSMError as err:
        print(f"error: {err}", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_INPUT  # pragma: no cover - argparse requires a command


if __name__ == "__main__":
    sys.exit(main())
