"""``ssm`` / ``python -m ssm_addon``: the headless command line (also ``blender -b --command ssm …``).

Subcommands
-----------
``info VOLUME``
    Labels with voxel counts, spacing, shape and affine of a label map.
``template VOLUME [--label L] [--spacing MM] [template options] --out TEMPLATE.ply``
    Build a template (paper 3) and write it as PLY in world mm; prints vertices, faces,
    Euler characteristic and genus.
``build PROJECT.toml --out DIR [--jobs N] [--no-blend]``
    The whole pipeline from a project file (see :mod:`ssm_addon.pipeline.project_build`).
``analyze MODEL_DIR [--attributes CSV] --group COLUMN [--covariate COLUMN …] --out DIR``
    Group differences and covariate effects of a built model (:mod:`ssm_addon.analysis`).
``demo --out DIR [--n N] [--jobs N] [--seed S] [--no-blend]``
    Generate the synthetic demo population (:mod:`ssm_addon.cli.demo`) and build it.

Errors in the input print one message (no traceback) and exit with status 2; a strict
build whose quality gates fail exits with 3; an interrupted one with 130 (SIGINT), 143
(SIGTERM) or 129 (SIGHUP).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from ..base import params as P
from ..base.errors import Cancelled, InputError, SSMError
from ..formats.registry import format_names

EXIT_INPUT = 2
EXIT_QUALITY = 3
EXIT_CANCELLED = 130


class Interrupted(BaseException):
    """SIGTERM or SIGHUP arrived: unwinds like KeyboardInterrupt (workers stopped, temporary
    folders removed, the output folder as it was)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum
        self.name = signal.Signals(signum).name


_received: list[int] = []  # the signals this command has received, in order of arrival
_written: list[Path] = []  # the outputs this command has put in place (a signal after them leaves them whole)


def _signal_exception(signum: int) -> BaseException:
    return KeyboardInterrupt() if signum == signal.SIGINT else Interrupted(signum)


def check_signals() -> bool:
    """The ``cancelled`` callable the command line gives the core: raises the exception of the
    first signal received (again: see :func:`signals_as_exceptions`); False when none arrived."""
    if _received:
        raise _signal_exception(_received[0])
    return False


