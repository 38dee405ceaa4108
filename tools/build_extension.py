"""Build the SSM Builder extension zips, one per platform, with every dependency bundled.

Plain Python, no Blender program: the build and validation are done by Blender's own
``blender_ext.py`` that ships inside the ``bpy`` wheel
(``bpy/<version>/scripts/addons_core/bl_pkg/cli/blender_ext.py``).

Steps
-----
1. For each platform, ``pip download --only-binary=:all: --python-version 3.11`` the
   runtime dependencies from ``pyproject.toml`` (except numpy) into
   ``wheels_cache/<platform>/``. Blender 4.2-5.0 ships Python 3.11 with its own numpy
   (1.24.3 in 4.2 LTS, 1.26.4 in 4.5 LTS and 5.0), so the resolution is constrained to
   the oldest, ``numpy==1.24.3``: pip then picks scipy, scikit-image, matplotlib,
   h5py... releases that accept it (checked again from each wheel's ``Requires-Dist``
   against every Blender numpy) and the numpy wheel itself is never bundled.
2. Copy the extension (repo root minus tests, tools, docs, CI, venv and caches) to a
   staging folder with ``./wheels/`` and a manifest listing the wheels and platforms.
3. ``blender_ext.py build --split-platforms`` into ``dist/``, then
   ``blender_ext.py validate`` on each zip.

Usage::

    python tools/build_extension.py [--platforms linux-x64,windows-x64,...] [--out dist]
                                    [--cache wheels_cache] [--offline] [--no-wheels]

``--offline`` resolves from the cache only (``pip --no-index``), so a second build or CI
with a warm cache needs no network. ``--no-wheels`` builds one platform-independent zip
without dependencies (for development and tests of the packaging itself).
"""

from __future__ import annotations

import argparse
import fnmatch
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import unquote, urlparse

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = "blender_manifest.toml"

#: Blender's Python and the numpy versions it ships (4.2 LTS: 1.24.3; 4.5 LTS, 5.0: 1.26.4).
#: Dependencies are resolved against the oldest and must accept all of them.
PYTHON_VERSION = "3.11"
BLENDER_NUMPYS = ("1.24.3", "1.26.4")
BLENDER_NUMPY = BLENDER_NUMPYS[0]

#: Blender platform -> pip ``--platform`` tags. macOS tags are upper bounds (pip expands
#: them down to 10.x); 12.0 is what current scipy publishes for arm64.
PLATFORM_TAGS: dict[str, tuple[str, ...]] = {
    "linux-x64": ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64"),
    "windows-x64": ("win_amd64",),
    "macos-arm64": ("macosx_12_0_arm64",),
    "macos-x64": ("macosx_12_0_x86_64",),
}
DEFAULT_PLATFORMS = ("linux-x64", "windows-x64", "macos-arm64")

#: Never bundled: Blender ships numpy (and bundling a second one breaks ``bpy``).
NEVER_BUNDLE = frozenset({"numpy"})

#: Top-level entries of the repo that are not part of the extension. The manifest's
#: ``[build] paths_exclude_pattern`` excludes the same again inside ``blender_ext.py``.
STAGE_EXCLUDE_TOP = frozenset({
    "ssm_addon",  # the core goes in once, as its wheel (imported as ``ssm_addon``)
    ".git", ".github", ".ci", ".venv", "venv", "tests", "tools", "docs", "build", "dist",
    "wheels", "wheels_cache", "scripts", ".pytest_cache", ".ruff_cache", "pyproject.toml", ".gitignore",
    "requirements.txt", "requirements-dev.txt", "constraints.txt", "out", "demo_out",
})
#: Names excluded at any depth.
STAGE_EXCLUDE_ANY = ("__pycache__", "*.pyc", "*.pyo", "*.zip", "*.blend1", ".DS_Store")


class BuildError(RuntimeError):
    """A build step failed; the message names the step and what went wrong."""


