"""Shared fixtures.

* Blender tests import the ``bpy`` module from PyPI with HOME and Blender's user folders
  pointed at a temporary directory, so nothing is written into the real home.
* The repo root (the extension) is importable as the package ``ssm`` (the way Blender
  loads it as ``bl_ext.<repo>.ssm``), so ``operators`` can import ``..ssm_addon``.
* ``verse_dir`` is the real VerSe sample in ``../shared/data/verse004``; tests that
  need it skip with a reason where it is absent (a user's fresh clone).
"""

from __future__ import annotations

import functools
import importlib.util
import os
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: The user's real home, before the tests point HOME elsewhere (pip's download cache lives there).
REAL_HOME = Path(os.path.expanduser("~"))
_TMP_HOME = tempfile.mkdtemp(prefix="ssm-test-home-")
for _var, _sub in (
    ("HOME", ""),
    ("BLENDER_USER_RESOURCES", "blender"),
    ("BLENDER_USER_CONFIG", "blender/config"),
    ("BLENDER_USER_SCRIPTS", "blender/scripts"),
    ("BLENDER_USER_EXTENSIONS", "blender/extensions"),
    ("BLENDER_USER_DATAFILES", "blender/datafiles"),
):
    os.environ[_var] = os.path.join(_TMP_HOME, _sub)
    os.makedirs(os.environ[_var], exist_ok=True)

# matplotlib's font cache survives between sessions (HOME above is new every run).
os.environ.setdefault("MPLCONFIGDIR", str(ROOT / ".cache" / "matplotlib"))
os.makedirs(os.environ["MPLCONFIGDIR"], exist_ok=True)

if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))


def shared_data_dir() -> Path:
    """``$SSM_SHARED_DATA`` or ``<repo>/../shared/data``."""
    env = os.environ.get("SSM_SHARED_DATA")
    return Path(env) if env else ROOT.parent / "shared" / "data"


VERSE_DIR = shared_data_dir() / "verse004"
FEMUR10_DIR = shared_data_dir() / "femur10"
KNEE30_DIR = shared_data_dir() / "knee30"
VERSE_FILE = VERSE_DIR / "sub-verse004_seg-vert_msk.nii.gz"
VERSE_LABELS = {"T9": 16, "T10": 17, "T11": 18, "T12": 19, "L1": 20, "L2": 21, "L3": 22, "L4": 23, "L5": 24}


@functools.lru_cache(maxsize=3)
def knee30_bone(bone: str):
    """(names, (30, V, 3) vertices in mm, (F, 3) faces) of one knee30 bone (``"Patella"``,
    ``"Tibia"``, ``"Femur"``): every subject's mesh shares the faces, so vertex i is the same
    place on all. Skips the test where the data is absent."""
    import numpy as np

    from ssm_addon.formats.meshes import read_mesh

    files = sorted(KNEE30_DIR.glob(f"*_{bone}.ply"))
    if len(files) < 30:
        pytest.skip(f"knee30 not found at {KNEE30_DIR} (set SSM_SHARED_DATA or place ../shared/data)")
    meshes = [read_mesh(f) for f in files]
    return [f.stem for f in files], np.stack([v for v, _f in meshes]), meshes[0][1]


@pytest.fixture(scope="session")
def verse_dir() -> Path:
    if not VERSE_FILE.exists():
        pytest.skip(f"real VerSe data not found at {VERSE_DIR} (set SSM_SHARED_DATA or place ../shared/data)")
    return VERSE_DIR


@functools.cache
def build_tool():
    """``tools/build_extension.py`` as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("build_extension", ROOT / "tools" / "build_extension.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("build_extension", module)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def zip_wheels() -> Path:
    """``wheels_cache/linux-x64``: the wheels the linux-x64 extension zip bundles, resolved and
    downloaded here when the cache lacks them (a warm cache needs no index), so a test that
    needs them runs alone as in the full suite. Skips where they cannot be had (no network)."""
    bx = build_tool()
    cache = ROOT / "wheels_cache"
    requirements = bx.runtime_requirements()
    try:
        bx.download_wheels("linux-x64", requirements, cache, offline=True, log=lambda *a: None)
    except bx.BuildError:
        try:
            bx.download_wheels("linux-x64", requirements, cache, offline=False, log=print)
        except bx.BuildError as err:
            pytest.skip(f"the zip's wheels cannot be downloaded here: {err}")
    return cache / "linux-x64"


def load_extension_package(name: str = "ssm"):
    """Import the repo root as the package ``name`` (as Blender imports an extension)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, ROOT / "__init__.py", submodule_search_locations=[str(ROOT)])
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def bpy_module():
    """The ``bpy`` module with SSM Builder registered (skips if bpy is not installed)."""
    bpy = pytest.importorskip("bpy", reason="bpy module not installed (pip install bpy==5.0.1 on Python 3.11)")
    pkg = load_extension_package()
    pkg.register()
    yield bpy
    try:
        pkg.unregister()
    except Exception:  # noqa: BLE001 - best effort at interpreter exit
        pass


@pytest.fixture()
def bpy_clean(bpy_module):
    """A factory-empty scene for one test, with SSM Builder registered."""
    bpy = bpy_module
    bpy.ops.wm.read_homefile(use_empty=True)
    yield bpy


class RecordingLayout:
    """A stand-in for UILayout: records labels, asserts props and operators exist."""

    def __init__(self, log):
        self.log = log

    def __getattr__(self, name):  # row, column, box, split, separator, progress, ...
        return lambda *a, **k: RecordingLayout(self.log)

    def label(self, text="", **kw):
        self.log.append(("label", text))

    def prop(self, data, prop, **kw):
        if prop.startswith('["') and prop.endswith('"]'):  # an ID property (a joint model's mode slider)
            assert prop[2:-2] in data.keys(), f"{data.name}{prop}"
        else:
            assert prop in data.bl_rna.properties, f"{type(data).__name__}.{prop}"
        self.log.append(("prop", prop))

    def operator(self, idname, **kw):
        import bpy

        group, name = idname.split(".")
        assert hasattr(getattr(bpy.ops, group), name), idname
        self.log.append(("operator", idname))
        return type("Props", (), {})()

    def operator_menu_enum(self, idname, prop, **kw):
        self.operator(idname)

    def template_list(self, list_type, list_id, data, prop, active_data, active_prop, **kw):
        import bpy

        assert hasattr(bpy.types, list_type)
        assert prop in data.bl_rna.properties and active_prop in active_data.bl_rna.properties
        self.log.append(("list", prop))


@pytest.fixture()
def layout_recorder():
    """The :class:`RecordingLayout` class: ``layout_recorder(log)`` stands in for a UILayout."""
    return RecordingLayout
