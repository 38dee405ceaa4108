"""Shared fixtures.

* Blender tests import the ``bpy`` module from PyPI with HOME and Blender's user folders
  pointed at a temporary directory, so nothing is written into the real home.
* The repo root (the extension) is importable as the package ``ssm`` (the way Blender
  loads it as ``bl_ext.<repo>.ssm``), so ``operators`` can import ``..ssm_addon``.
* ``verse_dir`` is the real VerSe sample in ``../shared/data/verse004``; tests that
  need it skip with a reason where it is absent (a user's fresh clone).
* ``scripts/test.sh`` runs the test files in several processes (pytest-xdist, a file per
  process at a time): what two files share on disk (``wheels_cache/``) is written by one
  process at a time (:func:`one_process_at_a_time`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib.util
import os
import re
import struct
import sys
import tempfile
from pathlib import Path

try:
    import fcntl
except ImportError:  # Windows: the suite runs in one process there (no shared writes to guard)
    fcntl = None
import h5py
import numpy as np
import pytest
from scipy.spatial import ConvexHull

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


def as_from_a_terminal() -> None:
    """``preexec_fn`` of a child the tests interrupt: SIGINT and SIGQUIT at their defaults, as a
    terminal starts a command. A shell without job control starts background commands with
    both ignored (POSIX), and a Python started so never raises KeyboardInterrupt: a suite run
    in the background (``nohup``, some CI runners) would otherwise test nothing of Ctrl-C."""
    import signal

    for name in ("SIGINT", "SIGQUIT"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)


@functools.cache
def build_tool():
    """``tools/build_extension.py`` as a module (it is a script, not part of the package)."""
    spec = importlib.util.spec_from_file_location("build_extension", ROOT / "tools" / "build_extension.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("build_extension", module)
    spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def one_process_at_a_time(name: str):
    """Hold an exclusive lock (a file in the system's temp folder, one per checkout and
    ``name``) for the block: test processes that write the same files take turns."""
    if fcntl is None:
        yield
        return
    path = Path(tempfile.gettempdir()) / f"ssm-tests-{hashlib.sha1(str(ROOT).encode()).hexdigest()[:12]}-{name}.lock"
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def zip_wheels() -> Path:
    """``wheels_cache/linux-x64``: the wheels the linux-x64 extension zip bundles, resolved and
    downloaded here when the cache lacks them (a warm cache needs no index), so a test that
    needs them runs alone as in the full suite. Skips where they cannot be had (no network)."""
    bx = build_tool()
    cache = ROOT / "wheels_cache"
    requirements = bx.runtime_requirements()
    with one_process_at_a_time("wheels_cache"):
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
        if self.__dict__.get("active", True) is False:  # greyed out (row.active = False)
            self.log.append(("inactive", prop))

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


# --------------------------------------------------------------------------------------
# Shapes, populations and project files shared by several test modules
# --------------------------------------------------------------------------------------

# ---------------------------------------------------------------------------------------
# synthetic shapes with known answers
# ---------------------------------------------------------------------------------------
def sphere_points(n_points: int = 200, radius_mm: float = 20.0) -> np.ndarray:
    """Fibonacci points on a sphere: (N, 3) mm."""
    i = np.arange(n_points) + 0.5
    phi = np.arccos(1 - 2 * i / n_points)
    theta = np.pi * (1 + 5**0.5) * i
    return radius_mm * np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def smooth_fields(base: np.ndarray) -> np.ndarray:
    """Three orthonormal (as 3N vectors) smooth displacement fields on ``base``: (3, N, 3).

    Radial growth, an x stretch and a bend of z with x²; Gram-Schmidt orthonormalised.
    """
    r = base / np.linalg.norm(base, axis=1, keepdims=True)
    stretch = np.zeros_like(base)
    stretch[:, 0] = base[:, 0]
    bend = np.zeros_like(base)
    bend[:, 2] = base[:, 0] ** 2
    q, _ = np.linalg.qr(np.stack([r.ravel(), stretch.ravel(), bend.ravel()], axis=1))
    return q.T.reshape(3, -1, 3)


def synthetic_population(n=60, n_points=200, variances=(25.0, 9.0, 4.0), noise_mm=0.01, seed=1):
    """Shapes = mean + Σ b_k f_k + noise with known fields f_k and exact sample variances λ_k.

    Returns (shapes (n, N, 3), mean (N, 3), fields (3, N, 3), variances (3,)).
    """
    rng = np.random.default_rng(seed)
    mean = sphere_points(n_points)
    fields = smooth_fields(mean)
    coeff = rng.standard_normal((n, 3))
    coeff -= coeff.mean(axis=0)
    q, _ = np.linalg.qr(coeff)  # zero-mean, orthonormal columns: exact, uncorrelated sample variances
    b = q * np.sqrt(n * np.asarray(variances))[None]
    shapes = mean[None] + np.tensordot(b, fields, axes=1) + noise_mm * rng.standard_normal((n, n_points, 3))
    return shapes, mean, fields, np.asarray(variances, float)


FACES = np.array([[0, 1, 2], [0, 2, 3], [1, 2, 3]])


def names(n):
    return [f"inst{i:02d}" for i in range(n)]


def random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


# 14 landmark directions: the six axes and the eight diagonals (like the VerSe files)
DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    + [[sx, sy, sz] for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)],
    dtype=float,
)


DIRECTIONS /= np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


def ellipsoid_landmarks(axes_mm):
    """(14, 3) points of the ellipsoid surface along DIRECTIONS."""
    return DIRECTIONS / np.sqrt(((DIRECTIONS / np.asarray(axes_mm, float)) ** 2).sum(1, keepdims=True))


def icosphere(radius: float = 1.0, subdivisions: int = 3):
    """Outward-oriented icosphere of ``radius`` (mm): (V, 3) vertices, (F, 3) faces (642 vertices at 3 subdivisions)."""
    t = (1 + 5**0.5) / 2
    v = np.array(
        [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
         [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float
    )  # fmt: skip
    f = np.array(
        [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
         [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
         [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    )  # fmt: skip
    v /= np.linalg.norm(v, axis=1)[:, None]
    for _ in range(subdivisions):
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        ue, inv = np.unique(e, axis=0, return_inverse=True)
        mid = v[ue].mean(axis=1)
        mid /= np.linalg.norm(mid, axis=1)[:, None]
        m = inv.reshape(3, -1).T + len(v)
        v = np.vstack([v, mid])
        a, b, c = f.T
        ab, bc, ca = m.T
        f = np.concatenate(
            [np.stack([a, ab, ca], 1), np.stack([b, bc, ab], 1), np.stack([c, ca, bc], 1), np.stack([ab, bc, ca], 1)]
        )
    return v * radius, f


def write_stl_binary(path, v, f):
    tri = v[f].astype("<f4")
    with open(path, "wb") as fh:
        fh.write(b"binary stl".ljust(80, b" ") + struct.pack("<I", len(f)))
        rec = np.zeros(len(f), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
        rec["v"] = tri
        fh.write(rec.tobytes())


def ellipsoid_mesh(radii=(30.0, 20.0, 14.0), n=24, centre=(0.0, 0.0, 0.0)):
    """A closed, outward triangle mesh of an ellipsoid_mesh (mm)."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n, endpoint=False), np.linspace(0, np.pi, n // 2 + 1)[1:-1])
    ring = np.stack([np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v)], axis=-1).reshape(-1, 3)
    pts = np.vstack([[0, 0, 1], ring, [0, 0, -1]]) * np.asarray(radii) + np.asarray(centre)
    rows, cols = n // 2 - 1, n
    idx = lambda r, c: 1 + r * cols + c % cols  # noqa: E731
    faces = [[0, idx(0, c), idx(0, c + 1)] for c in range(cols)]
    for r in range(rows - 1):
        for c in range(cols):
            faces += [[idx(r, c), idx(r + 1, c), idx(r + 1, c + 1)], [idx(r, c), idx(r + 1, c + 1), idx(r, c + 1)]]
    last = len(pts) - 1
    faces += [[last, idx(rows - 1, c + 1), idx(rows - 1, c)] for c in range(cols)]
    faces = np.array(faces)
    tri = pts[faces]
    if np.einsum("ij,ij->i", np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), tri.mean(1) - pts.mean(0)).sum() < 0:
        faces = faces[:, ::-1]
    return pts, faces


