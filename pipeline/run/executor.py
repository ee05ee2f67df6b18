"""Executors: where ``pcrelight batch`` runs its tasks — never in the driver's own process.

An executor runs a picklable function on each of a list of items in worker processes and yields the results
as they finish. The driver (``pcrelight batch``, :mod:`pipeline.run.batch`) creates no GL context: a worker
creates its own, once, on its first GL task (:func:`pipeline.run.batch.worker_context`), so a context is never
inherited across a fork (an EGL context made in a parent makes forked children hang); the local executor
starts its workers by *spawn*, Ray's are separate processes started by its raylet.

The table :data:`EXECUTORS` names the implementations: ``local`` (this module: a process pool on this
machine) and ``ray`` (:mod:`pipeline.run.executor_ray`: a local Ray or an existing cluster). A Dask or Slurm
executor is one more module with an :class:`Executor` subclass and one more row (docs/ARCHITECTURE.md,
"How to add an executor").
"""

from __future__ import annotations

import concurrent.futures as cf
import importlib
import multiprocessing
import os
from abc import ABC, abstractmethod
from typing import Any, Callable, ClassVar, Iterator, Sequence

from ..errors import ConfigError
from ..runtime import get_logger, setup_logging

log = get_logger("executor")


class WorkerLost(RuntimeError):
    """The worker process running a task died (killed, out of memory, its node lost): the task did not finish
    and may be run again."""


class Executor(ABC):
    """Runs ``fn(item)`` for many items in worker processes; ``workers``: how many run at once (None: the
    implementation's default);
    ``verbosity``: the workers' logging (-1 warnings only, 0 info, 1 debug)."""

    name: ClassVar[str] = ""
    # the one retry policy: a task whose worker died is run again up to ``retries`` times — by the engine itself
    # where it can (``reruns_lost``: Ray's max_retries), else by the driver (pcrelight batch's rounds)
    reruns_lost: ClassVar[bool] = False

    def __init__(self, workers: int | None, address: str | None = None, verbosity: int = -1,
                 gpus_per_task: float = 0.0, retries: int = 2) -> None:
        if workers is not None and workers < 1:
            raise ConfigError(f"--workers must be ≥ 1, got {workers}")
        if not 0 <= int(retries) <= 100:
            raise ConfigError(f"retries must be in [0, 100], got {retries}")
        self.workers = int(workers) if workers is not None else 1  # a subclass sets the default
        self.address = address
        self.verbosity = verbosity
        self.gpus_per_task = float(gpus_per_task)
        self.retries = int(retries)

    @abstractmethod
    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        """Yield ``(index, outcome)`` for every item as its task finishes (any order): the result, or the
        exception the task raised (as an object, not raised), or :class:`WorkerLost` when its worker died."""

    def describe(self) -> str:
        """One line for the log: the executor and its workers."""
        return f"{self.name}: {self.workers} worker(s)"

    def close(self, abort: bool = False) -> None:
        """Release the workers; ``abort``: do not wait for running tasks (a stop request)."""

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, kind: Any, exc: Any, tb: Any) -> None:
        self.close(abort=exc is not None)


def init_worker(verbosity: int) -> None:
    """Set up a worker process: pcrelight's logging at ``verbosity`` (the driver's, default warnings only)."""
    setup_logging(verbosity)


class LocalExecutor(Executor):
    """A pool of ``workers`` processes on this machine started by *spawn* (``concurrent.futures``). A worker
    that dies breaks the pool: its task and the tasks not yet finished are answered :class:`WorkerLost` and the
    next :meth:`map` starts a fresh pool."""

    name = "local"

    def __init__(self, workers: int | None, address: str | None = None, verbosity: int = -1,
                 gpus_per_task: float = 0.0, retries: int = 2) -> None:
        super().__init__(workers, address, verbosity, gpus_per_task, retries)
        self.workers = self.workers if workers is not None else (os.cpu_count() or 1)
        if address:
            raise ConfigError("--address is for --executor ray (the local executor runs on this machine)")
        if gpus_per_task:
            raise ConfigError("--gpus-per-job is for --executor ray (local workers share PCRELIGHT_EGL_DEVICE)")
        self._pool: cf.ProcessPoolExecutor | None = None

    def _fresh_pool(self) -> cf.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = cf.ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                                initializer=init_worker, initargs=(self.verbosity,))
        return self._pool

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        pool = self._fresh_pool()
        futures = {pool.submit(fn, x): i for i, x in enumerate(items)}
        broken = False
        for fut in cf.as_completed(futures):
            i = futures[fut]
            try:
                yield i, fut.result()
            except cf.process.BrokenProcessPool as e:
                broken = True
                yield i, WorkerLost(f"a worker process died ({e})")
            except Exception as e:  # the task's own error, handed to the caller as a value
                yield i, e
        if broken:
            self.close()

    def close(self, abort: bool = False) -> None:
        if self._pool is None:
            return
        if abort:  # do not wait for running tasks: stop the pool's processes (atomic writes keep outputs whole)
            for p in multiprocessing.active_children():
                p.terminate()
        self._pool.shutdown(wait=not abort, cancel_futures=True)
        self._pool = None


# name → "module:Class"; `pcrelight batch --executor` lists these
EXECUTORS: dict[str, str] = {
    "local": "pipeline.run.executor:LocalExecutor",
    "ray": "pipeline.run.executor_ray:RayExecutor",
}


def make_executor(name: str, workers: int | None = None, address: str | None = None, verbosity: int = -1,
                  gpus_per_task: float = 0.0, retries: int = 2) -> Executor:
    """The executor ``name`` of :data:`EXECUTORS` with ``workers`` workers (None: this machine's CPU count for
    ``local``; the cluster's CPUs for ``ray``); ``gpus_per_task``: GPUs a task asks for (Ray's scheduling);
    ``retries``: how often a task whose worker died runs again (:attr:`Executor.reruns_lost` says who reruns it)."""
    if name not in EXECUTORS:
        raise ConfigError(f"--executor must be one of {', '.join(EXECUTORS)}, got {name!r}")
    mod, _, cls = EXECUTORS[name].partition(":")
    klass: type[Executor] = getattr(importlib.import_module(mod), cls)
    return klass(workers, address, verbosity, gpus_per_task, retries)
