"""Where the per-instance work runs: serial, local processes or Dask.

The per-instance steps of a build (read + object frame + resample, coating; paper 2 and
4) are pure functions over small, serialisable inputs (paths, landmarks, the template
mesh, parameters) that return small results (point arrays, figures). An
:class:`Executor` maps such a function over the instances:

==================  ==========================================================
scheduler           runs on
==================  ==========================================================
``serial``          this process, one instance after the other
``processes``       ``jobs`` local processes (spawn; the default)
``dask-local``      a ``dask.distributed`` LocalCluster of ``jobs`` workers
``tcp://host:port`` an existing Dask scheduler (dask-jobqueue, Kubernetes, …)
==================  ==========================================================

Every scheduler runs the same function on the same inputs, so results are identical
bit for bit. Dask is optional (``pip install "ssm-builder[dask]"``); remote workers
need ``ssm_addon`` installed and the input paths readable under the same names.
"""

from __future__ import annotations

import importlib
import logging
import multiprocessing
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from multiprocessing import resource_tracker

from threadpoolctl import threadpool_limits

from .errors import Cancelled, InputError
from .progress import CancelledFn, ProgressFn, report

__all__ = ["CONNECT_TIMEOUT_S", "SCHEDULERS", "Executor", "check_scheduler", "dask_setup", "done_future", "executor_or_local",
           "ignore_sigint", "import_modules", "inner_threads", "probe_scheduler", "run_one_thread", "signals_deferred", "start_resource_tracker", "stop_children", "time_left_text",
           "usable_cores"]

SCHEDULERS = ("serial", "processes", "dask-local")
"""Scheduler names; anything else must be a Dask scheduler address (``tcp://``, ``tls://``, ``ucx://``)."""

CONNECT_TIMEOUT_S = 10.0
"""How long to wait for a Dask scheduler address to answer (the default of ``[compute] connect_timeout_s``)."""

_ADDRESS_PREFIXES = ("tcp://", "tls://", "ucx://", "inproc://", "ws://", "wss://")


def check_scheduler(value: str, where: str = "--scheduler") -> str:
    """Validate a scheduler name or address and return it.

    >>> check_scheduler("dask-local")
    'dask-local'
    >>> check_scheduler("tcp://10.0.0.5:8786")
    'tcp://10.0.0.5:8786'
    """
    value = str(value).strip()
    if value in SCHEDULERS or value.startswith(_ADDRESS_PREFIXES):
        return value
    raise InputError(f"{where}: unknown scheduler {value!r}; use {', '.join(SCHEDULERS)} or a Dask scheduler address "
                     "such as tcp://host:8786")


def time_left_text(done: int, total: int, elapsed_s: float) -> str:
    """'about 3 min left' from the rate so far (empty before the first result).

    >>> time_left_text(10, 40, 20.0)
    'about 1 min left'
    """
    if done <= 0 or done >= total:
        return ""
    left = elapsed_s / done * (total - done)
    if left < 1:
        return "less than 1 s left"
    if left < 60:
        return f"about {left:.0f} s left"
    if left < 3600:
        return f"about {left / 60:.0f} min left"
    return f"about {left / 3600:.1f} h left"


def import_modules(names: Sequence[str]) -> None:
    """Import ``names`` (a worker's start, :meth:`Executor.start_workers`); an import error is
    left to the first task that needs the module."""
    for name in names:
        try:
            importlib.import_module(name)
        except ImportError:
            return


def done_future(fn: Callable, item) -> Future:
    """A finished future of ``fn(item)``, computed here (:meth:`Executor.submit` without workers)."""
    future: Future = Future()
    try:
        future.set_result(run_one_thread(fn, item))
    except Exception as err:  # noqa: BLE001 - kept for result(), as a worker's would be
        future.set_exception(err)
    return future


def run_one_thread(fn: Callable, item):
    """``fn(item)`` with the BLAS limited to one thread.

    Summation order in BLAS depends on its thread count, so the same instance computed
    with 1 or 8 BLAS threads differs in the last bits. Every executor runs each item
    through here, which makes serial, processes and Dask results identical bit for bit
    (and process-level parallelism does not oversubscribe the cores).
    """
    with threadpool_limits(limits=1, user_api="blas"):
        return fn(item)


def inner_threads(wanted: int = 2) -> int:
    """Threads a step may use inside one instance's work (a k-d tree search, say): ``wanted``
    in the main process (one instance at a time: Blender, a serial build), 1 in a worker
    process, whose siblings already keep the cores busy (a thread per call there cost more to
    start than it saved). Only for work whose result does not depend on its thread count."""
    if multiprocessing.parent_process() is not None:
        return 1
    return max(1, min(int(wanted), usable_cores()))