def union_mesh(parts, spacing_mm: float = 0.5):
    """One closed surface of overlapping closed meshes ``[(vertices, faces), ...]`` (mm): the
    marching cubes of their voxelized union at ``spacing_mm``."""
    from ssm_addon.instances.voxelize import voxelize_mesh
    from ssm_addon.meshutil import marching_cubes

    h = float(spacing_mm)
    volumes = [voxelize_mesh(v, f, h) for v, f in parts]
    lo = np.min([v.affine[:3, 3] for v in volumes], axis=0)
    shape = np.max([np.array(v.mask.shape) + (v.affine[:3, 3] - lo) / h for v in volumes], axis=0).astype(int) + 2
    union = np.zeros(shape, bool)
    for v in volumes:
        o = np.round((v.affine[:3, 3] - lo) / h).astype(int)
        union[o[0]:o[0] + v.mask.shape[0], o[1]:o[1] + v.mask.shape[1], o[2]:o[2] + v.mask.shape[2]] |= v.mask
    mv, mf = marching_cubes(union)
    return mv * h + lo, mf


def spiked_project(folder: Path, shapes, header=(), *, landmarks=None) -> Path:
    """A project of ellipsoids with a thin spike along +x, as RAS PLY meshes (``s0``, ``s1``, …).

    ``shapes``: ``(spike length, body radii)`` per instance (mm; the spike 3.2 mm thick, its root
    3 mm inside the body); ``header``: the project's lines before the instances; ``landmarks``:
    the instances given landmark files (default all: the spike's tip and the body's poles, CSV).
    """
    folder.mkdir(parents=True, exist_ok=True)
    from ssm_addon.formats.meshes import write_ply

    lines = list(header) + [""]
    for i, (length, radii) in enumerate(shapes):
        body, bf = ellipsoid_mesh(radii, n=32)
        spike, sf = ellipsoid_mesh((length, 1.6, 1.6), n=16, centre=(radii[0] + length - 3.0, 0.0, 0.0))
        verts, faces = union_mesh([(body, bf), (spike, sf)])
        name = f"s{i}"
        write_ply(folder / f"{name}.ply", verts, faces, space="RAS")
        lines += ["[[instances]]", f'name = "{name}"', f'mesh = "{name}.ply"']
        if landmarks is None or name in landmarks:
            tips = verts[[np.argmax(verts[:, 0]), np.argmin(verts[:, 0]), np.argmax(verts[:, 1]),
                          np.argmin(verts[:, 1]), np.argmax(verts[:, 2]), np.argmin(verts[:, 2])]]
            (folder / f"{name}.csv").write_text("".join(f"{n},{x},{y},{z}\n" for n, (x, y, z) in zip("ABCDEF", tips)))
            lines.append(f'landmarks = "{name}.csv"')
        lines.append("")
    (folder / "project.toml").write_text("\n".join(lines))
    return folder / "project.toml"


