"""Executors (serial, processes, Dask) and the resumable build cache (ssm_addon.base.compute, ssm_addon.pipeline.cache)."""

from __future__ import annotations

import contextlib
import dataclasses
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import as_from_a_terminal

from ssm_addon.base.compute import Executor, check_scheduler, time_left_text
from ssm_addon.base.errors import InputError
from ssm_addon.cli import demo
from ssm_addon.pipeline.cache import BuildCache
from ssm_addon.pipeline.project import read_project
from ssm_addon.pipeline.project_build import build

ROOT = Path(__file__).resolve().parents[1]
ARRAYS = ("mean", "modes", "variances", "instance_points", "instance_points_world")
PICTURES = ("modes.png", "spectrum.png", "cumulative_variance.png", "variability.png", "metrics.png")


@pytest.fixture(scope="module")
def population(tmp_path_factory):
    folder = tmp_path_factory.mktemp("compute") / "pop"
    demo.make_demo_population(folder, n=6, seed=3)
    return folder


def _project(population: Path, folder: Path, n: int, extra: str = "") -> Path:
    """The demo project with its first ``n`` instances (and ``extra`` tables)."""
    text = (population / "project.toml").read_text()
    head, *blocks = text.split("[[instances]]")
    body = "".join("[[instances]]" + b for b in blocks[:n]).replace('volume = "demo', f'volume = "{population}/demo')
    body = body.replace('landmarks = "demo', f'landmarks = "{population}/demo')
    path = folder / f"project{n}.toml"
    head = re.sub(r'instance = "demo_\d+"', 'instance = "demo_00"', head)
    path.write_text(head.replace("[model]", f"{extra}\n[model]") + body)
    return path


def _arrays(out: Path) -> dict:
    with np.load(out / "model.npz", allow_pickle=False) as z:
        return {k: z[k] for k in ARRAYS}


def _build(project, out, lines=None, **kw):
    log = lines.append if lines is not None else None
    return build(read_project(project), out, log=log, blend=False, **kw)


@pytest.mark.slow
def test_schedulers_give_identical_models(population, tmp_path):
    """serial, processes and dask-local compute the same model bit for bit."""
    proj = _project(population, tmp_path, 5)
    schedulers = ["serial", "processes"]
    try:
        import distributed  # noqa: F401

        schedulers.append("dask-local")
    except ImportError:
        pass
    models = {}
    for s in schedulers:
        _build(proj, tmp_path / f"out-{s}", jobs=2, scheduler=s, cache="off")
        models[s] = _arrays(tmp_path / f"out-{s}")
    for s in schedulers[1:]:
        for k in ARRAYS:
            assert np.array_equal(models[s][k], models["serial"][k]), (s, k)
        for png in PICTURES:  # drawn on a worker by "processes", here by the others
            assert (tmp_path / f"out-{s}" / png).read_bytes() == (tmp_path / "out-serial" / png).read_bytes(), (s, png)
    assert "dask-local" in schedulers, "dask is in requirements-dev.txt: the Dask scheduler must be tested"


@pytest.mark.slow
def test_cache_resumes_and_invalidates_exactly(population, tmp_path):
    proj5 = _project(population, tmp_path, 5)
    cache = tmp_path / "cache"
    lines: list = []
    first = _build(proj5, tmp_path / "a", lines, cache=cache)
    assert first.study.streamed == {"cached": 0, "computed": 5}
    # unchanged: everything from the cache, the same numbers
    lines.clear()
    again = _build(proj5, tmp_path / "b", lines, cache=cache)
    assert again.study.streamed == {"cached": 5, "computed": 0}
    assert any("5 of 5 instance(s) taken from the cache" in m for m in lines)
    assert any("from the cache" in m and m.startswith("template") for m in lines)
    for k in ARRAYS:
        assert np.array_equal(_arrays(tmp_path / "a")[k], _arrays(tmp_path / "b")[k])
    # a model parameter: coatings stay valid
    proj_model = _project(population, tmp_path, 5, extra="")
    proj_model.write_text(proj_model.read_text().replace('alignment = "none"', 'alignment = "rigid"'))
    assert _build(proj_model, tmp_path / "c", cache=cache).study.streamed == {"cached": 5, "computed": 0}
    # one more instance: only it is coated; the template stays
    lines.clear()
    six = _build(_project(population, tmp_path, 6), tmp_path / "d", lines, cache=cache)
    assert six.study.streamed == {"cached": 5, "computed": 1}
    assert any(m.startswith("template") and "from the cache" in m for m in lines)
    # a coating parameter: every coating again, the template from the cache
    lines.clear()
    changed = _project(population, tmp_path, 5, extra="")
    changed.write_text(changed.read_text().replace("[coating]", "[coating]\nk1 = 0.3", 1))
    res = _build(changed, tmp_path / "e", lines, cache=cache)
    assert res.study.streamed == {"cached": 0, "computed": 5}
    assert any(m.startswith("template") and "from the cache" in m for m in lines)
    # a template parameter that changes the template: the template and every coating again
    # (one that leaves the template as it was, e.g. a seed unused by curvature selection, keeps them)
    tparam = _project(population, tmp_path, 5, extra="")
    tparam.write_text(tparam.read_text().replace("spacing = 1.0", "spacing = 1.0\nselection = \"random\"", 1))
    lines.clear()
    res = _build(tparam, tmp_path / "f", lines, cache=cache)
    assert res.study.streamed == {"cached": 0, "computed": 5}
    assert not any(m.startswith("template") and "from the cache" in m for m in lines)
    report = (tmp_path / "f" / "report.json").read_text()
    assert '"computed": 5' in report


