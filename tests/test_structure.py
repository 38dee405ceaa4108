"""The shape of the code: an installable core, no import cycles, one read -> frame -> resample,
no private names across modules, and every parameter reachable from every front end."""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
import venv
from pathlib import Path

import pytest
from conftest import REAL_HOME, ROOT

from ssm_addon.base import params as P

CORE = ROOT / "ssm_addon"
OPERATORS = ROOT / "operators"


STAGE_PACKAGES = ("base", "formats", "instances", "template", "coating", "model", "fitting", "correspondence", "analysis",
                  "segmentation", "pipeline", "cli")
#: Blender modules every operators module may import; the stage modules import only these,
#: ``project`` (which shows a whole study) and ``cli`` (its command) also the stage modules.
SHARED_OPERATOR_MODULES = {"bridge", "jobs", "properties", "scene"}


def _modules(folder: Path) -> list[str]:
    """Dotted names (relative to ``folder``) of every module, package ``__init__`` as the package."""
    out = []
    for p in sorted(folder.rglob("*.py")):
        rel = p.relative_to(folder).with_suffix("").parts
        if rel[-1] == "__main__":
            continue
        out.append(".".join(rel[:-1]) if rel[-1] == "__init__" else ".".join(rel))
    return out


def _path(folder: Path, module: str) -> Path:
    base = folder.joinpath(*module.split(".")) if module else folder
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def _imported_modules(folder: Path, module: str) -> set[str]:
    """Modules of ``folder`` that ``module`` imports (relative, or absolute ``ssm_addon.…``), anywhere in it."""
    path = _path(folder, module)
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    if module == "":
        package = []
    known = set(_modules(folder))
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom):
            continue
        if node.level:
            base = package[: len(package) - (node.level - 1)] if node.level > 1 else package
        elif folder == CORE and (node.module or "").split(".")[0] == "ssm_addon":
            base = []
        else:
            continue
        mod = node.module if node.level else ".".join((node.module or "").split(".")[1:])
        target = ".".join([*base, *([mod] if mod else [])])
        for a in node.names:
            sub = f"{target}.{a.name}" if target else a.name
            out.add(sub if sub in known else target)
    return {m for m in out if m in known and m != module}


@pytest.mark.parametrize("folder", [CORE, OPERATORS], ids=["core", "operators"])
def test_modules_import_each_other_without_cycles(folder):
    graph = {m: _imported_modules(folder, m) for m in _modules(folder)}
    state: dict[str, int] = {}

    def visit(m, path):
        if state.get(m) == 1:
            raise AssertionError(f"import cycle: {' -> '.join([*path, m])}")
        if state.get(m) == 2:
            return
        state[m] = 1
        for d in sorted(graph[m]):
            visit(d, [*path, m])
        state[m] = 2

    for m in graph:
        visit(m, [])


def test_the_core_is_one_subpackage_per_stage():
    top = sorted(p.name for p in CORE.iterdir() if not p.name.startswith((".", "__pycache__")))
    assert top == sorted(["__init__.py", "__main__.py", "_lazy.py", "meshutil.py", "version.py", *STAGE_PACKAGES]), top
    for pkg in STAGE_PACKAGES:  # every public name of a stage's modules is re-exported by its package
        init = importlib.import_module(f"ssm_addon.{pkg}")
        for m in _modules(CORE / pkg):
            if not m:
                continue
            module = importlib.import_module(f"ssm_addon.{pkg}.{m}")
            for name in getattr(module, "__all__", ()):
                assert name in init.__all__ and getattr(init, name) is getattr(module, name), (pkg, m, name)
        for name in init.__all__:  # and every name it re-exports exists
            assert hasattr(init, name), (pkg, name)


def test_the_public_api_and_the_old_module_paths():
    import warnings

    import ssm_addon

    for name in ("Study", "run", "read_project", "build", "ShapeModel", "load_model", "fit_model", "InputError"):
        assert name in ssm_addon.__all__ and getattr(ssm_addon, name) is not None
    for old, new in ssm_addon.MOVED_MODULES.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            mod = importlib.import_module(f"ssm_addon.{old}")
        assert mod is importlib.import_module(f"ssm_addon.{new}"), old
    from ssm_addon.project import build, read_project  # the documented imports of the flat layout

    assert build is ssm_addon.build and read_project is ssm_addon.read_project