def write_foreign_statismo(model, path):
    """``model`` as another tool writes a statismo file (the 0.9 layout, float32, no SSM
    extras and no training instances); returns ``path``."""
    with h5py.File(path, "w") as f:
        f.create_group("version")
        f["version/majorVersion"], f["version/minorVersion"] = np.int32(0), np.int32(9)
        f["model/mean"] = model.mean.reshape(-1).astype(np.float32)
        f["model/pcaBasis"] = model.modes.reshape(model.n_modes, -1).T.astype(np.float32)
        f["model/pcaVariance"] = model.variances.astype(np.float32)
        f["model/noiseVariance"] = np.float32(0.0)
        rep = f.create_group("representer")
        rep.attrs["name"] = "itkStandardMeshRepresenter"
        rep.attrs["datasetType"] = "POLYGON_MESH"
        rep["points"] = model.mean.T.astype(np.float32)
        rep["cells"] = np.asarray(model.faces, np.int32).T
        f.create_group("modelinfo")["build-time"] = "2026-01-01"
    return path


def femur10_meshes(folder: Path) -> tuple[list[Path], np.ndarray, np.ndarray]:
    """femur10's files, vertices (10, N, 3) mm and their shared faces."""
    from ssm_addon.formats.meshes import read_mesh

    files = sorted(folder.glob("femur*.ply"))
    meshes = [read_mesh(f) for f in files]
    return files, np.stack([np.asarray(v, float) for v, _f in meshes]), np.asarray(meshes[0][1])


