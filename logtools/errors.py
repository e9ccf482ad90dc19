"""tapost's known failures. Each becomes one line on stderr and an exit code in the CLI."""
from __future__ import annotations


class TapostError(Exception):
    """Base of every error the CLI reports as one line. ``exit_code`` follows DESIGN.md."""

    exit_code = 1

    def __init__(self, problem: str, path: str | None = None):
        self.problem = problem
        self.path = path
        super().__init__(f"{path}: {problem}" if path else problem)


class InputError(TapostError):
    """Bad usage or unreadable input (missing file, wrong format, corrupt, no such selector)."""

    exit_code = 2


class AnalysisError(TapostError):
    """The data are readable but cannot support the analysis (no overlap, no motion, NaNs)."""

    exit_code = 1


def os_error_path(exc: OSError) -> str | None:
    """The path an OSError is about as the user knows it: a rename's target (the output), not its temporary
    source; else the one file it names, or None."""
    return exc.filename2 if exc.filename2 is not None else exc.filename
