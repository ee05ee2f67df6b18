"""Errors the CLI turns into one clear line and an exit status."""

from __future__ import annotations

import os


class PcrelightError(Exception):
    """Base class: the CLI prints ``pcrelight: <message>``."""

    exit_code = 1


class InputError(PcrelightError):
    """A bad input file or value: ``<file>: <problem>`` (exit status 1)."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(problem if path is None else f"{self.path}: {problem}")


class OutputError(PcrelightError):
    """An output that cannot be written — disk full, a read-only folder, no permission:
    ``<file>: <problem>`` (exit status 1). The atomic writers leave the previous file as it was."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ConfigError(PcrelightError):
    """An out-of-range option or a bad config file (exit status 2, like click's usage errors)."""

    exit_code = 2


class NotImplementedStage(PcrelightError):
    """A stage (or a method of a stage) that is not built yet (exit status 2)."""

    exit_code = 2

    def __init__(self, stage: str, detail: str = ""):
        msg = f"{stage} is not implemented yet"
        super().__init__(msg + (f" ({detail})" if detail else ""))


class MissingPackage(PcrelightError):
    """A reader's package is not installed (exit status 2, like a stage that is not built)."""

    exit_code = 2


class GLUnavailable(PcrelightError):
    """No headless OpenGL context could be created (exit status 1)."""


class Interrupted(BaseException):
    """SIGINT/SIGTERM arrived; the CLI exits with 128 + signal number.

    A BaseException, like KeyboardInterrupt, not an Exception: a catch-all ``except Exception`` in a
    library or a stage (logging's handleError, a reader wrapping its parser's errors) must not swallow
    the stop request (it did: the stage went on and renamed its new output into place, exit 0)."""

    def __init__(self, signum: int):
        self.signum = signum
        self.exit_code = 128 + signum
        super().__init__(f"interrupted by signal {signum}; outputs left as they were")