def write_verse_project(folder: Path, verse_dir: Path, template: str = "L1") -> Path:
    """A project file with absolute paths to the VerSe label map and landmark files."""
    lines = ["[template]", f'instance = "{template}"', "spacing = 1.0", "", "[model]", 'alignment = "none"', ""]
    for name, label in VERSE_LABELS.items():
        lines += [
            "[[instances]]",
            f'name = "{name}"',
            f'volume = "{(verse_dir / VERSE_FILE.name).as_posix()}"',
            f"label = {label}",
            f'landmarks = "{(verse_dir / "landmarks" / f"{name}.fcsv").as_posix()}"',
            "",
        ]
    path = folder / "verse.toml"
    path.write_text("\n".join(lines))
    return path


def axis_rotation(axis, degrees):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def joint_population(n=12, seed=0, turn_sd=6.0):
    """Two ellipsoids per subject: ``b`` beside ``a``, turned about z and moved by a known amount."""
    rng = np.random.default_rng(seed)
    va, fa = ellipsoid_mesh((20.0, 12.0, 10.0), n=16)
    vb, fb = ellipsoid_mesh((10.0, 8.0, 8.0), n=12)
    a, b, turns = [], [], []
    for _ in range(n):
        scale = 1.0 + 0.05 * rng.normal()
        turn = turn_sd * rng.normal()
        rot = axis_rotation([0, 0, 1], turn)
        a.append(va * scale)
        b.append((vb * (1.0 + 0.05 * rng.normal())) @ rot.T + [32.0 + rng.normal(), 0.0, 0.0])
        turns.append(turn)
    return np.stack(a), np.stack(b), fa, fb, np.array(turns)


def joint_model(shapes_a, shapes_b, faces_a, faces_b, *, alignment="none"):
    from ssm_addon.model.pca import build_model

    pts = np.concatenate([shapes_a, shapes_b], axis=1)
    faces = np.concatenate([faces_a, faces_b + shapes_a.shape[1]])
    model = build_model(pts, faces, [f"s{i}" for i in range(len(pts))], alignment=alignment)
    return dataclasses.replace(model, structure_names=("a", "b"),
                               structure_offsets=np.array([0, shapes_a.shape[1], pts.shape[1]]))


def joint_project(folder, n, header=(), *, ages=False, name="project.toml"):
    """A joint project of ``n`` subjects of :func:`joint_population` as other tools write them: each
    structure a Slicer PLY, four landmarks A-D per structure in Scalismo JSON; ``header``: the
    project's tables; ``ages``: an ``age`` attribute per subject. Returns its path."""
    from foreign_data import scalismo_landmarks, slicer_ply

    a, b, fa, fb, _t = joint_population(n=n)
    lines = list(header)
    for i in range(n):
        s = f"S{i}"
        slicer_ply(folder / f"{s}_a.ply", a[i], fa, space=None)
        slicer_ply(folder / f"{s}_b.ply", b[i], fb, space=None)
        scalismo_landmarks(folder / f"{s}_a.json", list("ABCD"), a[i][[0, 5, 40, 100]])
        scalismo_landmarks(folder / f"{s}_b.json", list("ABCD"), b[i][[0, 5, 30, 50]])
        lines += ["[[instances]]", f'name = "{s}"', f'meshes = {{ a = "{s}_a.ply", b = "{s}_b.ply" }}',
                  f'landmarks = {{ a = "{s}_a.json", b = "{s}_b.json" }}']
        lines += [f"attributes = {{ age = {30 + 7 * i} }}"] if ages else []
        lines.append("")
    path = folder / name
    path.write_text("\n".join(lines))
    return path


def project_variant(path, name: str, *, correspondence: str = "", keep_landmarks=None):
    """The project with a [correspondence] table and landmarks kept on ``keep_landmarks`` only."""
    text = path.read_text()
    if keep_landmarks is not None:
        blocks = text.split("[[instances]]")
        for i, block in enumerate(blocks[1:], start=1):
            inst = re.search(r'name = "([^"]+)"', block).group(1)
            if inst not in keep_landmarks:
                blocks[i] = re.sub(r'landmarks = "[^"]+"\n', "", block)
        text = "[[instances]]".join(blocks)
    text = text.replace("[coating]", f"{correspondence}\n\n[coating]") if correspondence else text
    out = path.with_name(name)
    out.write_text(text)
    return out


