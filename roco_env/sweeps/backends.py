"""Where cells run: ``local`` (a process pool on this machine) or ``ray`` (a Ray cluster).

Both take a picklable module-level ``cell_fn(cell) -> record`` that never raises
(see :func:`roco_env.sweeps.episode.run_cell`) and yield ``(cell, record)`` in
completion order; the caller (the parent process) writes the records. A cell is a
pure function of its settings and seed, so both backends give identical records
apart from ``elapsed_s``. If the machinery itself fails for a cell (a worker
killed, a result that cannot be shipped back) that cell gets an error record.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.context
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool

from roco_env.policies import register_policy, registered_policies
from roco_env.sweeps.cells import Cell
from roco_env.sweeps.records import error_record

BACKENDS = ("local", "ray")
RAY_MISSING = "the ray backend needs Ray, which is not installed: pip install roco-env[ray]"

CellFn = Callable[[Cell], dict]
Results = Iterator[tuple[Cell, dict]]


# What a worker imports to run a cell: preloaded by the fork server (see _fork_server).
_WORKER_IMPORTS = ("torch", "roco_env.sweeps.episode")


def default_workers() -> int:
    """All cores this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def _die_with(sweep_pid: int) -> None:
    """Kill this process (SIGKILL) as soon as process ``sweep_pid`` ends, however it ends.

    A pool worker's parent is the fork server, not the sweep, so the kernel's parent-death
    signal (``PR_SET_PDEATHSIG``) would tie it to the server, which itself only exits once
    every worker has (each holds the server's "alive" pipe). So a daemon thread waits on a
    pidfd of the sweep process (Linux >= 5.3) instead; where there is none (macOS, Windows)
    nothing watches. With the workers gone, the fork server and the resource tracker see
    their pipes close and exit too.
    """
    try:
        pidfd = os.pidfd_open(sweep_pid)
    except ProcessLookupError:  # the sweep ended before this worker started
        os.kill(os.getpid(), signal.SIGKILL)
    except (AttributeError, OSError):  # no pidfd on this platform or kernel
        return

    def watch() -> None:
        select.select([pidfd], [], [])  # readable once the process has ended
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="die-with-the-sweep", daemon=True).start()


def _worker_setup(sweep_pid: int) -> None:
    """Pool initializer: workers ignore SIGINT (Ctrl-C reaches the whole process group,
    and the parent alone decides: it stops the workers, see :func:`_stop_workers`);
    SIGTERM gets its default action back; a worker dies with the sweep process
    ``sweep_pid`` even when that is SIGKILLed (:func:`_die_with`)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    _die_with(sweep_pid)


def _run_in_worker(cell_fn: CellFn, policies: dict[str, str], cell: Cell) -> dict:
    """``cell_fn(cell)`` in a pool or Ray worker, which may have run other sweeps' cells:
    torch at one thread (N workers use N cores, not N^2, and a cell runs as ``workers=1``
    runs it; a learned detector then sets its own count), and the sweep process's
    policies registered (names added there by ``register_policy``, which a worker started
    from the fork server, or by Ray, would not otherwise know)."""
    torch = sys.modules.get("torch")  # preloaded in the pool's workers
    if torch is not None:
        torch.set_num_threads(1)
    for name, target in policies.items():
        register_policy(name, target)
    return cell_fn(cell)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Kill the pool's worker processes now (a stopped sweep must not leave them).

    ``shutdown`` would wait for the running cells. SIGKILL: it stops a worker whatever
    its handlers (one still starting has not run :func:`_worker_setup`), and workers hold
    nothing to save (the parent writes the records). ``kill_workers`` only exists from
    Python 3.14, so older versions kill the pool's processes directly.
    """
    kill = getattr(pool, "kill_workers", None)
    if kill is not None:
        kill()
        return
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        process.kill()


def _ready() -> None:
    """A process that does nothing: once it has run, the fork server serves."""


def _start_method() -> str:
    """Where the pool's workers start: the fork server (:func:`_fork_server`), or fresh
    interpreters (``spawn``) on a platform without one (Windows)."""
    return "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"


# The process's pools by (workers, start method): kept between sweeps (see _pool).
_POOLS: dict[tuple[int, str], ProcessPoolExecutor] = {}
os.register_at_fork(after_in_child=_POOLS.clear)  # a forked child has none of their workers


def _pool(workers: int) -> tuple[tuple[int, str], ProcessPoolExecutor]:
    """This process's pool of ``workers`` workers (and its key), started on first use and
    kept: a later sweep reuses its workers warm (imports, compiled kernels, caches), where
    new ones would each pay those on their first cell (docs/performance.md). Dropped when
    a sweep stops early or a worker dies (:func:`_drop_pool`)."""
    key = (workers, _start_method())
    if key not in _POOLS:
        context = (_fork_server() if key[1] == "forkserver"
                   else multiprocessing.get_context(key[1]))
        _POOLS[key] = ProcessPoolExecutor(max_workers=workers, initializer=_worker_setup,
                                          initargs=(os.getpid(),), mp_context=context)
    return key, _POOLS[key]


def _drop_pool(key: tuple[int, str], kill: bool) -> None:
    """Forget the pool of ``key`` and shut it down, its workers killed first if ``kill``."""
    pool = _POOLS.pop(key)
    if kill:
        _stop_workers(pool)
    pool.shutdown(wait=True, cancel_futures=True)