#: One interpreter imports the libraries the core uses, then forks a child per core module: each child
#: starts with none of this repository's modules imported (none relies on another's side effects), without
#: paying the libraries' import again (the test took 26–32 s with one interpreter per module).
_FORKED_IMPORTS = """
import importlib, os, sys, traceback
import numpy, scipy, scipy.linalg, scipy.ndimage, scipy.sparse, scipy.sparse.csgraph, scipy.sparse.linalg
import scipy.spatial, scipy.spatial.transform, scipy.special, scipy.stats, scipy.fft, nibabel, skimage.measure
assert not [m for m in sys.modules if m.startswith("ssm_addon")]
failed = 0
for m in sys.argv[1:]:
    pid = os.fork()
    if pid == 0:
        try:
            importlib.import_module("ssm_addon." + m)
        except BaseException:
            sys.stderr.write("ssm_addon." + m + ": " + traceback.format_exc()[-1500:] + "\\n")
            sys.stderr.flush()
            os._exit(1)
        os._exit(0)
    failed += os.waitpid(pid, 0)[1] != 0
sys.exit(1 if failed else 0)
"""


@pytest.mark.slow
def test_each_core_module_imports_on_its_own_in_a_fresh_interpreter():
    modules = [m for m in _modules(CORE) if m]
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    if hasattr(os, "fork"):
        proc = subprocess.run([sys.executable, "-c", _FORKED_IMPORTS, *modules], cwd=ROOT, capture_output=True,
                              text=True, env=env)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "bpy" not in proc.stderr
        return
    code = "import importlib, sys\nfor m in sys.argv[1:]:\n    importlib.import_module('ssm_addon.' + m)\n"
    for m in modules:  # one interpreter per module: none relies on another's side effects
        proc = subprocess.run([sys.executable, "-c", code, m], cwd=ROOT, capture_output=True, text=True, env=env)
        assert proc.returncode == 0, f"ssm_addon.{m}: {proc.stderr[-1500:]}"
        assert "bpy" not in proc.stderr