@dataclass
class PlatformWheels:
    """The resolved wheels of one platform (file names inside ``cache_dir``)."""

    platform: str
    cache_dir: Path
    wheels: list[str] = field(default_factory=list)
    seconds: float = 0.0


# --------------------------------------------------------------------------------------
# Locating Blender's tooling and the dependency list


def blender_ext_path() -> Path:
    """Path of ``blender_ext.py`` inside the installed ``bpy`` wheel.

    Raises
    ------
    BuildError
        If ``bpy`` is not installed or the script is not where Blender 4.2+ puts it.
    """
    spec = importlib.util.find_spec("bpy")
    if spec is None or not spec.submodule_search_locations:
        raise BuildError("bpy is not installed: pip install bpy==5.0.1 (Python 3.11) to get blender_ext.py")
    bpy_dir = Path(next(iter(spec.submodule_search_locations)))
    found = sorted(bpy_dir.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not found:
        raise BuildError(f"blender_ext.py not found under {bpy_dir}/<version>/scripts/addons_core/bl_pkg/cli/")
    return found[-1]


def runtime_requirements(pyproject: Path = ROOT / "pyproject.toml") -> list[str]:
    """Runtime requirements from ``[project] dependencies`` without numpy."""
    with open(pyproject, "rb") as fh:
        deps = tomllib.load(fh)["project"]["dependencies"]
    return [d for d in deps if _project_name(re.split(r"[<>=!~;\[ ]", d, maxsplit=1)[0]) not in NEVER_BUNDLE]


def _project_name(name: str) -> str:
    """PEP 503 normalised project name (``scikit_image`` -> ``scikit-image``)."""
    return re.sub(r"[-_.]+", "-", name).lower()


def wheel_project(filename: str) -> str:
    """Normalised project name of a wheel file name."""
    return _project_name(filename.split("-", 1)[0])


def wheel_version(filename: str) -> str:
    return filename.split("-")[1]


def wheel_blender_platforms(filename: str, platforms: tuple[str, ...]) -> set[str]:
    """The Blender platforms among ``platforms`` a wheel installs on (Blender's own mapping)."""
    tag = Path(filename).stem.split("-")[-1]
    out = set()
    for plat_tag in tag.split("."):  # compressed tag sets, e.g. manylinux_2_17_x86_64.manylinux2014_x86_64
        if plat_tag == "any":
            return set(platforms)
        out.update(p for p in _blender_platforms_from_wheel_platform(plat_tag) if p in platforms)
    return out


def _blender_platforms_from_wheel_platform(tag: str) -> list[str]:
    """Mirror of ``blender_ext.blender_platforms_from_wheel_platform`` (same rules)."""
    head, _, tail = tag.partition("_")
    for src, dst in (("macosx", "macos"), ("manylinux", "linux"), ("musllinux", "linux"), ("win", "windows")):
        if head == src or (head.startswith(src) and head[len(src):].isdigit()):
            head = dst
            break
    for src, dst in (("x86_64", "x64"), ("amd64", "x64"), ("aarch64", "arm64")):
        if tail == src or tail.endswith("_" + src):
            tail = dst
            break
    else:
        tail = tail.rpartition("_")[2]
    tails = ["x64", "arm64"] if (head, tail) == ("macos", "universal2") else [tail]
    return [f"{head}-{t}" for t in tails]


# --------------------------------------------------------------------------------------
# Step 1: wheels


def _url_filename(url: str) -> str:
    return unquote(Path(urlparse(url).path).name)


def _run_pip(cmd: list[str], what: str, offline: bool) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if "is ignored: it is neither" not in ln]
        hint = " (offline: the cache lacks a wheel; run once without --offline)" if offline else ""
        raise BuildError(f"{what} failed{hint}:\n" + "\n".join(lines[-15:]))


