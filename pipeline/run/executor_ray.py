"""The Ray executor of ``pcrelight batch --executor ray`` (:mod:`pipeline.run.executor`'s interface).

Without ``--address`` it starts a Ray on this machine (``ray.init(num_cpus=workers)``, no dashboard) and stops
it at the end; with ``--address`` (``ray://head:10001`` for Ray Client, ``head:6379`` or ``auto`` on a cluster
node) it joins that cluster, whose nodes must have pcrelight installed and see the batch's paths at the same
place (a shared file system: the BSH and the job folders are shared paths). A Ray already initialised in this
process (a test's ``ray.init``) is used as it is and left running.

Ray runs each task in a worker process of its own pool (started by the raylet, never forked from the driver)
and reuses the process for later tasks, so the worker's GL context is made once. A task whose worker dies
(killed, out of memory, node lost) is rerun by Ray (``max_retries``); after that it is answered
:class:`~pipeline.run.executor.WorkerLost`. At most ``workers`` tasks are in flight at once. With
``--gpus-per-job F`` each task asks Ray for F GPUs and its worker's GL context is made on the EGL device of the
first GPU Ray gives it (:func:`pipeline.run.batch.worker_context`).
"""

from __future__ import annotations

import os
import signal
import threading
from typing import Any, Callable, Iterator, Sequence

from ..errors import ConfigError
from .executor import Executor, WorkerLost, init_worker
from ..runtime import get_logger

log = get_logger("executor")


def _python_signal_handlers() -> dict[int, Any]:
    """This process's Python handlers of SIGINT/SIGTERM (pcrelight's, when the CLI installed them)."""
    return {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}


def _restore(handlers: dict[int, Any]) -> None:
    """Put the Python handlers back: ray.init replaces SIGTERM's with its own C++ one, which prints a stack and
    ends the driver (exit 1, or SIGABRT) without the clean-up and the one line of a stop, and ray.shutdown leaves
    the default (measured)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for s, h in handlers.items():
        if callable(h) or h in (signal.SIG_DFL, signal.SIG_IGN):
            signal.signal(s, h)


def _call(fn: Callable[[Any], Any], item: Any, verbosity: int) -> Any:
    """A task on a Ray worker: set up its logging (once a process), then ``fn(item)``."""
    if os.environ.get("PCRELIGHT_WORKER_LOGGING") != str(verbosity):
        init_worker(verbosity)
        os.environ["PCRELIGHT_WORKER_LOGGING"] = str(verbosity)
    return fn(item)


class RayExecutor(Executor):
    """Tasks on a local Ray (``workers`` CPUs, default this machine's) or on the cluster at ``address``
    (``workers``: tasks in flight at once, default the cluster's CPUs)."""

    name = "ray"
    reruns_lost = True      # Ray reruns a task whose worker died (max_retries = the batch's retries)

    def __init__(self, workers: int | None, address: str | None = None, verbosity: int = -1,
                 gpus_per_task: float = 0.0, retries: int = 2) -> None:
        super().__init__(workers, address, verbosity, gpus_per_task, retries)
        try:
            import ray
        except ImportError:
            raise ConfigError("--executor ray needs Ray: pip install 'ray==2.*'") from None
        self._ray = ray
        self._own = not ray.is_initialized()
        if self._own:
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": verbosity >= 0,
                                  "configure_logging": False}
            if address:
                kw["address"] = address
            else:
                kw["num_cpus"] = workers if workers is not None else (os.cpu_count() or 1)
            handlers = self._handlers = _python_signal_handlers()
            try:
                ray.init(**kw)
            except ConnectionError as e:
                raise ConfigError(f"--address {address}: cannot connect to a Ray cluster ({str(e).splitlines()[0]})") from None
            finally:
                _restore(handlers)
        cpus = int(ray.cluster_resources().get("CPU", 1))
        self.workers = int(workers) if workers is not None else max(1, cpus)
        # a GPU task's worker is kept for later tasks (max_calls=0: Ray's default for GPU tasks is a new process
        # each, which would make a GL context a job); its EGL device: pipeline.run.batch.worker_context
        self._remote = ray.remote(num_cpus=1, num_gpus=self.gpus_per_task, max_calls=0, max_retries=self.retries)(_call)
        self._running: dict[Any, int] = {}

    def describe(self) -> str:
        res = self._ray.cluster_resources()
        return (f"ray ({'cluster at ' + self.address if self.address else 'local'}: {len(self._ray.nodes())} node(s), "
                f"{res.get('CPU', 0):g} CPUs, {res.get('GPU', 0):g} GPUs): {self.workers} task(s) at once")

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        ray = self._ray
        todo = list(enumerate(items))[::-1]
        running = self._running = {}
        while todo or running:
            while todo and len(running) < self.workers:
                i, x = todo.pop()
                running[self._remote.remote(fn, x, self.verbosity)] = i
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                i = running.pop(ref)
                try:
                    yield i, ray.get(ref)
                except ray.exceptions.RayTaskError as e:  # the task's own error
                    cause = e.cause if isinstance(getattr(e, "cause", None), BaseException) else e
                    yield i, cause
                except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError,
                        ray.exceptions.OutOfMemoryError, ray.exceptions.TaskUnschedulableError) as e:
                    yield i, WorkerLost(f"{type(e).__name__} after {self.retries} reruns")

    def close(self, abort: bool = False) -> None:
        if abort and self._ray.is_initialized():  # a stop request: the running tasks are not waited for
            for ref in self._running:
                self._ray.cancel(ref, force=True)
        self._running = {}
        if self._own and self._ray.is_initialized():
            self._ray.shutdown()
            self._own = False
            _restore(self._handlers)   # (ray.shutdown leaves SIGTERM at its default: no clean-up, no line)