@contextlib.contextmanager
def signals_as_exceptions():
    """SIGINT raises KeyboardInterrupt, SIGTERM and SIGHUP :class:`Interrupted` in the main
    thread, and each is remembered.

    Python drops an exception raised inside a finalizer (an object's ``__del__``, a weakref
    callback): a signal that lands while the garbage collector runs one would be lost, and the
    build would go on to write its output. :func:`check_signals` raises it again at the core's
    next check (every map result, every progress line, before the output folder is moved into
    place), and the dropped first raise is not printed. A signal ignored when the command
    started (``nohup``, a background job's SIGINT) stays ignored. Outside the main thread
    (Blender's) nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, _frame):
        _received.append(signum)
        raise _signal_exception(signum)

    unraisable = sys.unraisablehook

    def quiet_when_raised_again(info):
        if not (_received and isinstance(info.exc_value, Interrupted | KeyboardInterrupt)):
            unraisable(info)

    previous = {}
    _received.clear()
    for name in ("SIGINT", "SIGTERM", "SIGHUP"):
        signum = getattr(signal, name, None)
        if signum is not None and signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, handler)
    sys.unraisablehook = quiet_when_raised_again
    try:
        yield
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)
        sys.unraisablehook = unraisable
        _received.clear()


@contextlib.contextmanager
def _output_folder(out: Path, inputs, **options):
    """:func:`~ssm_addon.pipeline.outputs.owned_output_folder` with the command's signal check before
    the final move; remembers ``out`` once it is in place."""
    from ..pipeline.outputs import owned_output_folder

    with owned_output_folder(out, inputs, cancelled=check_signals, **options) as tmp:
        yield tmp
    _written.append(Path(out))


def _interrupted_line(name: str) -> str:
    """The one line an interrupted command prints: whether its output is as it was, or complete."""
    if _written:
        return f"interrupted by {name} after the output was written: {_written[-1]} is complete"
    return f"interrupted by {name}: stopped; the output folder is as it was"


def _print_progress():
    state = {"last": None}

    def progress(fraction: float, message: str) -> None:
        check_signals()
        if message != state["last"]:
            state["last"] = message
            print(f"[{fraction * 100:5.1f} %] {message}", flush=True)

    return progress



class _ShortErrors(argparse.ArgumentParser):
    """An argument parser whose error says first what is wrong, then where the options are (a
    subcommand's usage runs to dozens of lines: ``ssm build`` has one option per parameter)."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n(`{self.prog} --help` lists every option)\n")

def argument_parser() -> argparse.ArgumentParser:
    """The ``ssm`` command's parser: every subcommand, and every parameter as a ``--<table>-<key>`` option."""
    parser = _ShortErrors(
        prog="ssm",
        description="SSM Builder: point-based 3D statistical shape models from segmented volumes (headless). "
                    "Also runs as `python -m ssm_addon` and `blender -b --command ssm`.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="{info,template,build,fit,segment,analyze,demo,params}",
                                parser_class=_ShortErrors)

    p = sub.add_parser("info", help="labels, voxel counts, spacing and affine of a label map")
    p.add_argument("volume", help=f"label map ({format_names('label map', ', ')})")

    p = sub.add_parser("template", help="build a template from one object (paper 3) and write it as PLY")
    p.add_argument("volume", help=f"label map or closed mesh ({format_names('mesh')})")
    p.add_argument("--label", type=int, default=None, metavar="N", help="label to use (default: all non-zero voxels)")
    p.add_argument("--out", required=True, metavar="FILE", help="output PLY (vertices in world mm)")
    P.add_arguments(p.add_argument_group("template parameters ([template] of a project; lengths in mm)"),
                    P.TemplateParams)

    p = sub.add_parser("build", help="build a shape model from a project file")
    p.add_argument("project", help="project file (TOML)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (written atomically)")
    p.add_argument("--jobs", type=int, metavar="N", default=1, help="parallel workers for the per-instance work (default 1)")
    p.add_argument("--no-blend", action="store_true", help="do not write model.blend / modes.png even if bpy is available")
    p.add_argument("--force", action="store_true",
                   help="write into an existing folder that holds files an SSM build did not write (they are kept)")
    p.add_argument("--strict", action="store_true",
                   help="fail (exit 3, the output folder untouched) when a quality gate fails ([quality] strict)")
    for section, cls in P.TABLES.items():
        P.add_arguments(p.add_argument_group(f"[{section}] overrides (the project file's values otherwise)"), cls,
                        prefix=section)
    p.add_argument("--scheduler", dest="compute__scheduler", default=None, metavar="WHERE",
                   help="where per-instance work runs: processes (default), dask-local, serial, or a Dask scheduler "
                        "address tcp://host:8786 (same as --compute-scheduler)")
    p.add_argument("--cache", dest="compute__cache", default=None, metavar="PATH",
                   help="per-instance cache folder for resuming ('auto': DIR.cache beside --out; 'off')")

    sub.add_parser("params", help="print the parameter reference (every table, key, default and range) as Markdown")

    p = sub.add_parser("fit", help="fit a built model to new data: coefficients, pose, completion, outlier score")
    p.add_argument("model", help="model.npz (ssm build) or a statismo .h5 file")
    p.add_argument("--volume", metavar="FILE", help="label map of the target")
    p.add_argument("--label", type=int, default=None, metavar="N", help="label of the target in --volume")
    p.add_argument("--label-of", action="append", default=[], metavar="STRUCTURE=LABEL",
                   help="for a joint model: the label of a structure in --volume, repeated")
    p.add_argument("--mesh", action="append", metavar="[STRUCTURE=]FILE", help=f"closed surface mesh of the target ({format_names('mesh')}, world mm); for a "
                   "joint model STRUCTURE=FILE, repeated (the structures not given are predicted)")
    p.add_argument("--points", metavar="FILE", help="point cloud of the target (CSV x,y,z or PLY, world mm)")
    p.add_argument("--landmarks", metavar="FILE", help="landmarks of the target (matched by name to the model's)")
    p.add_argument("--partial", action="store_true",
                   help="the target covers part of the shape: predict the rest with its uncertainty")
    p.add_argument("--free", action="store_true", help="also relax the fit freely onto the target (fitted_free.ply)")
    p.add_argument("--floor", action="store_true",
                   help="also the best the model can do for the target (closest points within its span, no prior, "
                        "from 13 starts around the fit and the pose search's 3 nearest other rotations): fit.json "
                        "floor_mm, and how far the fit is above it (slow)")
    p.add_argument("--project", metavar="FILE", help="fit every instance of a project file (a batch; with its landmarks)")
    p.add_argument("--no-landmarks", action="store_true",
                   help="a --project batch fits the surfaces alone, without the instances' landmarks")
    p.add_argument("--glob", metavar="PATTERN", help="fit every file of a glob pattern (a batch; --label applies)")
    p.add_argument("--jobs", type=int, metavar="N", default=1, help="parallel workers of a batch")
    p.add_argument("--scheduler", default="processes", metavar="WHERE",
                   help="where a batch runs: processes (default), dask-local, serial, or a Dask scheduler address")
    p.add_argument("--outlier-probability", type=float, default=0.99, metavar="P",
                   help="chi-square quantile of the Mahalanobis distance above which a target is an outlier "
                        "(default 0.99)")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (written whole at the end; never one holding an input or files no SSM "
                        "command wrote)")
    p.add_argument("--force", action="store_true",
                   help="write into a folder holding other files (they are kept, never replaced)")
    P.add_arguments(p.add_argument_group("fit parameters"), P.FitParams)

    p = sub.add_parser("segment", help="segment a grey-value image (CT) with a model: pose and shape from coarse to "
                                       "fine, the label map on the image's grid, the surface with its uncertainty")
    p.add_argument("model", help="model.npz (ssm build; with its learned appearance when built with images) or a "
                                 "statismo .h5 file")
    p.add_argument("image", help=f"the image to segment ({format_names('image', ', ')}; world RAS mm from its header)")
    p.add_argument("--at", action="append", default=[], metavar="X,Y,Z",
                   help="a point inside the structure, world RAS mm (as 3D Slicer shows it); a joint model: "
                        "STRUCTURE=X,Y,Z, repeated")
    p.add_argument("--landmarks", metavar="FILE",
                   help="the model's landmarks clicked on the image (any landmark file ssm reads)")
    p.add_argument("--init-mask", metavar="FILE", help="a rough segmentation to refine (label map, world mm)")
    p.add_argument("--label", type=int, default=None, metavar="N",
                   help="the label of --init-mask (default: every non-zero voxel)")
    p.add_argument("--truth", metavar="FILE",
                   help="an expert's label map of the structure: Dice, mean and 95th percentile surface distance, "
                        "how the posterior SD ranks and covers the error (segment.json), its outline in segment.png")
    p.add_argument("--truth-label", type=int, default=None, metavar="N",
                   help="the label of --truth (default: --label when there is no --init-mask, else every non-zero "
                        "voxel)")
    p.add_argument("--labels", action="append", default=[], metavar="STRUCTURE=N",
                   help="a joint model's label numbers in segmentation.nii.gz, e.g. L1=20,L2=21 (default: VerSe's "
                        "numbers for structures named by a vertebra, C1=1 … T1=8 … L1=20, else 1, 2, … in the "
                        "model's order)")
    P.add_arguments(p.add_argument_group("segment parameters"), P.SegmentParams)
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (written whole at the end)")
    p.add_argument("--force", action="store_true", help="write into a folder holding other files (they are kept)")

    p = sub.add_parser("analyze", help="group differences and covariate effects of a built model: where on the "
                                       "surface, by how many mm, with permutation p-values")
    p.add_argument("model", help="a build's output folder (model.npz inside) or a model.npz / statismo file")
    p.add_argument("--attributes", metavar="CSV",
                   help="per-instance attributes joined by instance name (default: the build folder's "
                        "attributes.csv, written from the project's attributes)")
    p.add_argument("--group", metavar="COLUMN", help="attribute column whose groups are compared")
    p.add_argument("--covariate", dest="covariates", action="append", default=None, metavar="COLUMN",
                   help="a covariate modelled with the group (repeat for several; 'centroid_size' in mm is always "
                        "available)")
    p.add_argument("--reference", metavar="GROUP", help="the group the others are compared to (default: first in sorted order)")
    p.add_argument("--permutations", type=int, default=None, metavar="N", help="random permutations of every test (default 1000)")
    p.add_argument("--seed", type=int, default=None, metavar="N", help="seed of the permutations (default 0)")
    p.add_argument("--size-removed", action="store_true", default=None,
                   help="scale every shape to the mean centroid size first (shape without size)")
    p.add_argument("--structure", metavar="NAME", help="a joint model: analyse this structure's rows alone (its exact sub-model); "
                                       "default: the whole joint model, with the effects on the relative pose")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (written whole at the end)")
    p.add_argument("--force", action="store_true", help="write into a folder holding other files (they are kept)")

    p = sub.add_parser("demo", help="generate the synthetic demo population and build its model",
                       description="Generate the built-in synthetic population of vertebra-like label maps (with "
                                   "landmark files in four formats, a group and an age of known effect) in "
                                   "OUT/population, then build its shape model into OUT/model.")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder: population in DIR/population, model in DIR/model")
    p.add_argument("--n", type=int, default=24, metavar="N", help="number of instances (default 24)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="random seed of the population (default 0)")
    p.add_argument("--jobs", type=int, metavar="N", default=2, help="parallel workers (default 2)")
    p.add_argument("--no-blend", action="store_true", help="do not write model.blend / modes.png")
    return parser


def cmd_info(args) -> int:
    from nibabel.affines import voxel_sizes

    from ..formats import label_maps as imageio

    lm = imageio.read_label_map(args.volume)
    spacing = voxel_sizes(lm.affine)
    print(f"file:    {lm.path}")
    print(f"shape:   {' x '.join(str(s) for s in lm.labels.shape)} voxels")
    print(f"spacing: {' x '.join(f'{s:g}' for s in spacing)} mm")
    print("affine (voxel -> world RAS mm):")
    for row in lm.affine:
        print("   " + " ".join(f"{v:10.4f}" for v in row))
    counts = imageio.label_counts(lm)
    voxel_mm3 = float(abs(np.linalg.det(lm.affine[:3, :3])))
    print(f"labels:  {len(counts)} (background 0 not listed)")
    for label, count in counts.items():
        print(f"  {label:6d}: {count:9d} voxels  {count * voxel_mm3 / 1000:9.2f} cm³")
    return 0


def _writable_folder(folder: Path, option: str) -> None:
    """Create ``folder`` if needed and check that files can be written in it: a refusal naming
    it, before any work."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise InputError(f"{option}: {existing} is a file, not a folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):  # what writing will meet (a read-only mount, permissions)
            pass
    except OSError as err:
        raise InputError(f"{option}: cannot write in {folder}: {err.strerror or err}") from None


def cmd_template(args) -> int:
    from ..formats.meshes import write_ply
    from ..instances.importing import load_object
    from ..meshutil import euler_characteristic, genus
    from ..pipeline.stages import template_density
    from ..template.template import build_template

    params = P.from_arguments(args, P.TemplateParams)
    out = Path(args.out)
    if out.is_dir():
        raise InputError(f"{out}: --out is a folder; give the PLY file to write, e.g. {out / 'template.ply'}")
    _writable_folder(out.parent, "--out")  # before the work, not after it
    if out.exists() and Path(args.volume).exists() and os.path.samefile(out, args.volume):
        raise InputError(f"--out {out}: is the input itself; give another file for the template, e.g. "
                         f"{out.with_name(out.stem.split('.')[0] + '_template.ply')}")
    progress = _print_progress()
    t0 = time.perf_counter()
    ov = load_object(args.volume, label=args.label, spacing_mm=params.spacing_mm, frame_method=params.frame,
                     progress=progress)
    template = build_template(ov, params, progress=progress)
    n_v, faces = len(template.points_object), template.faces
    # whole or not at all: an earlier file of that name stays as it was if the writing fails or is interrupted
    part = out.with_name(f".{out.name}.{os.getpid()}.part")
    try:
        write_ply(part, template.points_world, faces, space="RAS")
        check_signals()
        os.replace(part, out)
    except BaseException:
        Path(part).unlink(missing_ok=True)
        raise
    _written.append(out)
    print(f"vertices: {n_v}")
    print(f"faces:    {len(faces)}")
    print(f"Euler characteristic: {euler_characteristic(n_v, faces)}")
    print(f"genus:    {genus(n_v, faces)}")
    print(f"density:  {template_density(template, params).removeprefix(', ')}")
    print(f"written:  {out} (world mm) in {time.perf_counter() - t0:.2f} s")
    return 0


def with_overrides(project, args):
    """The project with the parameters given on the command line (``--coating-k1 0.3``)."""
    if args is None:
        return project
    changes = {}
    cache = getattr(args, "compute__cache", None)
    if cache not in (None, "auto", "off"):  # a folder given on the command line is relative to the working folder
        args.compute__cache = str(Path(cache).expanduser().resolve())
    for section, cls in P.TABLES.items():
        current = getattr(project.params, section)
        updated = P.from_arguments(args, cls, prefix=section, base=current)
        if updated != current:
            changes[section] = updated
    return dataclasses.replace(project, params=project.params.replace(**changes)) if changes else project


def _run_build(project_path, out, jobs: int, blend: bool, writer, args=None) -> int:
    from ..cli import blender_layer
    from ..pipeline.project_build import build, read_project

    jobs = _workers(jobs)
    project = with_overrides(read_project(project_path), args)
    hook = None
    if blend and project.params.output.blend:
        hook = writer or blender_layer.blend_writer_in_child()
        if hook is None:
            why = ("bpy is not importable (pip install bpy==5.0.1)" if not blender_layer.bpy_available() else
                   "the Blender layer is not installed with this core (run `blender -b --command ssm build ...` "
                   "with the extension, or from a source checkout)")
            print(f"skipping model.blend: {why}; modes.png is drawn without Blender", flush=True)
    if project.structures:
        print(f"project: {project.path} ({len(project.instances)} subjects, {len(project.structures)} structures: "
              + ", ".join(f"{name} {len(st.landmark_names)} landmarks" for name, st in project.structures.items()) + ")",
              flush=True)
    else:
        print(f"project: {project.path} ({len(project.instances)} instances, {len(project.landmark_names)} landmarks)",
              flush=True)
    if args is not None and getattr(args, "strict", False) and not project.params.quality.strict:
        strict = dataclasses.replace(project.params.quality, strict=True)
        project = dataclasses.replace(project, params=project.params.replace(quality=strict))
    result = build(project, out, jobs=jobs, progress=_print_progress(), cancelled=check_signals,
                   log=lambda m: print(m, flush=True), blender_hook=hook, force=bool(getattr(args, "force", False)))
    _written.append(Path(result.out_dir))
    t = result.timings_s
    print("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in t.items()), flush=True)
    print(f"outputs in {result.out_dir}:")
    for key in ("npz", "statismo", "gltf", "report", "html", "blend", "picture", "scores", "eigenvalues",
                "attributes"):
        if key in result.files:
            print(f"  {key:11s} {result.files[key]}")
    for f in result.files.get("plots", []):
        print(f"  {'plot':11s} {f}")
    if "coated" in result.files:
        print(f"  {'coated':11s} {result.files['coated']}/<name>.ply")
    if "vtk" in result.files:
        coated = ", coated/<name>.vtp" if (Path(result.out_dir) / "vtk" / "coated").is_dir() else ""
        print(f"  {'vtk':11s} {result.files['vtk']}/ (mean, ±2 SD per mode{coated})")
    if "analysis" in result.files:
        print(f"  {'analysis':11s} {result.files['analysis']}/ (analysis.json, analysis.npz, effects/*.vtp, maps)")
    from ..model.quality import warnings_text

    # said last, where a reader looks (a joint build: each structure's, then the joint model's)
    groups = [("", result.study.findings)] if result.joint is None else (
        [(f"structure {name}: ", study.findings) for name, study in result.joint.structures.items()]
        + [("joint model: ", result.joint.findings)])
    for heading, findings in groups:
        if findings:
            print("\n" + heading + warnings_text(findings), flush=True)
    return 0


def _workers(jobs):
    """``--jobs`` as a number of workers: below 1 it is 1, said once."""
    if jobs is not None and jobs < 1:
        print(f"note: --jobs {jobs} is not a number of workers; used 1", flush=True)
        return 1
    return jobs


def _one_target(args, named: dict) -> None:
    """Refuse two targets at once (a batch and a single target, two batches, two single
    targets), naming them: one of them would otherwise be left out without a word."""
    single = [f"--{k} {v}" for k, v in (("volume", args.volume), ("mesh", args.mesh), ("points", args.points)) if v]
    single += [f"--mesh {k}={v}" for k, v in named.items()]
    batch = [f"--{k} {v}" for k, v in (("project", args.project), ("glob", args.glob)) if v]
    # a joint model's structures (--volume with --label-of, --mesh S=F; args.mesh is then None) are one target
    if (named or args.label_of) and not (batch or args.points or args.mesh):
        return
    if len(batch) + len(single) > 1:
        raise InputError(f"{' and '.join(batch + single)}: two targets at once; give one target, or one batch "
                         "(--project or --glob)")


def _one_mesh_for_a_joint_model(model, mesh) -> None:
    """A joint model fitted to one surface that holds fewer parts than the model has structures: the user
    meant one structure (``--mesh femur=FILE``), not the whole joint model."""
    from ..formats.meshes import read_mesh
    from ..meshutil import connected_components

    vertices, faces = read_mesh(mesh)
    parts, _labels = connected_components(faces, len(vertices))
    names = model.structure_names
    if parts < len(names):
        raise InputError(f"{mesh}: one surface of {parts} part(s) given to a joint model of {len(names)} structures "
                         f"({', '.join(names)}); name the structure it is, e.g. --mesh {names[0]}={mesh} (the others are "
                         "then predicted with their posterior SD)")


def cmd_fit(args) -> int:
    from ..fitting import batch as apply
    from ..model.figures import p_value_text
    from ..model.files import load_model
    from ..pipeline.project import targets_from_project

    params = P.from_arguments(args, P.FitParams)
    if not 0.5 < args.outlier_probability < 1.0:
        raise InputError(f"--outlier-probability must be between 0.5 and 1, got {args.outlier_probability}")
    out = Path(args.out).expanduser().resolve()
    meshes = args.mesh or []
    named = dict(m.split("=", 1) for m in meshes if "=" in m)
    if len(meshes) > 1 and len(named) != len(meshes):
        raise InputError("--mesh: several meshes are STRUCTURE=FILE each (a joint model's structures)")
    args.mesh = meshes[0] if meshes and not named else None
    _one_target(args, named)
    if args.floor and (args.project or args.glob or named or args.label_of):
        raise InputError("--floor: the model's floor is computed for one target (--mesh, --volume or --points), "
                         "not for a batch or a joint model's structures")
    args.jobs = _workers(args.jobs)
    inputs = [args.model, args.volume, args.mesh, args.points, args.landmarks, args.project, *named.values()]
    model = load_model(args.model, say=lambda line: print(line, flush=True))  # says which modes are empty
    if model.structure_names and args.mesh and not named and not args.partial:
        _one_mesh_for_a_joint_model(model, args.mesh)
    if params.n_modes is not None and params.n_modes > model.n_modes:
        print(f"note: --n-modes {params.n_modes}: the model has {model.n_modes} modes; used {model.n_modes}",
              flush=True)
    if named or args.label_of:
        labels = dict(x.split("=", 1) for x in args.label_of)
        targets = {n: apply.FitTarget(name=n, mesh=Path(f)) for n, f in named.items()}
        targets.update({n: apply.FitTarget(name=n, volume=Path(args.volume), label=int(lab)) for n, lab in labels.items()})
        with _output_folder(out, inputs, force=args.force, what="fitting") as tmp:
            doc = apply.fit_structures_to_folder(model, targets, tmp, params=params, model_path=str(args.model),
                                                 outlier_probability=args.outlier_probability,
                                                 progress=_print_progress())
        for n, d in doc["structures"].items():
            print(f"{n}: {'fitted' if d['given'] else 'predicted'}, posterior SD {d['posterior_sd_mm']['mean']:.2f} mm "
                  f"(up to {d['posterior_sd_mm']['max']:.2f}) -> {out / d['file']}")
        for w in doc.get("warnings", []):
            print(f"WARNING: {w}", file=sys.stderr)
        return 0
    if args.project or args.glob:
        targets = targets_from_project(args.project, landmarks=not args.no_landmarks) if args.project else \
            apply.targets_from_glob(args.glob, args.label)
        with_lm = [t.name for t in targets if t.landmarks is not None]
        if with_lm:
            print(f"landmarks: {len(with_lm)} of {len(targets)} targets are fitted with their project landmarks as "
                  "soft constraints (--no-landmarks: surfaces alone)")
        inputs += [p for t in targets for p in (t.volume, t.mesh, t.points, t.landmarks)]
        with _output_folder(out, inputs, force=args.force, what="fitting") as tmp:
            docs = apply.fit_batch(args.model, targets, tmp, params=params, partial=args.partial, free=args.free,
                                   outlier_probability=args.outlier_probability, jobs=args.jobs,
                                   progress=_print_progress(), scheduler=args.scheduler)
        for d in docs:
            flag = "  OUTLIER" if d["outlier"] else ""
            print(f"{d['name']}: Mahalanobis {d['mahalanobis']:.2f} ({p_value_text(d['p_value'])}), mean distance "
                  f"{d['mean_distance_mm']:.2f} mm{flag}")
        for d in docs:
            for w in d.get("warnings", []):
                print(f"WARNING {d['name']}: {w}", file=sys.stderr)
        print(f"coefficients: {out / 'coefficients.csv'}")
        return 0
    name = Path(args.volume or args.mesh or args.points or args.landmarks or "target").name
    t = apply.FitTarget(name=name, volume=Path(args.volume) if args.volume else None, label=args.label,
                        mesh=Path(args.mesh) if args.mesh else None, points=Path(args.points) if args.points else None,
                        landmarks=Path(args.landmarks) if args.landmarks else None)
    with _output_folder(out, inputs, force=args.force, what="fitting") as tmp:
        doc = apply.fit_to_folder(model, t, tmp, params=params, partial=args.partial, free=args.free,
                                  outlier_probability=args.outlier_probability, model_path=str(args.model),
                                  floor=args.floor, progress=_print_progress(), cancelled=check_signals)
    if doc.get("landmarks_used"):
        print(f"landmarks used: {', '.join(doc['landmarks_used'])}")
    print(f"{name}: Mahalanobis distance {doc['mahalanobis']:.2f} on {doc['n_modes']} modes ({p_value_text(doc['p_value'])})"
          f"{': an OUTLIER' if doc['outlier'] else ''}; mean distance {doc['mean_distance_mm']:.2f} mm, largest "
          f"{doc['max_distance_mm']:.2f} mm (pose from the start {doc['pose_search']['chosen']!r})")
    if "floor_mm" in doc:
        print(f"floor: the model reaches {doc['floor_mm']:.3f} mm from the target at best; this fit is "
              f"{doc['above_floor_mm']:+.3f} mm from that")
    for w in doc.get("warnings", []):
        print(f"WARNING {name}: {w}", file=sys.stderr)
    print(f"written: {out / 'fitted.ply'}, {out / 'fit.json'}, {out / 'fit.npz'}, {out / 'fit.png'}")
    return 0


def cmd_segment(args) -> int:
    from ..segmentation.files import parse_labels, segment_files

    out = Path(args.out).expanduser().resolve()
    params = P.from_arguments(args, P.SegmentParams)
    inputs = [args.model, args.image, args.landmarks, args.init_mask, args.truth]
    name = Path(args.image).name
    truth_label = args.truth_label if args.truth_label is not None else (None if args.init_mask else args.label)
    with _output_folder(out, inputs, force=args.force, what="segmentation") as tmp:
        doc = segment_files(args.model, args.image, tmp, at=args.at, landmarks_path=args.landmarks,
                            init_mask_path=args.init_mask, label=args.label if args.init_mask else None,
                            params=params, progress=_print_progress(), cancelled=check_signals,
                            say=lambda line: print(line, flush=True), truth_path=args.truth,
                            truth_label=truth_label, labels=parse_labels(args.labels))
    seg = doc["segmentation"]
    print(f"{name}: segmented with {doc['evidence']} evidence in {doc['iterations']} steps ({doc['seconds']:.1f} s): "
          f"{seg['voxels']} voxels ({seg['volume_mm3'] / 1000:.1f} cm³), Mahalanobis {doc['mahalanobis']:.2f}, "
          f"posterior SD {doc['posterior_sd_mm']['mean']:.2f} mm (up to {doc['posterior_sd_mm']['max']:.2f})")
    for structure, info in seg.get("structures", {}).items():
        print(f"{name}: {structure}: label {info['label']}, {info['voxels']} voxels ({info['volume_mm3'] / 1000:.1f} "
              f"cm³)" + (f", {info['shared_voxels_given_away']} voxels inside a neighbour's surface too given to it"
                         if info["shared_voxels_given_away"] else ""))
    truth = doc.get("truth")
    if truth:
        print(f"{name}: against {Path(truth['file']).name}: Dice {truth['dice']:.3f}, surface distance mean "
              f"{truth['mean_mm']:.2f} mm, 95th percentile {truth['p95_mm']:.2f} mm; posterior SD against each "
              f"point's error: Spearman {truth['sd_error_spearman']:.2f}, {100 * truth['within_2sd']:.0f} % within 2 SD")
        for structure, t in truth.get("structures", {}).items():
            print(f"{name}: {structure} against label {t['label']}: " + (t["missing"] if "missing" in t else
                  f"Dice {t['dice']:.3f}, surface distance mean {t['mean_mm']:.2f} mm, 95th percentile "
                  f"{t['p95_mm']:.2f} mm"))
    for f in doc["verdict"]["findings"]:
        print(f"WARNING {name}: [{f['kind']}] {f['message']}", file=sys.stderr)
    print(f"written: {out / 'segmentation.nii.gz'}, {out / 'segmented.ply'}, {out / 'segment.json'}, "
          f"{out / 'segment.png'}")
    return 0


def cmd_analyze(args) -> int:
    from ..analysis.attributes import read_attributes
    from ..analysis.files import analysis_summary, run_analysis
    from ..model.files import load_model, model_file
    model_path = model_file(args.model)  # a build's output folder: its model.npz
    model = load_model(model_path)
    if args.structure:
        from ..model.joint import structure_model

        if not model.structure_names:
            raise InputError(f"{model_path}: --structure {args.structure}: not a joint model (no structures)")
        model = structure_model(model, args.structure)  # an unknown name: an error naming the structures
    attributes_path = Path(args.attributes).expanduser() if args.attributes else model_path.parent / "attributes.csv"
    if not args.attributes and not attributes_path.is_file():
        raise InputError(f"{model_path.parent}: no attributes.csv (the build's project had no attributes); give "
                         "--attributes FILE")
    table = {k: v for k, v in (("group", args.group), ("covariates", args.covariates),
                               ("reference", args.reference), ("permutations", args.permutations),
                               ("seed", args.seed), ("size_removed", args.size_removed)) if v is not None}
    params = P.from_table(P.AnalysisParams, table, where="command line:")
    if not params.requested:
        raise InputError("analyze: give --group COLUMN, --covariate COLUMN, or both")
    attributes = read_attributes(attributes_path)
    out = Path(args.out).expanduser().resolve()
    with _output_folder(out, [model_path, attributes_path], force=args.force, what="analysis") as tmp:
        result, _, written = run_analysis(model, attributes, params, tmp, model_path=str(model_path),
                                          progress=_print_progress())
    print(f"analysis of {len(result.names)} instances ({', '.join(f'{k} {v}' for k, v in result.counts.items())})"
          if result.group else f"analysis of {len(result.names)} instances")
    for line in analysis_summary(result):
        print(line)
    for w in result.warnings:
        print(f"WARNING: {w}", file=sys.stderr)
    print(f"written: {', '.join(str(out / k) for k in written if '/' not in k)} and {out / 'effects'}/")
    return 0


def cmd_build(args, writer) -> int:
    return _run_build(args.project, args.out, args.jobs, not args.no_blend, writer, args)


def cmd_demo(args, writer) -> int:
    from ..cli.demo import make_demo_population

    out = Path(args.out)
    if args.n < 3:
        raise InputError(f"--n {args.n}: the demo needs at least 3 instances (a model of fewer has no variance "
                         "to speak of)")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: is a file, not a folder; the demo writes a folder (population/, model/)")
    _writable_folder(out, "--out")
    t0 = time.perf_counter()
    project = make_demo_population(out / "population", n=args.n, seed=args.seed)
    print(f"demo population: {args.n} synthetic vertebrae in {out / 'population'} ({time.perf_counter() - t0:.1f} s)",
          flush=True)
    code = _run_build(project, out / "model", args.jobs, not args.no_blend, writer)
    from ..cli.demo import explain_findings

    for line in explain_findings(out / "model" / "report.json", out / "population" / "truth.json"):
        print(line, flush=True)
    return code


def _joined_points(argv: list) -> list:
    """``--at -27,-160,-121`` as ``--at=-27,-160,-121``: a point whose first coordinate is negative
    would otherwise read as an option."""
    out, i = [], 0
    while i < len(argv):
        a = str(argv[i])
        if a == "--at" and i + 1 < len(argv) and re.match(r"^-\d|^-\.\d", str(argv[i + 1])):
            out.append(f"--at={argv[i + 1]}")
            i += 2
            continue
        out.append(argv[i])
        i += 1
    return out


def main(argv=None, in_blender: bool = False, blend_writer=None) -> int:
    """Run a subcommand; returns the exit status (0 ok, 2 bad input, 130 cancelled).

    Parameters
    ----------
    argv : list of str, optional
        Arguments after ``python -m ssm_addon`` (default ``sys.argv[1:]``).
    in_blender : bool
        True when called by ``blender -b --command ssm …`` (operators/cli.py).
    blend_writer : callable, optional
        The Blender layer's ``write_build_outputs`` (the extension passes its own);
        None: found from a source checkout when ``bpy`` is importable.
    """
    try:
        args = argument_parser().parse_args(_joined_points(sys.argv[1:] if argv is None else list(argv)))
    except SystemExit as exc:  # argparse: --help (0) or a usage error (2); never exit Blender
        return exc.code if isinstance(exc.code, int) else EXIT_INPUT
    _written.clear()
    try:
        with contextlib.nullcontext() if in_blender else signals_as_exceptions():
            code = _dispatch(args, blend_writer)
            if _received:  # dropped in a finalizer after the core's last check: the command had ended
                print(_interrupted_line(signal.Signals(_received[0]).name), file=sys.stderr)
                return 128 + _received[0]
            return code
    except Interrupted as sig:
        print(_interrupted_line(sig.name), file=sys.stderr)
        return 128 + sig.signum
    except KeyboardInterrupt:
        print(_interrupted_line("SIGINT"), file=sys.stderr)
        return EXIT_CANCELLED
    except Cancelled as err:
        print(f"cancelled: {err}", file=sys.stderr)
        return EXIT_CANCELLED
    except SSMError as err:
        from ..model.quality import QualityError

        print(f"error: {err}", file=sys.stderr)
        return EXIT_QUALITY if isinstance(err, QualityError) else EXIT_INPUT


def _dispatch(args, blend_writer) -> int:
    if args.command == "info":
        return cmd_info(args)
    if args.command == "template":
        return cmd_template(args)
    if args.command == "build":
        return cmd_build(args, blend_writer)
    if args.command == "demo":
        return cmd_demo(args, blend_writer)
    if args.command == "fit":
        return cmd_fit(args)
    if args.command == "segment":
        return cmd_segment(args)
    if args.command == "analyze":
        return cmd_analyze(args)
    if args.command == "params":
        print(P.markdown_tables())
        return 0
    return EXIT_INPUT  # pragma: no cover - argparse requires a command


def run() -> None:
    """The ``ssm`` command (``pip install .``): :func:`main` with the process's arguments."""
    try:
        code = main()
        sys.stdout.flush()
    except BrokenPipeError:  # e.g. `ssm info FILE | head`: the reader left, that is fine
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = 0
    sys.exit(code)


if __name__ == "__main__":
    run()
