"""The one error type for bad user input: it names the file and the problem."""
from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Malformed or missing input; ``str()`` reads ``<file>: <problem>``."""

    def __init__(self, path: Path | str, problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