def download_wheels(
    platform: str,
    requirements: list[str],
    cache: Path,
    offline: bool = False,
    log=print,
) -> PlatformWheels:
    """Resolve and download the wheels of one platform into ``cache/<platform>``.

    Parameters
    ----------
    platform : str
        Blender platform name, a key of :data:`PLATFORM_TAGS`.
    requirements : list of str
        Requirement strings (numpy excluded; it is pinned by constraint only).
    cache : Path
        Root of the wheel cache; already downloaded files are reused.
    offline : bool
        Resolve from the cache only: reuse the recorded resolution
        (``cache/<platform>/resolved.json``) when it was made for the same requirements,
        else ``pip --no-index --find-links``.

    Returns
    -------
    PlatformWheels
        The resolved wheel file names without numpy.
    """
    if platform not in PLATFORM_TAGS:
        raise BuildError(f"unknown platform {platform!r}; known: {', '.join(PLATFORM_TAGS)}")
    dest = cache / platform
    dest.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    record_path = dest / "resolved.json"
    key = {"requirements": requirements, "numpy": BLENDER_NUMPY, "python": PYTHON_VERSION,
           "tags": list(PLATFORM_TAGS[platform])}
    if offline:
        try:
            record = json.loads(record_path.read_text())
        except (OSError, ValueError):
            record = None
        if record and record.get("key") == key and all((dest / w).is_file() for w in record["wheels"]):
            result = PlatformWheels(platform, dest, list(record["wheels"]), time.perf_counter() - t0)
            log(f"  {platform}: {len(result.wheels)} wheels from the cache's recorded resolution")
            return result
    pip = [sys.executable, "-m", "pip"]
    target = [
        "--only-binary=:all:", "--python-version", PYTHON_VERSION, "--implementation", "cp",
        *(arg for tag in PLATFORM_TAGS[platform] for arg in ("--platform", tag)),
        "--disable-pip-version-check", "--progress-bar", "off",
    ]
    index = ["--no-index", "--find-links", str(dest)] if offline else []
    with tempfile.TemporaryDirectory(prefix="ssm-resolve-") as tmp:
        constraints = Path(tmp) / "constraints.txt"
        constraints.write_text(f"numpy=={BLENDER_NUMPY}\n")
        report = Path(tmp) / "report.json"
        # Resolve once (pip's report names the exact files), then fetch what the cache lacks.
        _run_pip(pip + ["install", "--dry-run", "--ignore-installed", "--quiet", "--report", str(report),
                        "--target", str(Path(tmp) / "target"), "--constraint", str(constraints),
                        *target, *index, *requirements], f"resolving the wheels for {platform}", offline)
        items = json.loads(report.read_text())["install"]
    urls = {_url_filename(item["download_info"]["url"]): item["download_info"]["url"] for item in items}
    if any(not f.endswith(".whl") for f in urls):
        raise BuildError(f"{platform}: pip resolved a non-wheel file: {sorted(urls)}")
    fetch = [url for name, url in urls.items() if not (dest / name).is_file()]
    if fetch:
        _run_pip(pip + ["download", "--no-deps", "--dest", str(dest), *target, *fetch],
                 f"downloading {len(fetch)} wheels for {platform}", offline)
    files = sorted(urls)
    missing = [f for f in files if not (dest / f).is_file()]
    if missing:
        raise BuildError(f"{platform}: pip did not put {missing} into {dest}")
    wheels = sorted(f for f in files if wheel_project(f) not in NEVER_BUNDLE)
    record_path.write_text(json.dumps({"key": key, "wheels": wheels}, indent=1) + "\n")
    result = PlatformWheels(platform, dest, wheels, time.perf_counter() - t0)
    log(f"  {platform}: {len(wheels)} wheels, {_mb(sum((dest / w).stat().st_size for w in wheels)):.1f} MB "
        f"({result.seconds:.1f} s{', offline' if offline else ''})")
    return result