def ignore_sigint() -> None:
    """Worker initializer: Ctrl-C and a hang-up are for the main process, which stops the workers.

    (A terminal sends both to every process of its foreground group, workers included.)
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if hasattr(signal, "SIGHUP"):
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):  # started inside signals_deferred: a SIGTERM held since then ends it now
        signal.pthread_sigmask(signal.SIG_UNBLOCK, _DEFERRED_SIGNALS)


def dask_setup(worker=None) -> None:
    """Dask preload hook (``preload=["ssm_addon.base.compute"]``): a LocalCluster worker leaves
    Ctrl-C and hang-ups to the main process, which closes the cluster, and logs nothing below
    CRITICAL: a task's error reaches the build through its future, and what a worker would log
    while the cluster shuts down under it (a heartbeat to a closed scheduler) is noise."""
    logging.getLogger("distributed").setLevel(logging.CRITICAL)
    if threading.current_thread() is threading.main_thread():
        ignore_sigint()


def start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker inside :func:`signals_deferred`: it inherits
    SIGHUP blocked (a mask it never lifts), so a terminal's hang-up to the whole process group
    does not kill it mid-build (its successor would print a KeyError traceback per
    semaphore); it ignores SIGINT and SIGTERM itself. A signal that comes meanwhile is acted on
    when the block ends (with SIGINT ignored for those milliseconds, a Ctrl-C to the group was
    lost and the build went on)."""
    with signals_deferred():
        resource_tracker.ensure_running()


_DEFERRED_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))


