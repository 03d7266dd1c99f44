"""Where evaluations run: in this process, in local worker processes (spawned), or as Ray tasks on a cluster.

Each pool maps `fn(chunk, *args)` over chunks and yields (chunk index, result, seconds) as chunks finish; callers
place results by index, so what a run computes never depends on the pool or the worker count.
"""

from __future__ import annotations

import importlib
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path
from typing import Any

from a3cqp_rl import worker_exit
from a3cqp_rl.exceptions import A3CQPError

__all__ = ["make_pool", "SerialPool", "ProcessPool", "RayPool"]

Result = tuple[int, Any, float]


def timed(fn: Callable, chunk: Any, args: tuple) -> tuple[Any, float]:
    """fn(chunk, *args) and its wall time [s] (runs in the worker)."""
    t0 = time.perf_counter()
    out = fn(chunk, *args)
    return out, time.perf_counter() - t0


def _init_worker(preload: tuple[str, ...] = ()) -> None:
    # one thread per worker: the pool is the parallelism, and small torch ops run slower with more threads
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"
    # Ctrl-C reaches the whole process group: the parent stops the run and says how to resume, while a worker's
    # KeyboardInterrupt would add its traceback (SystemExit prints none, and still unwinds a trial's temporary folder)
    signal.signal(signal.SIGINT, _stop_quietly)
    for module in preload:  # heavy imports (torch, torchrl) once at start, not inside the first task's timing
        importlib.import_module(module)


def _stop_quietly(signum: int, frame: object) -> None:
    raise SystemExit(130)


class SerialPool:
    """Evaluate in this process, one chunk after the other."""

    workers = 1

    def imap(self, fn: Callable, chunks: Sequence, args: tuple = ()) -> Iterator[Result]:
        """Yield (index, fn(chunk, *args), seconds) per chunk, in order."""
        for i, chunk in enumerate(chunks):
            yield i, *timed(fn, chunk, args)

    def close(self) -> None:
        """Nothing to release."""


class ProcessPool:
    """Local worker processes (started with 'spawn': no state copied from this process but its sys.path)."""

    def __init__(self, workers: int, preload: tuple[str, ...] = ()) -> None:
        self.workers = workers
        # (the workers end without their interpreter's teardown, ~1 s with torch and torchrl: worker_exit)
        self._ex = ProcessPoolExecutor(workers, mp_context=get_context("spawn"), initializer=worker_exit.initializer,
                                       initargs=(os.getpid(), "algorithms.tuning.pool:_init_worker", tuple(preload)))

    def imap(self, fn: Callable, chunks: Sequence, args: tuple = ()) -> Iterator[Result]:
        """Yield (index, fn(chunk, *args), seconds) as chunks finish."""
        pending = {self._ex.submit(timed, fn, chunk, args): i for i, chunk in enumerate(chunks)}
        try:
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for fut in done:
                    i = pending.pop(fut)
                    yield i, *fut.result()
        finally:
            for fut in pending:
                fut.cancel()

    def close(self) -> None:
        """Stop the workers."""
        self._ex.shutdown(cancel_futures=True)


class RayPool:
    """Ray tasks (one CPU each) on an existing cluster (`address`: 'auto' or host:port), or on a Ray instance
    this process has already started; 'local' starts one on this machine with `workers` CPUs.

    Every node must be able to import this package (pip install it there, or share the checkout).
    """

    def __init__(self, address: str, workers: int) -> None:
        try:
            import ray
        except ImportError:
            raise A3CQPError("--ray needs Ray: pip install 'a3cqp-rl[distributed]'") from None
        self._ray = ray
        self._started = False
        if not ray.is_initialized():
            root = str(Path(__file__).resolve().parents[2])  # the checkout, so local workers import this code
            env = {"env_vars": {"PYTHONPATH": os.pathsep.join([root, os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
                                "OMP_NUM_THREADS": "1"}}
            if address == "local":
                ray.init(num_cpus=workers, runtime_env=env, include_dashboard=False, log_to_driver=True)
            else:
                try:
                    ray.init(address=address, runtime_env=env)
                except ConnectionError as exc:
                    raise A3CQPError(f"cannot reach the Ray cluster at {address!r}: {exc}") from None
            self._started = True
        self.workers = int(ray.cluster_resources().get("CPU", workers))
        self._remote = ray.remote(num_cpus=1)(timed)

    def imap(self, fn: Callable, chunks: Sequence, args: tuple = ()) -> Iterator[Result]:
        """Yield (index, fn(chunk, *args), seconds) as tasks finish."""
        ray = self._ray
        refs = {self._remote.remote(fn, chunk, args): i for i, chunk in enumerate(chunks)}
        pending = list(refs)
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                for ref in done:
                    yield refs[ref], *ray.get(ref)
        finally:
            for ref in pending:
                ray.cancel(ref)

    def close(self) -> None:
        """Shut Ray down if this pool started it."""
        if self._started:
            self._ray.shutdown()


def make_pool(workers: int = 1, ray: str | None = None, preload: tuple[str, ...] = ()) -> SerialPool | ProcessPool | RayPool:
    """A pool for `workers` local processes (1 = this process), or Ray tasks when `ray` names a cluster; local
    workers import the `preload` modules when they start."""
    if ray:
        return RayPool(ray, workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1:
        for module in preload:
            importlib.import_module(module)
        return SerialPool()
    return ProcessPool(workers, preload)