def template_of(path) -> str:
    from ssm_addon.pipeline.project import read_project

    return read_project(path).template_instance


def object_frame_of(mask, affine):
    """The object frame of paper section 2 (volume.object_frame, patient axes)."""
    from ssm_addon.formats.label_maps import Volume
    from ssm_addon.instances import frame as FR

    return FR.object_frame(Volume(mask, affine, "verse", None, True))


ANALYSIS_RADIUS_MM = 20.0


ANALYSIS_NOISE_MM = 0.3


BUMP_MM = 2.0


AGE_STRETCH = 0.002  # relative x stretch per year: 0.04 mm/year at x = 20 mm


def analysis_population(n=30, seed=0, bump=BUMP_MM, stretch=AGE_STRETCH):
    """Spheres (R = 20 mm) with a known group displacement (an outward bump of ``bump`` mm on the
    cap z > 0.8 R for 'patient') and a known linear age effect (x scaled by 1 + stretch (age − 60)),
    plus independent noise of ANALYSIS_NOISE_MM per coordinate."""
    from ssm_addon.analysis import attributes_from_tables
    from ssm_addon.model.pca import build_model

    v, f = icosphere(subdivisions=3)
    v = v * ANALYSIS_RADIUS_MM
    rng = np.random.default_rng(seed)
    groups = np.array(["control", "patient"] * (n // 2))
    age = rng.uniform(40, 80, n)
    cap = v[:, 2] > 0.8 * ANALYSIS_RADIUS_MM
    bump_field = np.where(cap, bump, 0.0)[:, None] * v / ANALYSIS_RADIUS_MM
    pts = np.repeat(v[None], n, axis=0)
    pts[:, :, 0] *= 1 + stretch * (age[:, None] - 60)
    pts[groups == "patient"] += bump_field
    pts += rng.normal(scale=ANALYSIS_NOISE_MM, size=pts.shape)
    names = [f"s{i:02d}" for i in range(n)]
    model = build_model(pts, f, names)
    attrs = attributes_from_tables({nm: {"group": g, "age": a} for nm, g, a in zip(names, groups, age)})
    return model, attrs, {"cap": cap, "bump": bump_field, "age_effect": np.c_[stretch * v[:, 0], 0 * v[:, :2]],
                          "age": age, "groups": groups, "sphere": v}


N_INST = 10


def coated_population():
    """Ten synthetic shapes (120 points) with known frames, as coated instances hold them: (shapes, faces, frames)."""
    shapes, mean, fields, lam = synthetic_population(n=N_INST, n_points=120, noise_mm=0.2, seed=3)
    faces = ConvexHull(mean).simplices
    rng = np.random.default_rng(0)
    frames = [(rng.normal(scale=50, size=3), random_rotation(rng)) for _ in range(N_INST)]
    return shapes, faces, frames


def add_coated(bpy, population, n=N_INST):
    """Coated instances as the coating stage leaves them: object-frame points, an instance with a frame."""
    from ssm.operators import bridge, scene
    from ssm.operators.coating import write_coated
    from ssm.operators.template import write_template_object

    from ssm_addon.coating.coating import CoatingResult, FitFigures
    from ssm_addon.instances.volume import ObjectFrame
    from ssm_addon.template.template import Template

    shapes, faces, frames = population
    ctx = bpy.context
    for i in range(n):
        inst = bridge.new_mesh_object(ctx, f"V{i:02d}", np.zeros((0, 3)), np.zeros((0, 3), int), "SSM Instances")
        inst.ssm.role = "INSTANCE"
        inst.ssm.order = i
        frame = ObjectFrame(np.asarray(frames[i][0], float), np.asarray(frames[i][1], float))
        scene.write_frame(inst, frame, frame.matrix_world)
        bridge.set_matrix_world(inst, frame.matrix_world)
        if i == 0:
            write_template_object(ctx, inst, Template(shapes[0], faces, np.zeros(len(shapes[0])), frame))
        fit = FitFigures(mean_distance_mm=0.1 * i, max_distance_mm=0.2 * i, folded_before=0, folded_after=0,
                         iterations=10)
        write_coated(ctx, inst, CoatingResult(shapes[i], shapes[i], fit, f"V{i:02d}"), faces, shapes[0])