@contextmanager
def signals_deferred() -> Iterator[None]:
    """Hold SIGINT, SIGTERM and SIGHUP until the block ends, then act on the first that came.

    Starting a worker process writes its start-up data down a pipe; a signal that unwound the
    main thread in the middle of that write left a worker that printed ``EOFError: Ran out of
    input`` with a traceback. The three signals are also blocked in the main thread, whose
    mask a worker started here inherits: a terminal's Ctrl-C to the whole process group cannot
    reach the worker while its interpreter starts (:func:`ignore_sigint` unblocks them). Only
    the main thread handles signals; elsewhere this does nothing.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list = []
    previous = {n: signal.signal(n, lambda signum, _frame: arrived.append(signum)) for n in _DEFERRED_SIGNALS}
    mask = getattr(signal, "pthread_sigmask", None)
    before = mask(signal.SIG_BLOCK, _DEFERRED_SIGNALS) if mask is not None else None
    try:
        yield
    finally:
        if mask is not None:
            mask(signal.SIG_SETMASK, before)
        for n, handler in previous.items():
            signal.signal(n, signal.SIG_DFL if handler is None else handler)
        if arrived:
            signal.raise_signal(arrived[0])  # now handled as it would have been (an exception, or the default)


def stop_children(before: set) -> None:
    """Terminate the worker processes started since ``before`` (pids), killing those that linger."""
    children = [c for c in multiprocessing.active_children() if c.pid not in before]
    for child in children:
        child.terminate()
    for child in children:
        child.join(1.0)
        if child.is_alive():
            child.kill()


def inside_blender_program() -> bool:
    """True when this Python runs inside the Blender program, where ``processes`` runs serially.

    The Blender program embeds Python and its worker processes would start Blender's own
    ``sys.executable``; the ``bpy`` module from PyPI (``bpy.app.binary_path`` empty) is an
    ordinary interpreter whose worker processes start as any other's.
    """
    bpy = sys.modules.get("bpy")
    app = getattr(bpy, "app", None)
    return bool(getattr(app, "binary_path", ""))


def usable_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system says, else the CPU count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _host_port(address: str) -> tuple[str, int]:
    rest = address.split("://", 1)[1].rstrip("/")
    host, _, port = rest.rpartition(":")
    if not host or not port.isdigit():
        raise InputError(f"--scheduler {address}: expected tcp://HOST:PORT (a Dask scheduler listens on 8786 by "
                         "default)")
    return host.strip("[]"), int(port)


def probe_scheduler(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """Check that a Dask scheduler answers at ``tcp://HOST:PORT`` within ``timeout_s``.

    A Dask scheduler sends its handshake as soon as a connection opens: a message of
    frames whose first 8 bytes are the frame count (a small little-endian integer). No
    connection, no bytes within the deadline (a silent listener; an HTTP server such as
    the dashboard on 8787 waits for a request) or other bytes are each an InputError that
    names the address and what answered. Interruptible: Ctrl-C stops the wait at once.
    """
    host, port = _host_port(address)
    deadline = time.monotonic() + float(timeout_s)
    try:
        sock = socket.create_connection((host, port), timeout=max(float(timeout_s), 0.1))
    except OSError as err:
        raise InputError(f"--scheduler {address}: nothing accepts connections there ({err.strerror or err}); start a "
                         "scheduler with `dask scheduler` (port 8786) or check the address") from None
    with sock:
        data = b""
        try:
            while len(data) < 8 and time.monotonic() < deadline:
                sock.settimeout(max(deadline - time.monotonic(), 0.05))
                chunk = sock.recv(8 - len(data))
                if not chunk:
                    break
                data += chunk
        except TimeoutError:
            pass
        except OSError as err:
            raise InputError(f"--scheduler {address}: the connection failed ({err})") from None
    if not data:
        hint = " (8787 is the Dask dashboard's port; the scheduler's is 8786 by default)" if port == 8787 else ""
        raise InputError(f"--scheduler {address}: something accepts connections there but sent no Dask handshake "
                         f"within {timeout_s:g} s: not a Dask scheduler{hint}")
    frames = int.from_bytes(data.ljust(8, b"\0"), "little")
    if len(data) < 8 or not 1 <= frames <= 64:
        shown = data[:8].decode("latin-1").encode("unicode_escape").decode()
        raise InputError(f"--scheduler {address}: the server there answered {shown!r}, not a Dask handshake: not a "
                         "Dask scheduler (a web server or another service?)")


def _client_within(client_cls, address: str, timeout_s: float):
    """``client_cls(address)`` in a helper thread, abandoned with an InputError after ``timeout_s``
    (a Client's own timeout does not hold against every server)."""
    box: dict = {}

    def connect():
        try:
            box["client"] = client_cls(address, timeout=f"{timeout_s:g}s")
        except BaseException as err:  # noqa: BLE001 - handed to the caller
            box["error"] = err

    thread = threading.Thread(target=connect, daemon=True, name="ssm-dask-connect")
    thread.start()
    thread.join(timeout_s + 1.0)
    if thread.is_alive():
        raise InputError(f"--scheduler {address}: no Dask scheduler answered within {timeout_s:g} s; start one with "
                         "`dask scheduler` or check the address")
    err = box.get("error")
    if isinstance(err, OSError | TimeoutError):
        raise InputError(f"--scheduler {address}: no Dask scheduler answered within {timeout_s:g} s "
                         f"({type(err).__name__}: {err}); start one with `dask scheduler` or check the address")
    if err is not None:
        raise err
    return box["client"]


class Executor:
    """Maps a per-instance function over inputs on the chosen scheduler.

    Parameters
    ----------
    scheduler : str
        ``"serial"``, ``"processes"``, ``"dask-local"`` or a Dask scheduler address.
    jobs : int
        Local processes (``processes``) or LocalCluster workers (``dask-local``); an
        existing scheduler brings its own workers.

    Use as a context manager; the cluster (or pool) lives until it is closed, so several
    maps (the refinement rounds, say) share it. Inside the Blender program ``processes``
    runs serially (:func:`inside_blender_program`); a Python that imported the ``bpy``
    module runs real processes.

    Raises
    ------
    InputError
        Dask is not installed, or no scheduler answers at the address within
        :data:`CONNECT_TIMEOUT_S`.
    """

    def __init__(self, scheduler: str = "processes", jobs: int = 1, *, start_method: str = "spawn",
                 connect_timeout_s: float = CONNECT_TIMEOUT_S, tasks: int | None = None):
        self.scheduler = check_scheduler(scheduler)
        self.connect_timeout_s = float(connect_timeout_s)
        self.jobs = max(1, int(jobs or 1))
        self.note = ""
        if self.scheduler in ("processes", "dask-local"):
            cores, asked = usable_cores(), self.jobs
            limit = min(cores, tasks) if tasks is not None and self.scheduler == "dask-local" else cores
            if self.jobs > max(1, limit):
                self.jobs = max(1, int(limit))
                why = f"the machine's {cores} cores" if limit == cores else f"the {tasks} instance(s)"
                self.note = f"--jobs {asked} capped at {self.jobs} ({why})"
        if start_method not in ("spawn", "forkserver"):  # fork is avoided: the caller may hold threads
            raise InputError(f"start_method must be 'spawn' or 'forkserver', got {start_method!r}")
        self.start_method = start_method
        self._client = None
        self._cluster = None
        self._pool = None
        self._before_pool: set = set()
        if self.scheduler == "processes" and (inside_blender_program() or self.jobs == 1):
            self.scheduler = "serial"
        if self.scheduler not in ("serial", "processes"):
            self._start_dask()

    # ------------------------------------------------------------------ set-up
    def _start_dask(self) -> None:
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise InputError(f"--scheduler {self.scheduler}: Dask is not installed; install it with "
                             "pip install \"ssm-builder[dask]\" (or use --scheduler processes)") from None
        if self.scheduler == "dask-local":

            # the workers' scratch space in a folder of our own, removed on close (not $TMPDIR/dask-scratch-space)
            import dask

            start_resource_tracker()
            self._scratch = tempfile.mkdtemp(prefix="ssm-dask-")
            self._dask_config = dask.config.set({"temporary-directory": self._scratch})  # scheduler's too
            # no dashboard; the scheduler's own HTTP routes (health, metrics) on a free local port, not on
            # 8787: another cluster there (a second build, a notebook's) would make Dask warn on stderr
            self._cluster = LocalCluster(n_workers=self.jobs, threads_per_worker=1, processes=True,
                                         dashboard_address=None, silence_logs=logging.CRITICAL,
                                         local_directory=self._scratch, preload=[__name__],
                                         scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"})
            self._client = Client(self._cluster)
            return
        deadline = time.monotonic() + self.connect_timeout_s
        if self.scheduler.startswith("tcp://"):
            probe_scheduler(self.scheduler, self.connect_timeout_s)
        self._client = _client_within(Client, self.scheduler, max(deadline - time.monotonic(), 1.0))

    @property
    def workers(self) -> int:
        """Number of workers that run instances at once."""
        if self._client is not None:
            return max(1, len(self._client.scheduler_info().get("workers", {})))
        return 1 if self.scheduler == "serial" else self.jobs

    def describe(self) -> str:
        """One line for the log: scheduler and workers."""
        if self._client is not None:
            return f"Dask scheduler {self._client.scheduler.address}, {self.workers} worker(s)"
        return "serial" if self.scheduler == "serial" else f"{self.jobs} local processes"

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._client is not None:
            self._client.close()
            self._client = None
        if self._cluster is not None:
            self._cluster.close()
            self._cluster = None
        if getattr(self, "_dask_config", None) is not None:
            self._dask_config.__exit__(None, None, None)  # the caller's dask configuration again
            self._dask_config = None
        if getattr(self, "_scratch", None):

            shutil.rmtree(self._scratch, ignore_errors=True)
            self._scratch = None

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _local_pool(self) -> ProcessPoolExecutor:
        """The local worker pool, made on first use; the processes that existed before it are
        remembered, so that an error stops exactly this pool's workers."""
        if self._pool is None:
            self._before_pool = {c.pid for c in multiprocessing.active_children()}
            start_resource_tracker()
            context = multiprocessing.get_context(self.start_method)
            self._pool = ProcessPoolExecutor(max_workers=self.jobs, mp_context=context, initializer=ignore_sigint)
        return self._pool

    def start_workers(self, modules: Sequence[str] = ()) -> None:
        """Start the local worker processes now, each importing ``modules``, so that their start
        (an interpreter and numpy, scipy, scikit-image in each) runs while this process works on
        something else (the template) instead of before the first instance.

        Only for ``"processes"`` with two or more workers; serial and Dask executors do nothing
        (a Dask worker is started with the cluster). Nothing waits for the workers: a module
        that fails to import fails again, with its message, in the first :meth:`map`.
        """
        if self.scheduler != "processes" or self._pool is not None:
            return
        for _ in range(self.jobs):  # each submit starts a worker process (none is idle yet)
            self.submit(import_modules, tuple(modules))

    def submit(self, fn: Callable, item) -> Future:
        """``fn(item)`` begun now; its future's ``result()`` gives the value or raises its error.

        On a ``"processes"`` executor it runs on a local worker (through :func:`run_one_thread`,
        as :meth:`map`), so this process can work on something else meanwhile; on the others it
        is computed here before this returns (a Dask worker may be another machine, and the work
        given here writes this machine's files).
        """
        if self.scheduler == "processes":
            with signals_deferred():  # the submit may start a worker process
                return self._local_pool().submit(run_one_thread, fn, item)
        return done_future(fn, item)

    # ------------------------------------------------------------------ map
    def map(self, fn: Callable, items: Sequence, *, on_result: Callable | None = None,
            progress: ProgressFn = None, cancelled: CancelledFn = None, labels: Sequence[str] | None = None,
            verb: str = "done") -> list:
        """``[fn(x) for x in items]``, computed on the scheduler, in the order of ``items``.

        ``on_result(i, result)`` is called in this process as each result arrives (to
        write it to the cache at once). ``progress`` gets ``"<verb> <label> (k/n), about
        … left"`` per result. Cancelling stops submitting, lets running items finish
        (their ``on_result`` is still called) and raises :class:`~ssm_addon.base.errors.Cancelled`.
        An error in one item stops the map and is raised here unchanged.
        """
        items = list(items)
        n = len(items)
        labels = list(labels) if labels is not None else [str(i) for i in range(n)]
        results: list = [None] * n
        if n == 0:
            return results
        t0 = time.perf_counter()
        count = [0]

        def arrived(i, value):
            results[i] = value
            count[0] += 1
            if on_result is not None:
                on_result(i, value)
            left = time_left_text(count[0], n, time.perf_counter() - t0)
            report(progress, count[0] / n, f"{verb} {labels[i]} ({count[0]}/{n})" + (f", {left}" if left else ""))

        if self.scheduler == "serial" or n == 1 and self._client is None:
            for i, item in enumerate(items):
                if cancelled is not None and cancelled():
                    raise Cancelled(f"cancelled after {count[0]} of {n}")
                arrived(i, run_one_thread(fn, item))
            return results
        if self._client is not None:
            self._map_dask(fn, items, arrived, cancelled)
        else:
            self._map_processes(fn, items, arrived, cancelled)
        return results

    def _map_processes(self, fn, items, arrived, cancelled) -> None:

        pool = self._local_pool()
        before = self._before_pool
        queue = list(range(len(items)))
        pending: dict = {}
        ahead = self.jobs  # one in flight per worker: cancellation stops after the running ones

        try:
            while queue or pending:
                while queue and len(pending) < ahead:
                    i = queue.pop(0)
                    pending[self.submit(fn, items[i])] = i
                finished, _ = wait(list(pending), timeout=0.2, return_when=FIRST_COMPLETED)
                for fut in finished:
                    arrived(pending.pop(fut), fut.result())
                if cancelled is not None and cancelled():
                    for fut in pending:
                        fut.cancel()
                    for fut, i in list(pending.items()):
                        if not fut.cancelled():
                            try:
                                arrived(i, fut.result())
                            except Exception:  # noqa: BLE001 - cancelled: keep what finished cleanly
                                pass
                    raise Cancelled("cancelled by the user")
        except BaseException:
            self._pool = None
            pool.shutdown(wait=False, cancel_futures=True)
            stop_children(before)  # an interrupt or error: no worker outlives the map
            raise

    def _map_dask(self, fn, items, arrived, cancelled) -> None:
        from distributed import as_completed

        client = self._client
        queue = list(range(len(items)))
        live: dict = {}  # key -> (future, index)

        def submit(i):
            fut = client.submit(run_one_thread, fn, items[i], pure=False, key=f"ssm-{os.getpid()}-{id(items)}-{i}")
            live[fut.key] = (fut, i)
            return fut

        stream = as_completed([submit(queue.pop(0)) for _ in range(min(2 * self.workers, len(queue)))])
        try:
            for fut in stream:
                _, i = live.pop(fut.key)
                arrived(i, fut.result())
                if cancelled is not None and cancelled():
                    raise Cancelled("cancelled by the user")
                if queue:
                    stream.add(submit(queue.pop(0)))
        except BaseException:
            client.cancel([f for f, _ in live.values()])
            raise


@contextmanager
def executor_or_local(executor: Executor | None, jobs: int = 1, tasks: int | None = None,
                      **options) -> Iterator[Executor]:
    """``executor`` as given (the caller's: left open), else local processes for this call.

    The local pool has ``jobs`` processes, at most ``tasks`` (and the usable cores,
    :class:`Executor`), and is closed on leaving the block, also on an error. ``options``
    go to :class:`Executor` (``start_method``).
    """
    if executor is not None:
        yield executor
        return
    wanted = max(1, int(jobs or 1))
    if tasks is not None:
        wanted = max(1, min(wanted, int(tasks)))
    with Executor("processes", wanted, **options) as local:
        yield local