def check_numpy_compatible(wheel: Path, numpy_versions: tuple[str, ...] = BLENDER_NUMPYS) -> None:
    """Raise BuildError if the wheel's ``Requires-Dist: numpy`` excludes a Blender numpy."""
    try:
        from packaging.requirements import Requirement
        from packaging.version import Version
    except ImportError:  # pragma: no cover - pip always vendors packaging
        from pip._vendor.packaging.requirements import Requirement
        from pip._vendor.packaging.version import Version
    with zipfile.ZipFile(wheel) as zf:
        meta_name = next((n for n in zf.namelist() if n.endswith(".dist-info/METADATA") and n.count("/") == 1), None)
        if meta_name is None:
            raise BuildError(f"{wheel.name}: no .dist-info/METADATA in the wheel")
        meta = zf.read(meta_name).decode("utf-8", "replace")
    for line in meta.splitlines():
        if not line.startswith("Requires-Dist:"):
            continue
        req = Requirement(line.split(":", 1)[1].strip())
        if _project_name(req.name) != "numpy":
            continue
        if req.marker is not None and not req.marker.evaluate({"extra": "", "python_version": PYTHON_VERSION}):
            continue
        for version in numpy_versions:
            if not req.specifier.contains(Version(version), prereleases=True):
                raise BuildError(f"{wheel.name} requires {req} but Blender ships numpy {version}")


def merge_wheels(resolved: list[PlatformWheels]) -> dict[str, Path]:
    """Union of the platforms' wheels, one wheel per (project, Blender platform).

    A wheel that covers several platforms (pure Python, macOS universal2) is preferred and
    kept once; a narrower wheel of the same project is kept only for platforms no chosen
    wheel covers. Two different versions of one project on one platform are an error
    (the zip would hold both).

    Returns
    -------
    dict
        Wheel file name -> path in the cache, sorted by name.
    """
    platforms = tuple(r.platform for r in resolved)
    candidates: dict[str, tuple[Path, set[str]]] = {}
    wanted: dict[str, set[str]] = {}  # project -> platforms it was resolved for
    for res in resolved:
        for name in res.wheels:
            targets = wheel_blender_platforms(name, platforms)
            if res.platform not in targets:
                raise BuildError(f"{name} was resolved for {res.platform} but Blender maps it to {sorted(targets)}")
            candidates.setdefault(name, (res.cache_dir / name, targets))
            wanted.setdefault(wheel_project(name), set()).add(res.platform)
    versions: dict[tuple[str, str], str] = {}
    for name, (_, targets) in candidates.items():
        for plat in targets:
            key = (wheel_project(name), plat)
            if versions.setdefault(key, wheel_version(name)) != wheel_version(name):
                raise BuildError(
                    f"{key[0]}: versions {versions[key]} and {wheel_version(name)} would both install on {plat}; "
                    "pin one version in pyproject.toml"
                )
    chosen: dict[str, Path] = {}
    covered: set[tuple[str, str]] = set()
    for name in sorted(candidates, key=lambda n: (-len(candidates[n][1]), n)):
        path, targets = candidates[name]
        project = wheel_project(name)
        new = {p for p in targets & wanted[project] if (project, p) not in covered}
        if new:
            chosen[name] = path
            covered.update((project, p) for p in targets)
    return dict(sorted(chosen.items()))


# --------------------------------------------------------------------------------------
# Step 2: staging


def _excluded(rel: Path) -> bool:
    if rel.parts and rel.parts[0] in STAGE_EXCLUDE_TOP:
        return True
    return any(fnmatch.fnmatch(part, pat) for part in rel.parts for pat in STAGE_EXCLUDE_ANY)


def extension_files(root: Path = ROOT) -> list[Path]:
    """Paths (relative to ``root``) of the files that go into the extension, sorted.

    In a git work tree these are the tracked and untracked-but-not-ignored files (so
    ``.gitignore`` keeps build outputs and caches out); otherwise every file. Either way
    minus :data:`STAGE_EXCLUDE_TOP` and :data:`STAGE_EXCLUDE_ANY`.
    """
    listed = _git_files(root)
    if listed is None:
        listed = []
        for dirpath, dirnames, filenames in os.walk(root):
            rel_dir = Path(dirpath).relative_to(root)
            dirnames[:] = [d for d in dirnames if not _excluded(rel_dir / d)]
            listed.extend(rel_dir / f for f in filenames)
    return sorted({rel for rel in listed if not _excluded(rel) and (root / rel).is_file()})