def _core_module_aliases(tree: ast.AST, folder: Path) -> set[str]:
    """Local names bound to modules of this repository (``from . import bridge``, ``import … as P``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("ssm_addon")):
            names.update(a.asname or a.name for a in node.names if a.name[0].islower())
        if isinstance(node, ast.Import):
            names.update(a.asname or a.name for a in node.names if a.name.startswith("ssm_addon"))
    return names


def test_no_private_names_used_across_modules():
    """Neither imported (``from .x import _y``) nor reached by attribute (``meshutil._y``), by the core,
    the operators or the tests (a path a test needs is a public option of the function)."""
    offenders = []
    for folder in (CORE, OPERATORS, ROOT / "tests"):
        for path in sorted(folder.rglob("*.py")):
            tree = ast.parse(path.read_text())
            modules = _core_module_aliases(tree, folder)
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and (node.level > 0 or (node.module or "").startswith("ssm_addon")):
                    offenders += [f"{path.name}: {node.module}.{a.name}" for a in node.names
                                  if a.name.startswith("_") and not a.name.startswith("__")]
                if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in modules
                        and node.attr.startswith("_") and not node.attr.startswith("__")):
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value.id}.{node.attr}")
    assert not offenders, offenders


def test_operator_stage_modules_import_only_the_shared_blender_modules():
    stage_modules = set(_modules(OPERATORS)) - SHARED_OPERATOR_MODULES - {"", "project", "cli"}
    offenders = {m: sorted(_imported_modules(OPERATORS, m) - SHARED_OPERATOR_MODULES)
                 for m in sorted(stage_modules)}
    assert not {m: d for m, d in offenders.items() if d}, offenders


def test_read_frame_resample_exists_once():
    """Only ssm_addon.instances.importing chains reading, the object frame and resampling (paper 2)."""
    callers = {}
    for folder in (CORE, OPERATORS):
        for path in sorted(folder.rglob("*.py")):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, ast.Call):
                    f = node.func
                    name = f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", "")
                    if name in ("object_frame", "resample"):
                        callers.setdefault(name, set()).add(path.relative_to(ROOT).as_posix())
    assert callers["object_frame"] == {"ssm_addon/instances/importing.py"}, callers
    # resample is also the template's re-gridding and the mesh proposal's fallback, both on a given frame
    assert callers["resample"] <= {"ssm_addon/instances/importing.py", "ssm_addon/correspondence/proposal.py"}, callers


def test_every_parameter_has_a_project_key_and_a_command_line_option():
    from ssm_addon.cli.command import argument_parser

    parser = argument_parser()
    build_parser = parser._subparsers._group_actions[0].choices["build"]  # noqa: SLF001 - argparse has no public accessor
    flags = {opt for action in build_parser._actions for opt in action.option_strings}  # noqa: SLF001
    for section, cls in P.TABLES.items():
        keys = P.keys(cls)
        for s in P.specs(cls):
            assert s.key in keys and keys[s.key] is s
            assert f"--{section}-{s.key.replace('_', '-')}" in flags, (section, s.key)
            assert s.help and s.label
            if s.kind == "choice":
                assert s.default in s.choices
            # the default passes its own validation
            P.check_value(s, s.default, section)


def test_command_line_options_override_the_project(tmp_path):
    from ssm_addon.cli.command import argument_parser, with_overrides
    from ssm_addon.pipeline.project import Project

    args = argument_parser().parse_args(["build", "p.toml", "--out", "o", "--coating-k1", "0.3", "--template-spacing", "0.5",
                                 "--coating-registration-sigmas-mm", "8", "4", "--model-n-modes", "3"])
    project = Project(path=tmp_path / "p.toml", instances=(), template_instance="")
    changed = with_overrides(project, args)
    assert changed.params.coating.k1 == 0.3 and changed.params.template.spacing_mm == 0.5
    assert changed.params.coating.registration_sigmas_mm == (8.0, 4.0) and changed.params.model.n_modes == 3
    bad = argument_parser().parse_args(["build", "p.toml", "--out", "o", "--coating-k2", "0.1"])
    from ssm_addon.base.errors import InputError

    with pytest.raises(InputError, match="k2 .* must exceed k1"):
        with_overrides(project, bad)


def test_parameters_validated_with_the_allowed_range():
    from ssm_addon.base.errors import InputError

    with pytest.raises(InputError, match=r"coating parameters: dt must be a number > 0 and <= 2, got 100.0"):
        P.CoatingParams(dt=100.0)
    with pytest.raises(InputError, match=r"seed must be an integer >= 0"):
        P.TemplateParams(seed=-1)
    with pytest.raises(InputError, match=r"picture_modes must be an integer >= 1 and <= 10, got 0"):
        P.OutputParams(picture_modes=0)
    with pytest.raises(InputError, match=r"r_min_mm must be a number > 0 mm and <= 1000 mm, got nan"):
        P.TemplateParams(r_min_mm=float("nan"))
    assert P.shortest_float32(0.20000000298023224) == 0.2
    assert P.shortest_float32(1e-7) == float("1e-07")


@pytest.mark.slow
def test_pip_install_gives_a_working_ssm_command_from_any_folder(tmp_path):
    """``pip install .`` into a clean venv without bpy: ``ssm --help``, ``ssm info``, ``ssm build``."""
    wheels = tmp_path / "wheels"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation",
                           "-q", "-w", str(wheels)], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (wheel,) = wheels.glob("ssm_builder-*.whl")
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    py, ssm = env_dir / "bin" / "python", env_dir / "bin" / "ssm"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PIP_CACHE_DIR"] = str(REAL_HOME / ".cache" / "pip")
    proc = subprocess.run([str(py), "-m", "pip", "install", "-q", str(wheel)], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()

    def run(*args):
        return subprocess.run([str(ssm), *map(str, args)], capture_output=True, text=True, env=env, cwd=elsewhere,
                              timeout=600)

    assert subprocess.run([str(py), "-c", "import bpy"], capture_output=True, env=env).returncode != 0
    out = run("--help")
    assert out.returncode == 0 and "build" in out.stdout and "template" in out.stdout
    from ssm_addon.cli import demo

    project = demo.make_demo_population(tmp_path / "population", n=4, seed=2)
    lm = next((tmp_path / "population").glob("demo_*.nii.gz"))
    out = run("info", lm)
    assert out.returncode == 0 and "labels:" in out.stdout, out.stderr
    out = run("build", project, "--out", tmp_path / "model", "--template-r-min-mm", "4.5")
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "skipping model.blend" in out.stdout  # no bpy in this environment: said, not a traceback
    assert (tmp_path / "model" / "model.npz").is_file() and (tmp_path / "model" / "report.json").is_file()
    # the installed core is the one that ran (not the checkout's)
    where = subprocess.run([str(py), "-c", "import ssm_addon; print(ssm_addon.__file__)"], capture_output=True,
                           text=True, env=env, cwd=elsewhere)
    assert str(env_dir) in where.stdout


def test_parameter_reference_in_docs_is_generated_from_the_definitions():
    assert (ROOT / "docs" / "parameters.md").read_text() == P.markdown_tables() + "\n", (
        "docs/parameters.md is stale: run `python -m ssm_addon params > docs/parameters.md`")


def test_the_core_doctests_pass():
    """Every docstring example in the core runs and gives what it shows."""
    import doctest

    attempted = 0
    for m in _modules(CORE):
        module = importlib.import_module(f"ssm_addon.{m}" if m else "ssm_addon")
        result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS, verbose=False)
        assert result.failed == 0, f"ssm_addon.{m}: {result.failed} doctest(s) failed"
        attempted += result.attempted
    assert attempted >= 20, attempted


def _operator_classes():
    for path in sorted(OPERATORS.glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                yield path, node


def test_every_panel_is_an_ssm_sidebar_panel():
    """Panels take the sidebar placement from one base (``properties.SSMPanel``), not each their own."""
    panels = 0
    for path, cls in _operator_classes():
        bases = [ast.unparse(b) for b in cls.bases]
        if "bpy.types.Panel" in bases:
            panels += 1
            assert bases[0] == "SSMPanel", f"{path.name}: {cls.name} does not derive from SSMPanel"
        own = {t.id for n in cls.body if isinstance(n, ast.Assign) for t in n.targets if isinstance(t, ast.Name)}
        if cls.name != "SSMPanel":
            assert not own & {"bl_space_type", "bl_region_type", "bl_category"}, f"{path.name}: {cls.name}"
    assert panels >= 10, panels


def test_panels_draw_without_scanning_every_object():
    """``draw()`` runs at every redraw: it must not loop over ``bpy.data.objects`` (a look-up by
    name is fine)."""
    offenders = []
    for path, cls in _operator_classes():
        for fn in cls.body:
            if isinstance(fn, ast.FunctionDef) and fn.name in ("draw", "draw_item", "poll"):
                for node in ast.walk(fn):
                    if isinstance(node, ast.For | ast.comprehension) and ast.unparse(node.iter) == "bpy.data.objects":
                        offenders.append(f"{path.name}: {cls.name}.{fn.name}")
    assert not offenders, offenders


def test_the_build_path_does_not_import_scipy_stats():
    """``scipy.stats`` costs about 0.5 s and 20 MB per process to import; the build's modules
    (and every worker process that runs them) use ``scipy.special`` for distribution tails."""
    code = ("import sys\nimport ssm_addon.pipeline.project_build, ssm_addon.pipeline.study, ssm_addon.correspondence.rounds, "
            "ssm_addon.fitting.fit, ssm_addon.coating.coating\nprint('scipy.stats' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0 and proc.stdout.strip() == "False", proc.stdout + proc.stderr


#: The core's layers, bottom to top (docs/architecture.md). A package imports packages of the
#: layers below it and, within its own layer, only packages that do not import it back.
LAYERS = (
    ("", "_lazy", "version", "base", "meshutil"),  # foundation ("": the root package, whose names are lazy re-exports)
    ("formats", "instances", "template", "coating", "model", "fitting", "correspondence", "analysis",
     "segmentation"),  # stages
    ("pipeline",),  # orchestrator: the study, its stage functions, cache, project file
    ("cli",),  # the command line
)


def _package_graph() -> dict[str, set[str]]:
    """Imports between the core's top-level packages and modules (anywhere in a module)."""
    graph: dict[str, set[str]] = {}
    for m in _modules(CORE):
        src = m.split(".")[0]
        for d in _imported_modules(CORE, m):
            dst = d.split(".")[0]
            if dst != src:
                graph.setdefault(src, set()).add(dst)
    return graph