def test_an_entry_written_by_other_code_is_not_read(population, tmp_path, monkeypatch):
    """The package's own source is part of every key (``code_digest``): the same project and
    version, but other code, recomputes the template and every coating."""
    from ssm_addon.pipeline import cache as cache_module

    proj = _project(population, tmp_path, 4)
    cache = tmp_path / "cache"
    assert _build(proj, tmp_path / "a", cache=cache).study.streamed == {"cached": 0, "computed": 4}
    assert _build(proj, tmp_path / "b", cache=cache).study.streamed == {"cached": 4, "computed": 0}
    monkeypatch.setattr(cache_module, "code_digest", lambda: "other code")
    lines: list = []
    assert _build(proj, tmp_path / "c", lines, cache=cache).study.streamed == {"cached": 0, "computed": 4}
    assert not any(m.startswith("template") and "from the cache" in m for m in lines)


@pytest.mark.slow
def test_killed_build_resumes_with_only_the_missing_instances(population, tmp_path):
    """SIGKILL mid-coating; the rerun coats only what the cache lacks and equals a fresh build."""
    proj = _project(population, tmp_path, 6)
    cache = tmp_path / "cache"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "ssm_addon", "build", str(proj), "--out", str(tmp_path / "out"), "--no-blend",
           "--scheduler", "serial", "--cache", str(cache)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    entries = cache / "instances"
    deadline = time.time() + 120
    while time.time() < deadline and (not entries.exists() or len(list(entries.glob("*.npz"))) < 2):
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=30)
    done = len(list(entries.glob("*.npz")))
    assert 2 <= done < 6, done
    assert not list(entries.glob(".*.tmp"))  # no half-written entry under a final name
    res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    assert f"{done} of 6 instance(s) taken from the cache {cache}, {6 - done} to coat" in res.stdout
    _build(proj, tmp_path / "fresh", cache="off")
    for k in ARRAYS:
        assert np.array_equal(_arrays(tmp_path / "out")[k], _arrays(tmp_path / "fresh")[k]), k


def test_cache_refuses_foreign_folders(population, tmp_path):
    mine = tmp_path / "notes"
    mine.mkdir()
    (mine / "thesis.txt").write_text("precious")
    with pytest.raises(InputError, match="not an SSM build cache"):
        BuildCache(mine)
    assert (mine / "thesis.txt").read_text() == "precious"
    proj = _project(population, tmp_path, 3)
    with pytest.raises(InputError, match="inside the output folder"):
        _build(proj, tmp_path / "out", cache=tmp_path / "out" / "cache")
    assert not (tmp_path / "out").exists()


def test_project_compute_table(population, tmp_path):
    proj = _project(population, tmp_path, 3, extra='[compute]\nscheduler = "serial"\ncache = "mycache"\n')
    p = read_project(proj)
    assert p.params.compute.scheduler == "serial" and Path(p.params.compute.cache) == (tmp_path / "mycache").resolve()
    bad = _project(population, tmp_path, 3, extra='[compute]\nscheduler = "slurm"\n')
    with pytest.raises(InputError, match="unknown scheduler 'slurm'"):
        read_project(bad)
    from ssm_addon.pipeline.project import project_text

    text = project_text(p, tmp_path)
    assert "[compute]" in text and 'cache = "mycache"' in text
    assert "[compute]" not in project_text(dataclasses.replace(p, params=p.params.replace(compute=type(p.params.compute)())), tmp_path)


