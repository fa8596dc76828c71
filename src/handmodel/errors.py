"""Error types. Every error for bad input carries the file (or object) and the reason.

The CLIs catch :class:`ToolkitError`, print ``str(err)`` on one line and exit with code 2.
"""
from __future__ import annotations

from os import PathLike


class ToolkitError(ValueError):
    """Base of all bad-input errors of this project: ``<where>: <reason>``."""

    def __init__(self, where: str | PathLike | None, reason: str):
        self.where = None if where is None else str(where)
        self.reason = reason
        super().__init__(f"{self.where}: {reason}" if self.where else reason)

    def __reduce__(self):
        # rebuilt from (where, reason), not from the formatted message: an error raised in a worker
        # process (Dask, the report's parallel steps) reaches the caller as itself
        return type(self), (self.where, self.reason)


class HandModelError(ToolkitError):
    """A hand-model file or a parameter vector is invalid."""


class SolverError(ToolkitError):
    """Bad input to the IK solver (shapes, NaN parameters, bad subspace)."""