def test_packages_form_layers_whose_imports_point_down():
    """Foundation, stages, orchestrator, command line: no import runs from a lower layer to a
    higher one, and the packages import each other without a cycle, so every package has a floor."""
    graph = _package_graph()
    layer = {p: i for i, names in enumerate(LAYERS) for p in names}
    tops = {p.name.removesuffix(".py") for p in CORE.iterdir() if not p.name.startswith(("__", "."))} | {""}
    assert tops <= set(layer) | {"__main__"}, f"packages without a layer: {sorted(tops - set(layer))}"
    up = sorted(f"{a or 'ssm_addon'} -> {b}" for a, ds in graph.items() for b in ds if a in layer and layer[b] > layer[a])
    assert not up, f"imports that run up a layer: {up}"
    state: dict[str, int] = {}

    def visit(p, path):
        assert state.get(p) != 1, f"package import cycle: {' -> '.join([*path, p])}"
        if state.get(p) == 2:
            return
        state[p] = 1
        for d in sorted(graph.get(p, ())):
            visit(d, [*path, p])
        state[p] = 2

    for p in sorted(graph):
        visit(p, [])
    foundation = {p for p in LAYERS[0]}
    assert all(d in foundation for p in foundation for d in graph.get(p, ())), {p: graph.get(p) for p in foundation}


