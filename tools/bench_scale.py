"""Scale-out benchmark: builds of n demo instances per scheduler, resume after a kill, PCA at 10⁴ shapes.

Usage::

    python tools/bench_scale.py build [--n 100,300,1000] [--schedulers processes,dask-local] [--jobs 2]
    python tools/bench_scale.py resume [--n 300] [--jobs 2]
    python tools/bench_scale.py pca [--n 10000] [--points 5000] [--modes 100] [--precision float32]
    python tools/bench_scale.py study [--n 10000] [--points 627]

``build`` prints, per n and scheduler: wall time, coating time per instance and per
instance-worker, peak resident memory of the main process and of the largest worker
(sampled every 0.1 s with psutil), and a projection to 10⁴ and 10⁵ instances on 100
workers from the measured per-instance cost. ``resume`` kills a build (SIGKILL) once half
of the instances are in the cache and times the rerun. ``pca`` builds a model and its
metrics from synthetic points (low rank plus noise) and prints time and peak memory;
``study`` times what a build does with such a model after the metrics: the leave-one-out
outlier scores, the scores table and the shape analysis (a group and a covariate, 1,000
permutations), each with its peak memory.
Populations are generated once into ``--data`` (default /tmp/ssm-bench-scale).
"""

from __future__ import annotations

import argparse
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ssm_addon.cli import demo  # noqa: E402
from ssm_addon.pipeline.project import read_project  # noqa: E402
from ssm_addon.pipeline.project_build import build  # noqa: E402


class MemorySampler:
    """Peak RSS (MB) of this process and of its largest descendant, sampled in a thread."""

    def __init__(self, interval_s: float = 0.1):
        import psutil

        self._me = psutil.Process()
        self.interval_s = interval_s
        self.main_mb = 0.0
        self.worker_mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        import psutil

        while not self._stop.is_set():
            try:
                self.main_mb = max(self.main_mb, self._me.memory_info().rss / 2**20)
                for child in self._me.children(recursive=True):
                    try:
                        self.worker_mb = max(self.worker_mb, child.memory_info().rss / 2**20)
                    except psutil.Error:
                        pass
            except psutil.Error:
                pass
            time.sleep(self.interval_s)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def population(data: Path, n: int) -> Path:
    folder = data / f"demo-{n}"
    if not (folder / "project.toml").exists():
        t0 = time.perf_counter()
        demo.make_demo_population(folder, n=n, seed=0)
        print(f"generated {n} demo instances in {time.perf_counter() - t0:.1f} s", flush=True)
    return folder / "project.toml"


def cmd_build(args) -> None:
    data = Path(args.data)
    rows = []
    for n in [int(v) for v in args.n.split(",")]:
        proj = read_project(population(data, n))
        for scheduler in args.schedulers.split(","):
            with tempfile.TemporaryDirectory(dir=data) as tmp, MemorySampler() as mem:
                t0 = time.perf_counter()
                res = build(proj, Path(tmp) / "out", jobs=args.jobs, scheduler=scheduler, cache="off", log=None,
                            blend=False)
                wall = time.perf_counter() - t0
            coat = res.timings_s["coating"]
            per = coat / n
            rows.append((n, scheduler, wall, coat, per, per * args.jobs, mem.main_mb, mem.worker_mb, res.timings_s))
            print(f"n={n:5d} {scheduler:11s} wall {wall:7.1f} s, coating {coat:7.1f} s = {per:.3f} s/instance "
                  f"({per * args.jobs:.3f} s per instance per worker), model {res.timings_s.get('model', 0):.2f} s, "
                  f"metrics {res.timings_s.get('metrics', 0):.2f} s; peak RSS main {mem.main_mb:.0f} MB, "
                  f"largest worker {mem.worker_mb:.0f} MB", flush=True)
            print("  stages: " + ", ".join(f"{k} {v:.1f} s" for k, v in res.timings_s.items()), flush=True)
    if rows:
        cost = max(r[5] for r in rows if r[0] == max(x[0] for x in rows))  # s per instance per worker, largest n
        for total in (10_000, 100_000):
            print(f"projection: {total} instances on 100 workers: coating ≈ {total * cost / 100 / 60:.1f} min "
                  f"({cost:.3f} s per instance per worker, measured at n = {max(r[0] for r in rows)}), plus the "
                  "model and metrics of the main process")


def cmd_resume(args) -> None:
    data = Path(args.data)
    n = int(args.n)
    proj = population(data, n)
    with tempfile.TemporaryDirectory(dir=data) as tmp:
        out, cache = Path(tmp) / "out", Path(tmp) / "cache"
        cmd = [sys.executable, "-m", "ssm_addon", "build", str(proj), "--out", str(out), "--no-blend",
               "--jobs", str(args.jobs), "--cache", str(cache)]
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        def cached() -> int:
            return len(list((cache / "instances").glob("*.npz")))

        while proc.poll() is None and cached() < n // 2:  # the cache folder appears with its first entry
            time.sleep(0.05)
        killed_after = time.perf_counter() - t0
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        done = cached()
        t1 = time.perf_counter()
        res = subprocess.run(cmd, env=env, capture_output=True, text=True)
        rerun = time.perf_counter() - t1
        line = next((m for m in res.stdout.splitlines() if "taken from the cache" in m), "")
        print(f"n={n}: killed after {killed_after:.1f} s with {done} of {n} coatings cached; rerun {rerun:.1f} s "
              f"(exit {res.returncode}): {line.strip()}")


