"""The extension zip: manifest, build excludes, wheel selection, and a real install.

The slow test builds the linux-x64 zip with ``tools/build_extension.py`` (wheels cached in
``wheels_cache/``), then installs it the way a user does
(``bpy.ops.extensions.package_install_files``) into a ``bpy`` session in a separate
process whose Python sees only ``bpy`` and numpy, like Blender's own Python: every other
dependency must come from the zip's wheels.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
import time
import tomllib
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import build_tool, one_process_at_a_time

ROOT = Path(__file__).resolve().parents[1]


bx = build_tool()


def _has_bpy() -> bool:
    return importlib.util.find_spec("bpy") is not None


needs_bpy = pytest.mark.skipif(not _has_bpy(), reason="bpy not installed (blender_ext.py ships inside the bpy wheel)")


# --------------------------------------------------------------------------------------
# Fast tests: no download


def test_manifest_has_required_keys():
    with open(ROOT / "blender_manifest.toml", "rb") as fh:
        manifest = tomllib.load(fh)
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "ssm"
    assert manifest["type"] == "add-on"
    assert manifest["blender_version_min"] == "4.2.0"
    assert all(lic.startswith("SPDX:") for lic in manifest["license"])
    reason = manifest["permissions"]["files"]
    assert 0 < len(reason) <= 64 and not reason.endswith(".")
    assert manifest.get("wheels", []) == [], "the source manifest lists no wheels; the build fills them in"
    for key in ("version", "name", "tagline", "maintainer"):
        assert manifest[key]
    excludes = manifest["build"]["paths_exclude_pattern"]
    for path in ("/tests/", "/tools/", "/.venv/", "/docs/", "/.ci/", "/wheels_cache/", "/dist/"):
        assert path in excludes


@needs_bpy
def test_manifest_tags_are_blender_tags():
    tags_py = bx.blender_ext_path().parents[3] / "modules" / "_bpy_internal" / "extensions" / "tags.py"
    namespace: dict = {}
    exec(compile(tags_py.read_text(), str(tags_py), "exec"), namespace)  # a plain literal module
    with open(ROOT / "blender_manifest.toml", "rb") as fh:
        tags = tomllib.load(fh)["tags"]
    assert set(tags) <= namespace["addons"]


def test_extension_files_exclude_dev_files():
    files = [p.as_posix() for p in bx.extension_files(ROOT)]
    for needed in ("__init__.py", "blender_manifest.toml", "operators/__init__.py"):
        assert needed in files
    assert not any(str(f).startswith("ssm_addon") for f in files)  # bundled as a wheel instead
    for prefix in ("tests/", "tools/", ".venv/", "docs/", ".ci/", ".git/", "wheels_cache/", "dist/", "scripts/"):
        assert not any(f.startswith(prefix) for f in files), prefix
    assert not any("__pycache__" in f or f.endswith((".pyc", ".zip")) for f in files)
    assert "pyproject.toml" not in files


def test_runtime_requirements_never_include_numpy():
    reqs = bx.runtime_requirements(ROOT / "pyproject.toml")
    names = {bx._project_name(r.split(">")[0].split("=")[0].split("<")[0].strip()) for r in reqs}
    assert "numpy" not in names
    assert {"scipy", "scikit-image", "nibabel", "pynrrd", "h5py", "matplotlib"} <= names


def test_staged_manifest_lists_wheels_and_platforms():
    source = (ROOT / "blender_manifest.toml").read_text()
    wheels = ["scipy-1.17.1-cp311-cp311-win_amd64.whl", "nibabel-5.4.2-py3-none-any.whl"]
    staged = tomllib.loads(bx.staged_manifest_text(source, wheels, ["windows-x64", "linux-x64"]))
    assert staged["wheels"] == ["./wheels/" + w for w in wheels]
    assert staged["platforms"] == ["windows-x64", "linux-x64"]
    original = tomllib.loads(source)
    for key in ("id", "version", "permissions", "build", "license"):
        assert staged[key] == original[key]


def test_wheel_platforms_follow_blender_mapping():
    allp = ("linux-x64", "windows-x64", "macos-arm64", "macos-x64")
    assert bx.wheel_blender_platforms("a-1-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl", allp) == {
        "linux-x64"
    }
    assert bx.wheel_blender_platforms("a-1-cp311-cp311-win_amd64.whl", allp) == {"windows-x64"}
    assert bx.wheel_blender_platforms("a-1-cp311-cp311-macosx_10_9_universal2.whl", allp) == {"macos-x64", "macos-arm64"}
    assert bx.wheel_blender_platforms("a-1-py3-none-any.whl", allp[:2]) == {"linux-x64", "windows-x64"}


def _resolved(platform, names):
    return bx.PlatformWheels(platform, Path("/cache") / platform, list(names))


def test_merge_keeps_one_wheel_per_project_and_platform():
    merged = bx.merge_wheels([
        _resolved("macos-x64", ["fonttools-4.6-cp311-cp311-macosx_10_9_x86_64.whl", "cycler-0.12-py3-none-any.whl"]),
        _resolved("macos-arm64", ["fonttools-4.6-cp311-cp311-macosx_10_9_universal2.whl", "cycler-0.12-py3-none-any.whl"]),
        _resolved("linux-x64", ["fonttools-4.6-cp311-cp311-manylinux_2_17_x86_64.whl", "cycler-0.12-py3-none-any.whl"]),
    ])
    # universal2 covers both macOS platforms, the x86_64-only copy is dropped; the pure wheel is kept once.
    assert sorted(merged) == [
        "cycler-0.12-py3-none-any.whl",
        "fonttools-4.6-cp311-cp311-macosx_10_9_universal2.whl",
        "fonttools-4.6-cp311-cp311-manylinux_2_17_x86_64.whl",
    ]
    assert merged["cycler-0.12-py3-none-any.whl"] == Path("/cache/macos-x64/cycler-0.12-py3-none-any.whl")


def test_merge_refuses_two_versions_on_one_platform():
    with pytest.raises(bx.BuildError, match="cycler"):
        bx.merge_wheels([
            _resolved("linux-x64", ["cycler-0.12-py3-none-any.whl"]),
            _resolved("windows-x64", ["cycler-0.11-py3-none-any.whl"]),
        ])


def _fake_wheel(path: Path, requires: list[str]) -> Path:
    name, version = path.name.split("-")[:2]
    meta = f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n" + "".join(
        f"Requires-Dist: {r}\n" for r in requires
    )
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(f"{name}-{version}.dist-info/METADATA", meta)
    return path


def test_numpy_requirement_checked_against_every_blender_numpy(tmp_path):
    ok = _fake_wheel(tmp_path / "good-1.0-py3-none-any.whl", ["numpy<2.5,>=1.23.5", "numpy>=2; extra == 'fast'"])
    bx.check_numpy_compatible(ok)  # the extra is not installed, so numpy>=2 there does not count
    too_new = _fake_wheel(tmp_path / "new-1.0-py3-none-any.whl", ["numpy>=1.26.4"])
    with pytest.raises(bx.BuildError, match="new-1.0.*numpy 1.24.3"):  # Blender 4.2 LTS
        bx.check_numpy_compatible(too_new)
    numpy2 = _fake_wheel(tmp_path / "two-1.0-py3-none-any.whl", ["numpy>=2.0"])
    with pytest.raises(bx.BuildError, match="two-1.0"):
        bx.check_numpy_compatible(numpy2)
    assert bx.BLENDER_NUMPY == min(bx.BLENDER_NUMPYS, key=lambda v: tuple(map(int, v.split("."))))


def test_cli_rejects_unknown_platform(tmp_path, capsys):
    code = bx.main(["--platforms", "beos-x64", "--offline", "--cache", str(tmp_path), "--out", str(tmp_path)])
    assert code == 1
    assert "unknown platform 'beos-x64'" in capsys.readouterr().err
    assert not list(tmp_path.glob("*.zip"))


@pytest.mark.slow
@needs_bpy
def test_build_without_wheels_excludes_dev_files_and_validates(tmp_path):
    zips = bx.build(out_dir=tmp_path, cache=tmp_path / "cache", with_wheels=False, log=lambda *a: None)
    assert [z.name for z in zips] == ["ssm-0.1.0.zip"]
    names = zipfile.ZipFile(zips[0]).namelist()
    assert "__init__.py" in names and "blender_manifest.toml" in names and "operators/scene.py" in names
    # the core is in the zip once: as its wheel, imported as ssm_addon (not as a folder of the extension)
    assert "wheels/ssm_builder-0.1.0-py3-none-any.whl" in names
    assert not any(n.startswith("ssm_addon/") for n in names)
    assert [n for n in names if n.startswith("wheels/")] == ["wheels/ssm_builder-0.1.0-py3-none-any.whl"]
    for prefix in ("tests/", "tools/", ".venv/", "docs/", ".ci/"):
        assert not any(n.startswith(prefix) for n in names), prefix


# --------------------------------------------------------------------------------------
# Slow test: the real linux-x64 zip installed into a bpy session


INSTALL_SCRIPT = textwrap.dedent(
    r'''
    import json, os, sys, time, traceback
    zip_path, iso_dir, nifti = sys.argv[1:4]
    sys.path.insert(0, iso_dir)  # bpy and numpy only, like Blender's own Python
    out = {"errors": [], "seconds": {}}
    t0 = time.perf_counter()
    try:
        import bpy
        out["seconds"]["import_bpy"] = time.perf_counter() - t0
        import addon_utils
        prefs = bpy.context.preferences
        repo = next((r for r in prefs.extensions.repos if r.module == "user_default"), None)
        if repo is None:  # a user folder without the default local repository
            repo = prefs.extensions.repos.new(name="User", module="user_default")
        out["install"] = sorted(bpy.ops.extensions.package_install_files(
            filepath=zip_path, repo=repo.module, enable_on_install=True))
        out["seconds"]["install"] = time.perf_counter() - t0 - out["seconds"]["import_bpy"]
        out["addons"] = sorted(a.module for a in prefs.addons)
        out["addon_enabled"] = addon_utils.check("bl_ext.user_default.ssm")[1]
        site = os.path.join(os.environ["BLENDER_USER_EXTENSIONS"], ".local", "lib",
                            "python%d.%d" % sys.version_info[:2], "site-packages")
        out["site_packages"] = site
        import importlib
        mods = {}
        for name in ("scipy", "scipy.ndimage", "skimage.measure", "nibabel", "nrrd", "h5py", "matplotlib"):
            mods[name] = importlib.import_module(name).__file__
        out["modules"] = mods
        import numpy
        out["numpy"] = [numpy.__version__, numpy.__file__]
        out["object_has_ssm"] = hasattr(bpy.types.Object, "ssm")
        ops = sorted(dir(bpy.ops.ssm))
        out["ssm_ops"] = ops
        if "import_segmentation" in ops:
            before = set(bpy.data.objects.keys())
            t1 = time.perf_counter()
            out["import"] = sorted(bpy.ops.ssm.import_segmentation(filepath=nifti, label=1))
            out["seconds"]["import_segmentation"] = time.perf_counter() - t1
            new = [bpy.data.objects[n] for n in sorted(set(bpy.data.objects.keys()) - before)]
            out["imported"] = [{
                "name": o.name,
                "type": o.type,
                "label": int(o.ssm.label),
                "n_vertices": len(o.data.vertices) if o.type == "MESH" else 0,
                "collections": [c.name for c in o.users_collection],
                "world_vertices": [list(o.matrix_world @ v.co) for v in o.data.vertices] if o.type == "MESH" else [],
            } for o in new]
        # the core exists once, under its one name, from the extension's wheel
        core = sys.modules["ssm_addon"]
        out["core_file"] = core.__file__
        out["core_copies"] = sorted(k for k in sys.modules if k.endswith(".ssm_addon") or ".ssm_addon." in k)
        ops_scene = sys.modules["bl_ext.user_default.ssm.operators.scene"]
        out["one_study_class"] = ops_scene.Study is sys.modules["ssm_addon.pipeline.study"].Study
        # the workflow: a second instance, landmarks, template, coating, model
        bpy.ops.ssm.import_segmentation(filepath=nifti, label=3)
        insts = sorted((o for o in bpy.data.objects if o.ssm.role == "INSTANCE"), key=lambda o: o.ssm.label)
        for obj, path in zip(insts, sys.argv[4:6]):
            bpy.context.view_layer.objects.active = obj
            bpy.ops.ssm.import_landmarks(filepath=path, add_to_schema=True)
        bpy.context.view_layer.objects.active = insts[0]
        s = bpy.context.scene.ssm_template
        s.r_min_mm, s.r_max_mm = 2.0, 3.0
        out["template"] = sorted(bpy.ops.ssm.build_template())
        out["coat"] = sorted(bpy.ops.ssm.coat_template())
        out["model"] = sorted(bpy.ops.ssm.build_model())
        model = next(o for o in bpy.data.objects if o.ssm.role == "MODEL")
        out["mode_keys"] = [k.name for k in model.data.shape_keys.key_blocks]
    except Exception:
        out["errors"].append(traceback.format_exc())
    print("SSM_RESULT " + json.dumps(out))
    '''
)


def _isolated_python_path(dest: Path) -> Path:
    """A folder holding only ``bpy`` and numpy (symlinks into this venv)."""
    site = Path(importlib.util.find_spec("bpy").submodule_search_locations[0]).parent
    dest.mkdir()
    for entry in site.iterdir():
        if entry.name in ("bpy", "numpy", "numpy.libs") or entry.name.startswith(("numpy-", "bpy-")):
            (dest / entry.name).symlink_to(entry)
    return dest


def _write_ball_nifti(path: Path):
    """A 48x24x16 label map, 1x1x2 mm: label 1 a ball of radius 6 mm centred at voxel (10, 12, 8),
    label 2 a small block, label 3 an ellipsoid (8, 6.5, 6 mm) centred at voxel (34, 12, 8).

    Returns the ball's centre (world mm) and the six axis-extreme landmarks of the ball and
    of the ellipsoid as CSV files (``name,x,y,z``, world mm) next to ``path``.
    """
    nib = pytest.importorskip("nibabel")
    shape = (48, 24, 16)
    ijk = np.indices(shape).reshape(3, -1).T * np.array([1.0, 1.0, 2.0])
    ball_c, ell_c, ell_r = np.array([10.0, 12.0, 16.0]), np.array([34.0, 12.0, 16.0]), np.array([8.0, 6.5, 6.0])
    labels = np.zeros(len(ijk), np.int16)
    labels[np.linalg.norm(ijk - ball_c, axis=1) <= 6.0] = 1
    labels[(((ijk - ell_c) / ell_r) ** 2).sum(axis=1) <= 1.0] = 3
    labels = labels.reshape(shape)
    labels[20:23, 20:23, 1:3] = 2
    affine = np.diag([1.0, 1.0, 2.0, 1.0])
    affine[:3, 3] = (-30.0, 5.0, 40.0)
    nib.save(nib.Nifti1Image(labels, affine), str(path))
    csvs = []
    for tag, centre, radii in (("ball", ball_c, np.full(3, 6.0)), ("ellipsoid", ell_c, ell_r)):
        rows = []
        for k, axis in enumerate("xyz"):
            for sign, side in ((1, "plus"), (-1, "minus")):
                p = centre + affine[:3, 3]
                p[k] += sign * radii[k]
                rows.append(f"{axis}-{side},{p[0]!r},{p[1]!r},{p[2]!r}")
        csvs.append(path.with_name(f"{tag}.csv"))
        csvs[-1].write_text("name,x,y,z\n" + "\n".join(rows) + "\n")
    return ball_c + affine[:3, 3], csvs


def _build_linux_zip(out_dir: Path) -> Path:
    with one_process_at_a_time("wheels_cache"):  # it may download into wheels_cache/
        try:  # a warm cache needs no index
            zips = bx.build(["linux-x64"], out_dir=out_dir, offline=True, log=print)
        except bx.BuildError:
            zips = bx.build(["linux-x64"], out_dir=out_dir, offline=False, log=print)
    assert [z.name for z in zips] == ["ssm-0.1.0-linux_x64.zip"]
    return zips[0]


@pytest.mark.slow
@pytest.mark.blender
@needs_bpy
def test_linux_zip_installs_enables_and_imports(tmp_path):
    t0 = time.perf_counter()
    zip_path = _build_linux_zip(tmp_path / "dist")
    print(f"build: {time.perf_counter() - t0:.1f} s")
    print(f"zip: {zip_path.stat().st_size / 2**20:.1f} MB")
    bx.run_blender_ext("validate", str(zip_path))

    with zipfile.ZipFile(zip_path) as zf:
        names = zf.namelist()
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
    wheels = [n for n in names if n.startswith("wheels/")]
    assert manifest["build"]["generated"]["platforms"] == ["linux-x64"]
    assert sorted("./" + w for w in wheels) == sorted(manifest["build"]["generated"]["wheels"])
    assert not any(bx.wheel_project(Path(w).name) == "numpy" for w in wheels)
    projects = {bx.wheel_project(Path(w).name) for w in wheels}
    assert {"scipy", "scikit-image", "nibabel", "pynrrd", "h5py", "matplotlib"} <= projects
    assert not any(n.startswith(("tests/", "tools/", ".venv/")) for n in names)

    home = tmp_path / "home"
    env = dict(os.environ, HOME=str(home))
    for var, sub in (
        ("BLENDER_USER_RESOURCES", "blender"),
        ("BLENDER_USER_CONFIG", "blender/config"),
        ("BLENDER_USER_SCRIPTS", "blender/scripts"),
        ("BLENDER_USER_EXTENSIONS", "blender/extensions"),
        ("BLENDER_USER_DATAFILES", "blender/datafiles"),
    ):
        env[var] = str(home / sub)
        Path(env[var]).mkdir(parents=True, exist_ok=True)
    env.pop("PYTHONPATH", None)
    iso = _isolated_python_path(tmp_path / "iso")
    nifti = tmp_path / "ball.nii.gz"
    centre_world, landmark_files = _write_ball_nifti(nifti)
    script = tmp_path / "install_and_run.py"
    script.write_text(INSTALL_SCRIPT)

    proc = subprocess.run(
        [sys.executable, "-S", str(script), str(zip_path), str(iso), str(nifti), *map(str, landmark_files)],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("SSM_RESULT ")]
    assert lines, f"no result (exit {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    result = json.loads(lines[-1][len("SSM_RESULT "):])
    print(json.dumps({k: result.get(k) for k in ("seconds", "install", "addon_enabled", "ssm_ops", "import")}))
    assert not result["errors"], "\n".join(result["errors"])

    assert result["install"] == ["FINISHED"]
    assert "bl_ext.user_default.ssm" in result["addons"]
    assert result["addon_enabled"]
    # Every dependency comes from the wheels Blender unpacked for the extension ...
    site = Path(result["site_packages"])
    for name, file in result["modules"].items():
        assert Path(file).is_relative_to(site), f"{name} imported from {file}, not from the extension's wheels"
    # ... except numpy, which is Blender's.
    assert result["numpy"][0].startswith("1.26")
    assert not Path(result["numpy"][1]).is_relative_to(site)
    assert result["object_has_ssm"], "the add-on's register() did not run (Object.ssm missing)"

    assert "import_segmentation" in result["ssm_ops"], f"ssm operators registered: {result['ssm_ops']}"
    assert result["import"] == ["FINISHED"]
    meshes = [o for o in result["imported"] if o["type"] == "MESH"]
    assert len(meshes) == 1, result["imported"]
    ball = meshes[0]
    assert ball["label"] == 1
    assert "SSM Instances" in ball["collections"]
    verts = np.array(ball["world_vertices"])
    assert len(verts) > 100
    # The surface of the 6 mm ball sits at its world position (mm), within a voxel.
    assert np.linalg.norm(verts.mean(axis=0) - centre_world) < 1.0
    radii = np.linalg.norm(verts - centre_world, axis=1)
    assert 4.5 < radii.min() and radii.max() < 7.5
    # one core: the wheel's ssm_addon, no second copy under the extension's package
    assert Path(result["core_file"]).is_relative_to(site), result["core_file"]
    assert result["core_copies"] == [] and result["one_study_class"]
    # and the workflow runs: template, coating, model with one mode for two instances
    assert (result["template"], result["coat"], result["model"]) == (["FINISHED"],) * 3
    assert result["mode_keys"] == ["Basis", "Mode 1"]