def _function_local_imports(path: Path):
    tree = ast.parse(path.read_text())
    parents = {c: n for n in ast.walk(tree) for c in ast.iter_child_nodes(n)}
    for node in ast.walk(tree):
        if not isinstance(node, ast.Import | ast.ImportFrom):
            continue
        up = node
        while up in parents and not isinstance(up, ast.FunctionDef | ast.AsyncFunctionDef):
            up = parents[up]
        if isinstance(up, ast.FunctionDef | ast.AsyncFunctionDef):
            yield node


def test_imports_stand_at_the_top_of_their_module():
    """A function-local import hides a dependency and fails only when the function runs: the core and
    the Blender layer import at the top, except the libraries and modules ``ssm_addon._lazy`` names."""
    from ssm_addon._lazy import DEFERRED_IMPORTS, DEFERRED_IN

    offenders = []
    for folder in (CORE, OPERATORS):
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            for node in _function_local_imports(path):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
                own = isinstance(node, ast.ImportFrom) and node.level > 0
                if not own and all(n.split(".")[0] in DEFERRED_IMPORTS for n in names):
                    continue
                if rel in DEFERRED_IN:
                    continue
                offenders.append(f"{rel}:{node.lineno}: {ast.unparse(node)}")
    assert not offenders, offenders


def test_the_architecture_page_names_every_package_module_and_parameter_class():
    """docs/architecture.md's package table is the code's: a row per package of the core (and
    ``meshutil.py``), each of the package's modules named in its row, and every parameter class of
    ``base/params.py`` named on the page."""
    import re

    page = (ROOT / "docs" / "architecture.md").read_text()
    rows = {}
    for line in page.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and re.fullmatch(r"`[a-z_]+(/|\.py)`", cells[1]):
            rows[cells[1].strip("`").rstrip("/")] = cells[3]
    packages = {p.name for p in CORE.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    assert set(rows) == packages | {"meshutil.py"}, sorted(set(rows) ^ (packages | {"meshutil.py"}))
    for pkg in packages:
        named = set(re.findall(r"`([a-z_]+)`", rows[pkg]))
        modules = {m.stem for m in (CORE / pkg).glob("*.py") if m.stem != "__init__"}
        assert modules <= named, (pkg, sorted(modules - named))
    classes = re.findall(r"^class (\w+Params)\b", (CORE / "base" / "params.py").read_text(), re.M)
    assert classes and all(f"`{c}`" in page for c in classes), [c for c in classes if f"`{c}`" not in page]