def _git_files(root: Path) -> list[Path] | None:
    if not (root / ".git").exists() or shutil.which("git") is None:
        return None
    proc = subprocess.run(
        ["git", "-C", str(root), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        capture_output=True,
    )
    if proc.returncode != 0:
        return None
    return [Path(p) for p in proc.stdout.decode("utf-8", "surrogateescape").split("\0") if p]


def _toml_list(items) -> str:
    if not items:
        return "[]"
    body = "".join(f'    "{item}",\n' for item in items)
    return "[\n" + body + "]"


def staged_manifest_text(source_text: str, wheels: list[str], platforms: list[str]) -> str:
    """The source manifest with ``wheels`` (as ``./wheels/<file>``) and ``platforms`` set.

    Both keys are top-level, so they are (re)written before the first table header.
    """
    text = re.sub(r"(?ms)^wheels\s*=\s*\[.*?\]\s*\n", "", source_text)
    text = re.sub(r"(?ms)^platforms\s*=\s*\[.*?\]\s*\n", "", text)
    block = f"wheels = {_toml_list(['./wheels/' + w for w in wheels])}\n"
    if platforms:
        block += f"platforms = {_toml_list(platforms)}\n"
    match = re.search(r"(?m)^\[", text)
    pos = match.start() if match else len(text)
    text = text[:pos] + block + "\n" + text[pos:]
    parsed = tomllib.loads(text)  # must stay valid TOML with the keys at the top level
    if parsed.get("wheels", []) != ["./wheels/" + w for w in wheels]:
        raise BuildError("could not write the wheels list into the staged manifest")
    return text


def stage(stage_dir: Path, wheels: dict[str, Path], platforms: list[str], root: Path = ROOT) -> Path:
    """Copy the extension files, wheels and the filled-in manifest into ``stage_dir``."""
    for rel in extension_files(root):
        dst = stage_dir / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / rel, dst)
    if wheels:
        (stage_dir / "wheels").mkdir()
        for name, src in wheels.items():
            dst = stage_dir / "wheels" / name
            try:
                os.link(src, dst)
            except OSError:
                shutil.copy2(src, dst)
    manifest = stage_dir / MANIFEST
    manifest.write_text(staged_manifest_text((root / MANIFEST).read_text(), list(wheels), platforms))
    return stage_dir


# --------------------------------------------------------------------------------------
# Step 3: Blender's build and validate


def core_wheel(dest: Path, root: Path = ROOT) -> Path:
    """Build the core's wheel (``ssm_addon``, pure Python) into ``dest`` with this interpreter.

    ``pip wheel --no-build-isolation`` uses the setuptools of the running environment
    (``requirements-dev.txt``), so it needs no network. It builds from a copy of the
    sources the wheel is made of (``pyproject.toml`` and ``ssm_addon/``): setuptools writes
    ``build/`` and ``*.egg-info`` next to the sources it builds, so two builds at once (two
    test processes, two zips) would otherwise share and remove one another's files, and the
    checkout is left as it was.
    """
    dest.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="ssm-core-wheel-") as tmp:
        src, out_dir = Path(tmp) / "src", Path(tmp) / "wheel"
        src.mkdir()
        shutil.copy2(root / "pyproject.toml", src / "pyproject.toml")
        shutil.copytree(root / "ssm_addon", src / "ssm_addon", ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        proc = subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation",
                               "--quiet", "-w", str(out_dir)], capture_output=True, text=True, cwd=tmp)
        built = sorted(out_dir.glob("ssm_builder-*.whl"))
        if proc.returncode != 0 or not built:
            raise BuildError(f"building the core wheel failed:\n{proc.stdout[-2000:]}{proc.stderr[-2000:]}")
        out = dest / built[0].name
        shutil.copy2(built[0], out)
    return out