def _fork_server() -> multiprocessing.context.BaseContext:
    """The fork-server context, its server started (once a process) importing once what
    every worker needs, so that each worker starts as a fork of it: a process's first pool
    pays the imports once, every later one starts in a fraction of a second (measured
    with and without the preload in docs/performance.md). Importing torch starts no threads, so the
    workers inherit no OpenMP pool.

    Ctrl-C reaches the whole process group. From the main thread the server starts with
    SIGINT ignored (which survives its exec and passes to the workers): one still
    importing, for seconds, would print a KeyboardInterrupt traceback and die. Returns
    once the server serves: a sweep stopped while the server imports then has asked it
    for no worker, which it would fork later to find the pool's queues gone (another
    traceback).
    """
    from multiprocessing import forkserver  # POSIX only, as the context

    context = multiprocessing.get_context("forkserver")
    context.set_forkserver_preload(["__main__", *_WORKER_IMPORTS])
    handler = signal.getsignal(signal.SIGINT)
    if handler is None or threading.current_thread() is not threading.main_thread():
        forkserver.ensure_running()  # a handler set outside Python cannot be restored
    else:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            forkserver.ensure_running()
        finally:
            signal.signal(signal.SIGINT, handler)
    process = context.Process(target=_ready)
    process.start()
    process.join()
    return context


def run_local(cells: Sequence[Cell], cell_fn: CellFn, workers: int | None = None) -> Results:
    """Run cells in a process pool of ``workers`` processes (default: all cores).

    ``workers=1`` runs in this process (no pool): the 1-process reference for speedups,
    with torch at one thread as in the pool's workers (restored after).

    The pool is kept for the process's later sweeps of as many workers (:func:`_pool`).
    Its workers start from a fork server, not from this process: a worker forked
    from a process that has run torch on several threads inherits a dead OpenMP pool and
    hangs on its first multi-threaded operation (``detector.params.threads`` > 1). So
    ``cells`` and ``cell_fn`` must pickle by reference (module-level functions), and a
    script that runs a sweep needs the ``if __name__ == "__main__":`` guard. Policies
    registered in this process are registered in every worker before its cells.
    """
    workers = workers or default_workers()
    if workers == 1:
        # One torch thread, as in the pool's workers: torch's results can round
        # differently on other thread counts (the learned detector's network does).
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            for cell in cells:
                start = time.perf_counter()
                try:
                    record = cell_fn(cell)
                except Exception as exc:  # noqa: BLE001 - same contract as the pool below
                    record = error_record(cell, exc, time.perf_counter() - start)
                yield cell, record
        finally:
            torch.set_num_threads(threads)
        return
    key, pool = _pool(workers)
    policies = registered_policies()
    broken = False
    try:
        futures = {pool.submit(_run_in_worker, cell_fn, policies, cell):
                   (cell, time.perf_counter()) for cell in cells}
        for future in as_completed(futures):
            cell, start = futures[future]
            try:
                record = future.result()
            except Exception as exc:  # noqa: BLE001 - machinery failure, recorded per cell
                broken |= isinstance(exc, BrokenProcessPool)
                record = error_record(cell, exc, time.perf_counter() - start)
            yield cell, record
    except BaseException:  # stopped (signal, consumer gone): the workers stop too
        _drop_pool(key, kill=True)
        raise
    if broken:  # a worker died: the pool takes no more cells
        _drop_pool(key, kill=False)


def _import_ray():
    try:
        import ray
    except ImportError as exc:
        raise ValueError(RAY_MISSING) from exc
    return ray


def run_ray(cells: Sequence[Cell], cell_fn: CellFn, workers: int | None = None,
            address: str | None = None) -> Results:
    """Run cells as Ray tasks (1 CPU each).

    ``address``: ``"auto"`` (the running cluster), ``"ray://host:10001"`` or
    ``"host:6379"`` to join a cluster; None starts a local Ray with ``workers`` CPUs
    (default: all cores). An already initialised Ray is reused and left running.
    """
    ray = _import_ray()
    started_here = not ray.is_initialized()
    if started_here:
        options = {"include_dashboard": False, "log_to_driver": False}
        if address:
            try:
                ray.init(address=address, **options)
            except ConnectionError as exc:
                raise ValueError(
                    f"no Ray cluster reachable at address {address!r} ({exc}); start one with "
                    "`ray start --head` or leave out the address to run a local Ray"
                ) from exc
        else:
            ray.init(num_cpus=workers or default_workers(), **options)
    try:
        remote_fn = ray.remote(num_cpus=1)(_run_in_worker)
        policies = registered_policies()
        start = time.perf_counter()
        pending = {remote_fn.remote(cell_fn, policies, cell): cell for cell in cells}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                cell = pending.pop(ref)
                try:
                    record = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - worker died etc., recorded per cell
                    record = error_record(cell, exc, time.perf_counter() - start)
                yield cell, record
    finally:
        if started_here:
            ray.shutdown()


def check_backend(backend: str, workers: int | None = None, address: str | None = None) -> None:
    """ValueError naming the bad option (unknown backend, workers < 1, Ray missing, ...)."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of: {', '.join(BACKENDS)}")
    if workers is not None and workers < 1:
        raise ValueError(f"workers must be >= 1; got {workers}")
    if backend == "local" and address:
        raise ValueError("address (--address) is only used by the ray backend")
    if backend == "ray":
        _import_ray()


def run_cells(cells: Sequence[Cell], cell_fn: CellFn, backend: str = "local",
              workers: int | None = None, address: str | None = None) -> Results:
    """Run cells on the named backend after :func:`check_backend`."""
    check_backend(backend, workers, address)
    if backend == "local":
        return run_local(cells, cell_fn, workers)
    return run_ray(cells, cell_fn, workers, address)
