"""Logging, progress bars, timings and stop requests shared by every stage."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import time
from pathlib import Path
from typing import Iterable, Iterator, TypeVar

from .errors import Interrupted

T = TypeVar("T")
_QUIET = False
_STOP: int | None = None


def get_logger(name: str) -> logging.Logger:
    """A logger under the ``pcrelight`` namespace (the CLI sets the level)."""
    return logging.getLogger(f"pcrelight.{name}")


class _Formatter(logging.Formatter):
    """Info lines as they are; a warning or an error says so (``WARNING: …``)."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        line = super().formatMessage(record)
        if record.levelno >= logging.WARNING:
            head, sep, msg = line.partition(": ")
            return f"{head}: {record.levelname}: {msg}" if sep else f"{record.levelname}: {line}"
        return line


def process_age_s() -> float | None:
    """Seconds since this process started (Linux /proc; None elsewhere): the interpreter's start-up and imports
    when called at the start of a stage."""
    try:
        import os

        start_ticks = int(open("/proc/self/stat").read().rsplit(")", 1)[1].split()[19])
        uptime = float(open("/proc/uptime").read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return None


def available_memory() -> int | None:
    """Bytes this process may still allocate (Linux): /proc/meminfo's MemAvailable, less where a cgroup v2 limit
    (memory.max − memory.current) is tighter; None where neither can be read."""
    best = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                best = int(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        pass
    try:
        cg = Path("/sys/fs/cgroup")
        lim = (cg / "memory.max").read_text().strip()
        if lim != "max":
            left = int(lim) - int((cg / "memory.current").read_text())
            best = left if best is None else min(best, left)
    except (OSError, ValueError):
        pass
    return best


def setup_logging(verbosity: int) -> None:
    """-q → warnings only, default → info, -v → debug (tracebacks are shown by the CLI)."""
    global _QUIET
    _QUIET = verbosity < 0
    level = logging.WARNING if verbosity < 0 else logging.DEBUG if verbosity > 0 else logging.INFO
    root = logging.getLogger("pcrelight")
    root.handlers.clear()
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(_Formatter("%(asctime)s %(name)s: %(message)s", "%H:%M:%S"))
    root.addHandler(h)
    root.setLevel(level)
    root.propagate = False


def progress_enabled() -> bool:
    """A bar only on an interactive terminal, never in CI or with -q."""
    return (not _QUIET) and sys.stderr.isatty() and os.environ.get("CI", "").lower() not in ("1", "true", "yes")


def progress(iterable: Iterable[T], total: int | None = None, desc: str = "") -> Iterator[T]:
    """Iterate with a tqdm bar (with ETA) when :func:`progress_enabled`; checks for stop requests."""
    if progress_enabled():
        from tqdm import tqdm

        it: Iterable[T] = tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True)
    else:
        it = iterable
    for x in it:
        check_interrupt()
        yield x


class Timings:
    """Wall-clock seconds per named step: ``with t.step("sort"): ...``."""

    def __init__(self) -> None:
        self._d: dict[str, float] = {}

    @contextlib.contextmanager
    def step(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._d[name] = self._d.get(name, 0.0) + time.perf_counter() - t0

    def as_dict(self) -> dict[str, float]:
        return {k: round(v, 6) for k, v in self._d.items()}

    @property
    def total(self) -> float:
        return sum(self._d.values())


# Where raising would not stop the stage but print "Exception ignored in …" and a traceback: ctypes
# callbacks (llvmlite's object-cache hook while numba compiles: seen in the kill tests), numba's compiler
# and finalisers (__del__). A stop that lands there is kept and raised at the next safe point:
# :func:`check_interrupt` (progress loops, and io.atomic_path before it renames an output into place).
_DEFER_IN = (f"{os.sep}llvmlite{os.sep}", f"{os.sep}numba{os.sep}", f"{os.sep}ctypes{os.sep}")
# ... and imports: raised inside one, a C extension's initialisation fails ("ImportError: initialization
# failed") or leaves a half-made native module whose teardown crashed the interpreter (SIGSEGV, make fuzz's
# signal trials on import, whose Open3D import takes ~0.5 s).
_IMPORTING = "<frozen importlib"
_RAISED = False


def _unsafe_to_raise(frame) -> bool:
    f = frame
    while f is not None:
        co = f.f_code
        if co.co_name == "__del__" or any(m in co.co_filename for m in _DEFER_IN) or co.co_filename.startswith(_IMPORTING):
            return True
        f = f.f_back
    return False


_HELD = 0   # > 0 inside held_stops()


@contextlib.contextmanager
def held_stops() -> Iterator[None]:
    """Around a call whose native worker threads use the caller's arrays (SciPy's ``cKDTree.query(...,
    workers=-1)`` runs Python threads over C++ loops and joins them): a stop that lands inside waits for the call to
    return and is raised then. Raised while the threads ran, the unwinding freed their arrays under them (SIGSEGV
    after the stop's line: make fuzz's import signal trials, 1 in 40)."""
    global _HELD
    _HELD += 1
    try:
        yield
    finally:
        _HELD -= 1
    if _HELD == 0:
        check_interrupt()


def _on_signal(signum: int, frame) -> None:
    global _STOP, _RAISED
    if _STOP is None:
        _STOP = signum
    if _RAISED or _HELD or _unsafe_to_raise(frame):
        return  # raised once already (let the clean-up finish), or deferred to check_interrupt()
    _RAISED = True
    raise Interrupted(_STOP)


def stop_signal() -> int | None:
    """The signal number of a stop request that arrived (SIGINT/SIGTERM), or None."""
    return _STOP


def install_signal_handlers() -> None:
    """SIGINT/SIGTERM raise :class:`Interrupted`; atomic writes keep outputs intact."""
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)


def check_interrupt() -> None:
    """Raise :class:`Interrupted` if a stop request arrived (for loops in C code that swallow it, and stops
    deferred by the handler)."""
    global _RAISED
    if _STOP is not None:
        _RAISED = True
        raise Interrupted(_STOP)