@pytest.mark.slow
def test_unreachable_scheduler_fails_fast_and_clearly():
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    t0 = time.perf_counter()
    with pytest.raises(InputError, match=r"tcp://127\.0\.0\.1:9: nothing accepts connections there"):
        Executor("tcp://127.0.0.1:9", jobs=1, connect_timeout_s=600.0)
    # a refusal is known at once: the 600 s wait for an answer was not spent (60 s: far above any machine's noise)
    assert time.perf_counter() - t0 < 60


def _listener(kind: str):
    """A local TCP server that is not a Dask scheduler: 'silent' accepts and never answers, 'http' is a
    web server (as the Dask dashboard's port 8787 is). Returns (address, close)."""
    import http.server
    import socket
    import threading

    if kind == "http":
        server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        return f"tcp://127.0.0.1:{server.server_address[1]}", server.shutdown
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(8)
    address = f"tcp://127.0.0.1:{sock.getsockname()[1]}"
    accepted = _ACCEPTED[address] = threading.Event()
    held = []

    def serve():
        for _ in range(8):
            held.append(sock.accept())
            accepted.set()

    threading.Thread(target=serve, daemon=True).start()
    return address, sock.close


_ACCEPTED: dict = {}


def _wait_for_connection(address: str) -> None:
    """Until the build has connected to the silent listener at ``address`` (a hang fails after 300 s)."""
    assert _ACCEPTED[address].wait(timeout=300), f"nothing connected to {address}"


@pytest.mark.parametrize("kind", ["silent", "http"])
def test_a_listener_that_is_not_a_scheduler_fails_within_the_deadline(kind):
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    address, close = _listener(kind)
    try:
        # the message names the deadline it waited for; a hang is caught by the suite's own limit
        with pytest.raises(InputError, match=rf"{re.escape(address)}: something accepts connections there but sent "
                                             r"no Dask handshake within 2 s: not a Dask scheduler"):
            Executor(address, jobs=1, connect_timeout_s=2.0)
    finally:
        close()


@pytest.mark.slow
def test_build_against_a_silent_listener_stops_within_15_s_with_its_address(population, tmp_path):
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    address, close = _listener("silent")
    try:
        proj = _project(population, tmp_path, 3)
        proc = subprocess.run([sys.executable, "-m", "ssm_addon", "build", str(proj), "--out", str(tmp_path / "out"),
                               "--scheduler", address, "--no-blend"], cwd=ROOT, capture_output=True, text=True,
                              timeout=300, env={**os.environ, "PYTHONPATH": str(ROOT)})  # against a hang only
    finally:
        close()
    assert proc.returncode == 2, proc.stderr[-1500:]
    assert f"{address}: something accepts connections there but sent no Dask handshake within 10 s" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.cache").exists()


def test_jobs_are_capped_at_the_cores_with_a_note():
    from ssm_addon.base.compute import usable_cores

    with Executor("processes", jobs=100000) as ex:
        assert ex.jobs == usable_cores() and ex.note == f"--jobs 100000 capped at {usable_cores()} (the machine's " \
                                                        f"{usable_cores()} cores)"
    with Executor("processes", jobs=1) as ex:
        assert ex.note == ""


