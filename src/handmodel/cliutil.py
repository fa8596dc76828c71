"""Shared by the ``synergy`` and ``tracker`` command lines (no heavy imports at module level)."""
from __future__ import annotations

import functools


def errors_exit_2(fn):
    """Bad input (:class:`~handmodel.errors.ToolkitError`, or an output that would be overwritten)
    becomes one line ``error: …`` on stderr and exit code 2 — never a traceback."""
    import typer

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from .errors import ToolkitError

        try:
            return fn(*args, **kwargs)
        except (ToolkitError, FileExistsError) as err:
            typer.echo(f"error: {err}", err=True)
            raise typer.Exit(2) from None

    return wrapper
