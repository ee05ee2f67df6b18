"""Logging, progress bars, timings and stop requests shared by every stage."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import time
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


def _on_signal(signum: int, frame) -> None:  # noqa: ARG001
    global _STOP
    first = _STOP is None
    _STOP = signum
    if first:
        raise Interrupted(signum)


def install_signal_handlers() -> None:
    """SIGINT/SIGTERM raise :class:`Interrupted`; atomic writes keep outputs intact."""
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)


def check_interrupt() -> None:
    """Raise :class:`Interrupted` if a stop request arrived (for loops in C code that swallow it)."""
    if _STOP is not None:
        raise Interrupted(_STOP)