def cmd_pca(args) -> None:
    from ssm_addon.model.metrics import evaluate
    from ssm_addon.model.pca import build_model

    n, npts, k = int(args.n), int(args.points), 40
    dtype = np.float32 if args.precision == "float32" else np.float64
    sd = (30.0 / np.arange(1, k + 1)).astype(dtype)
    t0 = time.perf_counter()
    x = synthetic_shapes(n, npts, k, dtype)
    print(f"synthetic {n} shapes x {npts} points ({x.nbytes / 2**30:.2f} GB {args.precision}) in "
          f"{time.perf_counter() - t0:.1f} s", flush=True)
    with MemorySampler() as mem:
        t0 = time.perf_counter()
        model = build_model(x, np.zeros((0, 3), int), [str(i) for i in range(n)], n_modes=int(args.modes),
                            precision=args.precision)
        t_model = time.perf_counter() - t0
        t0 = time.perf_counter()
        metrics = evaluate(model, n_samples=500, seed=0, max_loo=100)
        t_metrics = time.perf_counter() - t0
    g = metrics.generalization
    print(f"PCA ({model.params['eigensolver']}): {model.n_modes} modes in {t_model:.1f} s; metrics "
          f"({g['method']}) in {t_metrics:.1f} s; peak RSS {mem.main_mb / 1024:.2f} GB "
          f"(ru_maxrss {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GB)")
    print(f"  variance of mode 1..3: {', '.join(f'{v:.1f}' for v in model.variances[:3])} mm² "
          f"(true {', '.join(f'{v:.1f}' for v in (sd[:3].astype(float) ** 2))} + noise)")


def synthetic_shapes(n: int, npts: int, k: int = 40, dtype=np.float64, seed: int = 0) -> np.ndarray:
    """(n, npts, 3) shapes of low rank (``k`` modes, SD 30/j mm) plus 0.2 mm noise, made in blocks."""
    rng = np.random.default_rng(seed)
    basis = np.linalg.qr(rng.standard_normal((3 * npts, k)))[0].T.astype(dtype)
    sd = (30.0 / np.arange(1, k + 1)).astype(dtype)
    x = np.empty((n, npts, 3), dtype)
    for start in range(0, n, 1000):  # bounded temporaries
        stop = min(n, start + 1000)
        block = (rng.standard_normal((stop - start, k)).astype(dtype) * sd) @ basis
        block += rng.standard_normal(block.shape).astype(dtype) * dtype(0.2)
        x[start:stop] = block.reshape(-1, npts, 3)
    return x


def cmd_study(args) -> None:
    from ssm_addon.analysis import analyze, attributes_from_tables
    from ssm_addon.model.files import write_score_tables
    from ssm_addon.model.pca import build_model
    from ssm_addon.model.quality import loo_outlier_scores

    n, npts = int(args.n), int(args.points)
    x = synthetic_shapes(n, npts)
    rng = np.random.default_rng(1)
    age = rng.uniform(20, 80, n)
    long = np.arange(n) % 2 == 1
    x[:, :, 2] += 0.02 * (age - 50)[:, None] + 0.5 * long[:, None]  # an age effect and a group difference
    names = [f"s{i:05d}" for i in range(n)]
    model = build_model(x, np.zeros((0, 3), int), names, n_modes=int(args.modes) or None)
    attrs = attributes_from_tables({m: {"group": "long" if g else "short", "age": float(a)}
                                    for m, g, a in zip(names, long, age)})
    print(f"synthetic {n} shapes x {npts} points, model of {model.n_modes} modes", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        steps = (("outlier scores", lambda: loo_outlier_scores(model.instance_points)),
                 ("scores.csv", lambda: write_score_tables(model, tmp)),
                 ("shape analysis", lambda: analyze(model, attrs, group="group", covariates=["age"],
                                                    permutations=1000)))
        for label, step in steps:
            with MemorySampler() as mem:
                t0 = time.perf_counter()
                step()
                seconds = time.perf_counter() - t0
            print(f"  {label:15s} {seconds:7.1f} s, peak RSS {mem.main_mb:.0f} MB", flush=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    b = sub.add_parser("build")
    b.add_argument("--n", default="100,300,1000")
    b.add_argument("--schedulers", default="processes,dask-local")
    b.add_argument("--jobs", type=int, default=2)
    r = sub.add_parser("resume")
    r.add_argument("--n", default="300")
    r.add_argument("--jobs", type=int, default=2)
    p = sub.add_parser("pca")
    p.add_argument("--n", default="10000")
    p.add_argument("--points", default="5000")
    p.add_argument("--modes", default="100")
    p.add_argument("--precision", default="float64", choices=("float64", "float32"))
    st = sub.add_parser("study")
    st.add_argument("--n", default="10000")
    st.add_argument("--points", default="627")
    st.add_argument("--modes", default="0", help="modes kept (0: all)")
    for x in (b, r, p, st):
        x.add_argument("--data", default="/tmp/ssm-bench-scale")
    args = ap.parse_args(argv)
    Path(args.data).mkdir(parents=True, exist_ok=True)
    {"build": cmd_build, "resume": cmd_resume, "pca": cmd_pca, "study": cmd_study}[args.cmd](args)


if __name__ == "__main__":
    main()