@pytest.mark.slow
def test_dask_local_starts_no_more_workers_than_cores_and_instances_and_leaves_no_scratch(tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    import tempfile

    monkeypatch.setenv("TMPDIR", str(tmp_path))
    tempfile.tempdir = None  # re-read TMPDIR
    try:
        with Executor("dask-local", jobs=100000, tasks=1) as ex:
            assert ex.jobs == 1 and "capped at 1 (the 1 instance(s))" in ex.note
            assert len(ex._client.scheduler_info()["workers"]) == 1  # noqa: SLF001 - the cluster's own count
            assert ex.map(abs, [-4]) == [4]
    finally:
        tempfile.tempdir = None
    assert list(tmp_path.iterdir()) == []  # no dask-scratch-space, no ssm-dask-* left


@pytest.mark.slow
def test_dask_local_beside_another_cluster_on_8787_says_nothing():
    """A second dask-local build (or a notebook's cluster) holds Dask's usual port 8787: the build's
    scheduler takes a free local port and Dask prints no "Port 8787 is already in use" warning."""
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    import socket
    import warnings

    other = socket.socket()
    try:
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        with contextlib.suppress(OSError):  # another process holds it already: as good for this test
            other.bind(("0.0.0.0", 8787))
            other.listen()
        socket.create_connection(("127.0.0.1", 8787), timeout=10).close()  # taken: by this test or another process
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            with Executor("dask-local", jobs=1, tasks=1) as ex:
                assert ex.map(abs, [-4]) == [4]
    finally:
        other.close()
    assert [str(w.message) for w in seen if "8787" in str(w.message)] == []


def test_scheduler_names_and_time_left():
    assert check_scheduler(" processes ") == "processes"
    with pytest.raises(InputError, match="unknown scheduler"):
        check_scheduler("threads")
    assert time_left_text(0, 10, 5.0) == ""
    assert time_left_text(5, 10, 50.0) == "about 50 s left"
    assert time_left_text(1, 100, 120.0) == "about 3.3 h left"


def test_executor_map_keeps_order_and_reports(tmp_path):
    seen = []
    with Executor("processes", jobs=2) as ex:
        out = ex.map(abs, [-3, 1, -2, 5], on_result=lambda i, r: seen.append((i, r)), labels=list("abcd"))
    assert out == [3, 1, 2, 5] and sorted(seen) == [(0, 3), (1, 1), (2, 2), (3, 5)]


def test_processes_are_processes_after_bpy_is_imported_and_serial_only_inside_the_blender_program(
        tmp_path, monkeypatch):
    """The rule is the program, not what was imported before: a Python that imported the ``bpy`` module
    (a Blender test earlier in the same pytest worker, a notebook) runs real worker processes; only the
    Blender program itself (``bpy.app.binary_path`` set) runs ``processes`` serially. Run in a fresh
    interpreter that imports ``bpy`` first, so no earlier test decides it."""
    pytest.importorskip("bpy", reason="the bpy module is not installed")
    (tmp_path / "pid_of.py").write_text("import os\n\ndef pid_of(_):\n    return os.getpid()\n")
    code = ("import os, bpy\n"
            "from pid_of import pid_of\n"
            "from ssm_addon.base.compute import Executor\n"
            "with Executor('processes', jobs=2) as ex:\n"
            "    assert ex.scheduler == 'processes', ex.scheduler\n"
            "    pids = set(ex.map(pid_of, [0, 1, 2, 3]))\n"
            "assert os.getpid() not in pids, pids\n"
            "print('ok')\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=600)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-2000:]

    import types

    from ssm_addon.base import compute

    monkeypatch.setitem(sys.modules, "bpy", types.SimpleNamespace(app=types.SimpleNamespace(binary_path="/opt/blender")))
    assert compute.inside_blender_program()
    with Executor("processes", jobs=2) as ex:
        assert ex.scheduler == "serial"
    monkeypatch.setitem(sys.modules, "bpy", types.SimpleNamespace(app=types.SimpleNamespace(binary_path="")))
    assert not compute.inside_blender_program()


def _damage(entry: Path, how: str) -> None:
    data = entry.read_bytes()
    if how == "truncated":
        entry.write_bytes(data[: len(data) // 2])
    elif how == "bit-flipped":
        b = bytearray(data)
        b[len(b) // 2] ^= 0x40
        entry.write_bytes(bytes(b))
    elif how == "wrong-shape":
        with np.load(entry, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["points_object"] = arrays["points_object"][:-7]
        np.savez(entry, **arrays)
        if not str(entry).endswith(".npz"):
            os.replace(str(entry) + ".npz", entry)


@pytest.fixture(scope="module")
def cached3(population, tmp_path_factory):
    """The demo's first three instances built once with a cache: (project, output folder, cache); a test
    that changes the cache works on its own copy (:func:`_copied_cache`)."""
    folder = tmp_path_factory.mktemp("cached3")
    proj = _project(population, folder, 3)
    first = _build(proj, folder / "a", cache=folder / "cache")
    assert first.study.streamed["computed"] == 3
    return proj, folder / "a", folder / "cache"


def _copied_cache(cached3, tmp_path: Path) -> Path:
    return Path(shutil.copytree(cached3[2], tmp_path / "cache"))


@pytest.mark.slow
@pytest.mark.parametrize("how", ["truncated", "bit-flipped", "wrong-shape"])
def test_a_damaged_cache_entry_is_recomputed_with_one_line(cached3, tmp_path, how):
    proj, first = cached3[0], cached3[1]
    cache = _copied_cache(cached3, tmp_path)
    entries = sorted((cache / "instances").glob("*.npz"))
    assert len(entries) == 3
    _damage(entries[0], how)
    lines: list = []
    res = _build(proj, tmp_path / "b", lines, cache=cache)
    said = [m for m in lines if m.startswith("cache: the entry of instance")]
    assert len(said) == 1 and "is damaged" in said[0] and "recomputing it" in said[0], lines
    assert res.study.streamed == {"cached": 2, "computed": 1}
    for k in ARRAYS:
        assert np.array_equal(_arrays(first)[k], _arrays(tmp_path / "b")[k])
    assert (entries[0].parent / (entries[0].name + ".damaged")).exists()  # kept aside, never read again
    lines.clear()
    assert _build(proj, tmp_path / "c", lines, cache=cache).study.streamed == {"cached": 3, "computed": 0}
    assert not any("is damaged" in m for m in lines)


@pytest.mark.slow
def test_a_cache_that_cannot_be_written_is_used_read_only(cached3, tmp_path, monkeypatch):
    import errno

    from ssm_addon.pipeline import cache as cache_module

    proj, first = cached3[0], cached3[1]
    cache = _copied_cache(cached3, tmp_path)
    next(iter(sorted((cache / "instances").glob("*.npz")))).unlink()  # one entry missing: needs a write

    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(cache_module, "open", read_only, raising=False)
    lines: list = []
    res = _build(proj, tmp_path / "b", lines, cache=cache)
    said = [m for m in lines if "used read-only" in m]
    assert len(said) == 1 and "Read-only file system" in said[0]
    assert res.study.streamed == {"cached": 2, "computed": 1}
    for k in ARRAYS:
        assert np.array_equal(_arrays(first)[k], _arrays(tmp_path / "b")[k])


def test_ctrl_c_stops_a_build_waiting_for_a_scheduler_at_once(population, tmp_path):
    """The handshake wait is set to 600 s: a build that ended only when the wait did would
    need 10 minutes, one that stops at Ctrl-C ends in well under one (the bound is 10×
    anything a loaded machine needs, and 10× below the wait)."""
    pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    address, close = _listener("silent")
    try:
        proj = _project(population, tmp_path, 3, extra="[compute]\nconnect_timeout_s = 600.0")
        proc = subprocess.Popen([sys.executable, "-u", "-m", "ssm_addon", "build", str(proj), "--out",
                                 str(tmp_path / "out"), "--scheduler", address, "--no-blend"], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env={**os.environ, "PYTHONPATH": str(ROOT)}, preexec_fn=as_from_a_terminal)
        for line in proc.stdout:
            if line.startswith("project:"):
                break
        _wait_for_connection(address)  # the build is inside the handshake wait
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=300)
        took = time.perf_counter() - t0
        err = proc.stderr.read()
    finally:
        close()
    assert proc.returncode == 130 and took < 60, (took, err[-1500:])
    assert err.strip().splitlines() == ["interrupted by SIGINT: stopped; the output folder is as it was"]


def _inner_threads_here(_item):
    from ssm_addon.base.compute import inner_threads

    return inner_threads(2)


def test_inner_threads_are_one_in_a_worker_process_and_up_to_two_here(monkeypatch):
    """A k-d tree search may use two threads in the main process (one instance at a time), one in
    a worker process (its siblings keep the cores busy); the search's result is the same."""
    from ssm_addon.base import compute

    monkeypatch.setattr(compute, "usable_cores", lambda: 2)
    assert compute.inner_threads(2) == 2 and compute.inner_threads(8) == 2
    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    with compute.Executor("processes", jobs=2) as ex:
        assert ex.map(_inner_threads_here, [0, 1]) == [1, 1]


def _pid_of_worker(item):
    if item == "fail":
        raise ValueError("a bad item")
    return os.getpid()


def test_workers_started_ahead_run_the_map_and_an_error_stops_them(monkeypatch):
    """``start_workers`` starts the pool's processes before the first map (which then runs on
    them, not on new ones), and an error in a later map stops every one of them."""
    import multiprocessing

    from ssm_addon.base import compute

    monkeypatch.setattr(compute, "usable_cores", lambda: 2)
    monkeypatch.delitem(sys.modules, "bpy", raising=False)
    before = {c.pid for c in multiprocessing.active_children()}
    with compute.Executor("processes", jobs=2) as ex:
        ex.start_workers(("json", "no_such_module_anywhere"))  # an import error is left to the tasks
        started = {c.pid for c in multiprocessing.active_children()} - before
        assert len(started) == 2
        assert set(ex.map(_pid_of_worker, range(6))) <= started
        with pytest.raises(ValueError, match="a bad item"):
            ex.map(_pid_of_worker, [1, "fail", 2])
        deadline = time.monotonic() + 30.0  # stopped, not necessarily gone yet on a loaded machine
        while started & {c.pid for c in multiprocessing.active_children()} and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not started & {c.pid for c in multiprocessing.active_children()}
        assert set(ex.map(_pid_of_worker, range(4))).isdisjoint(started)  # a new pool after the error
    with compute.Executor("serial") as ex:
        ex.start_workers(("json",))
        assert ex.map(_pid_of_worker, [0]) == [os.getpid()]
