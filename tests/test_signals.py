"""Interrupting a headless build: SIGINT, SIGTERM and SIGHUP at any step stop it at once
(before the step it interrupted could end: no output folder is left) with one line and exit 128 + signal, end the worker processes, remove the temporary
folder and leave the output folder as it was; the Blender step cannot be made to crash."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, as_from_a_terminal

from ssm_addon.cli import demo

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    folder = tmp_path_factory.mktemp("signals")
    path = demo.make_demo_population(folder / "population", n=8, seed=4)
    return path


def _children(pid: int) -> set[int]:
    """Every descendant process of ``pid`` (from /proc)."""
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                kids = (task / "children").read_text().split()
            except OSError:
                continue
            for k in map(int, kids):
                if k not in found:
                    found.add(k)
                    todo.append(k)
    return found


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _wait_for(condition, what: str, seconds: float = 120.0):
    """Poll ``condition()`` until it returns a true value; a hang fails after ``seconds``."""
    deadline = time.monotonic() + seconds
    while not (value := condition()):
        assert time.monotonic() < deadline, f"waited {seconds:.0f} s for {what}"
        time.sleep(0.02)
    return value


def _ended(kids) -> list[int]:
    """Wait until none of ``kids`` runs; returns those still alive after the wait (a hang's evidence)."""
    deadline = time.monotonic() + 60
    while (alive := [k for k in kids if _alive(k)]) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive


def _interrupt(project: Path, out: Path, signum: int, when: str, extra=()):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-u", "-m", "ssm_addon", "build", str(project), "--out", str(out),
                             "--jobs", "2", *extra], cwd=out.parent, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, preexec_fn=as_from_a_terminal)
    seen = []
    deadline = time.monotonic() + 240
    for line in proc.stdout:
        seen.append(line)
        if when in line:
            break
        assert time.monotonic() < deadline, "".join(seen[-20:])
    else:
        pytest.fail(f"the build ended before {when!r}:\n{''.join(seen[-20:])}{proc.stderr.read()[-2000:]}")
    # inside the step: the workers (or Blender) have started, so the signal must reach them too
    kids = _wait_for(lambda: _children(proc.pid), "the build's child processes")
    proc.send_signal(signum)
    proc.wait(timeout=120)  # against a hang only
    rest = proc.stdout.read()
    err = proc.stderr.read()
    return proc.returncode, err, _ended(kids | _children(proc.pid)), seen, rest


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130), (signal.SIGHUP, 129)])
def test_signal_during_coating_with_two_workers_stops_cleanly(project, tmp_path, signum, code):
    out = tmp_path / "out"
    rc, err, alive, seen, rest = _interrupt(project, out, signum, "coating:", ("--no-blend",))
    assert rc == code, err  # and no model was written: the signal stopped the build, not its end
    assert f"interrupted by {signal.Signals(signum).name}" in err and "Traceback" not in err + rest
    assert len(err.strip().splitlines()) == 1, err
    assert alive == [], f"processes left: {alive}"
    assert not out.exists()
    # no temporary folder; the instances coated before the signal stay in the cache (for resuming)
    assert [p.name for p in tmp_path.iterdir()] in ([], ["out.cache"])


def test_sigterm_leaves_an_earlier_output_as_it_was(project, tmp_path):
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    subprocess.run([sys.executable, "-m", "ssm_addon", "build", str(project), "--out", str(out), "--no-blend"],
                   cwd=tmp_path, env=env, check=True, capture_output=True)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    # without the cache the second build coats again, so the signal lands well before the writing
    rc, err, alive, _seen, _rest = _interrupt(project, out, signal.SIGTERM, "template:",
                                                        ("--no-blend", "--cache", "off"))
    assert rc == 143 and alive == [], err
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "out.cache"]  # the first build's cache


@pytest.mark.blender
def test_signal_during_the_blender_step_cannot_crash_it(project, tmp_path):
    pytest.importorskip("bpy")
    out = tmp_path / "out"
    for signum, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        rc, err, alive, _seen, rest = _interrupt(project, out, signum, "Blender: model.blend")
        assert rc == code, err[-2000:]
        assert "Segmentation fault" not in err + rest and "Traceback" not in err
        assert alive == []
        assert not out.exists() and [p.name for p in tmp_path.iterdir()] in ([], ["out.cache"])


@pytest.mark.parametrize("scheduler", ["processes", "dask-local"])
@pytest.mark.parametrize(("signum", "code"), [(signal.SIGHUP, 129), (signal.SIGINT, 130)])
def test_a_signal_to_the_whole_process_group_ends_with_one_line(project, tmp_path, scheduler, signum, code):
    """A terminal's hang-up or Ctrl-C reaches every process of the group: the workers, Dask's nannies
    and multiprocessing's resource tracker too. None of them prints a traceback."""
    if scheduler == "dask-local":
        pytest.importorskip("distributed", reason="Dask is optional (pip install .[dask])")
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-u", "-m", "ssm_addon", "build", str(project), "--out", str(out),
                             "--jobs", "2", "--no-blend", "--scheduler", scheduler], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=as_from_a_terminal)
    seen = []
    for line in proc.stdout:
        seen.append(line)
        if "coating:" in line:
            break
    else:
        pytest.fail("".join(seen[-20:]) + proc.stderr.read()[-2000:])
    kids = _wait_for(lambda: _children(proc.pid), "the build's workers")
    os.killpg(proc.pid, signum)
    proc.wait(timeout=120)  # against a hang only
    rest, err = proc.stdout.read(), proc.stderr.read()
    assert proc.returncode == code, (proc.returncode, err[-2000:])
    assert "Traceback" not in err + rest and "KeyError" not in err, err[-3000:]
    assert err.strip().splitlines() == [f"interrupted by {signal.Signals(signum).name}: stopped; the output folder "
                                        "is as it was"]
    assert _ended(kids) == []
    assert not out.exists()