def run_blender_ext(*args: str) -> str:
    """Run ``blender_ext.py`` with this interpreter; raise BuildError on failure."""
    proc = subprocess.run([sys.executable, str(blender_ext_path()), *args], capture_output=True, text=True)
    out = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0:
        raise BuildError(f"blender_ext.py {args[0]} failed:\n{out}")
    return out


def build(
    platforms: list[str] | None = None,
    out_dir: Path = ROOT / "dist",
    cache: Path = ROOT / "wheels_cache",
    offline: bool = False,
    with_wheels: bool = True,
    root: Path = ROOT,
    log=print,
) -> list[Path]:
    """Build and validate the extension zips.

    Parameters
    ----------
    platforms : list of str, optional
        Blender platforms (keys of :data:`PLATFORM_TAGS`); default :data:`DEFAULT_PLATFORMS`.
    out_dir : Path
        Where the zips go (``ssm-<version>-<platform>.zip``).
    cache : Path
        Wheel cache root (``<cache>/<platform>/*.whl``).
    offline : bool
        Use only the wheel cache.
    with_wheels : bool
        False builds one platform-independent zip without dependencies (the core's own
        wheel is always bundled).

    Returns
    -------
    list of Path
        The validated zips.
    """
    platforms = list(platforms or DEFAULT_PLATFORMS)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    wheels: dict[str, Path] = {}
    if with_wheels:
        requirements = runtime_requirements(root / "pyproject.toml")
        log(f"resolving {', '.join(requirements)} for Python {PYTHON_VERSION}, numpy=={BLENDER_NUMPY} (Blender's, not bundled)")
        resolved = [download_wheels(p, requirements, Path(cache), offline, log) for p in platforms]
        wheels = merge_wheels(resolved)
        for path in wheels.values():
            check_numpy_compatible(path)
    core_dir = Path(cache) / "core"
    shutil.rmtree(core_dir, ignore_errors=True)
    core = core_wheel(core_dir, root)
    wheels = {core.name: core, **wheels}
    t_wheels = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="ssm-ext-stage-") as tmp:
        stage_dir = stage(Path(tmp) / "ssm", wheels, platforms if with_wheels else [], root)
        before = {p: p.stat().st_mtime_ns for p in out_dir.glob("*.zip")}
        args = ["build", "--source-dir", str(stage_dir), "--output-dir", str(out_dir)]
        if with_wheels:
            args.append("--split-platforms")
        run_blender_ext(*args)
    zips = sorted(p for p in out_dir.glob("*.zip") if before.get(p) != p.stat().st_mtime_ns)
    if not zips:
        raise BuildError(f"blender_ext.py build produced no zip in {out_dir}")
    for z in zips:
        run_blender_ext("validate", str(z))
    t_end = time.perf_counter()
    log(f"built and validated in {t_end - t_start:.1f} s (wheels {t_wheels - t_start:.1f} s, "
        f"build+validate {t_end - t_wheels:.1f} s):")
    for z in zips:
        log(f"  {z}  {_mb(z.stat().st_size):.1f} MB")
    return zips


def _mb(n: int) -> float:
    return n / 2**20


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--platforms", default=",".join(DEFAULT_PLATFORMS),
                        help=f"comma-separated, from {', '.join(PLATFORM_TAGS)} or 'all' (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=ROOT / "dist", help="output folder (default: dist/)")
    parser.add_argument("--cache", type=Path, default=ROOT / "wheels_cache",
                        help="wheel cache folder (default: wheels_cache/)")
    parser.add_argument("--offline", action="store_true", help="use only wheels already in the cache")
    parser.add_argument("--no-wheels", action="store_true",
                        help="one platform-independent zip without bundled dependencies (development)")
    args = parser.parse_args(argv)
    platforms = list(PLATFORM_TAGS) if args.platforms == "all" else [p.strip() for p in args.platforms.split(",") if p.strip()]
    try:
        build(platforms, args.out, args.cache, args.offline, with_wheels=not args.no_wheels)
    except BuildError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
