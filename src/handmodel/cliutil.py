"""Shared by the ``synergy`` and ``tracker`` command lines (no heavy imports at module level)."""
from __future__ import annotations

import errno
import functools
import os
import sys

# What an OS error number means for an output or input path, in the words a user acts on.
_OS_REASONS = {
    errno.ENOSPC: "no space left on the device",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EISDIR: "is a folder, not a file",
    errno.ENOTDIR: "a part of the path is not a folder",
    errno.ENOENT: "no such file or folder",
    errno.EEXIST: "exists and is never overwritten",
    errno.ENAMETOOLONG: "file name too long",
    errno.EIO: "input/output error",
    errno.EFBIG: "file too large",
    errno.EMFILE: "too many open files",
}


def os_error_line(err: OSError) -> str:
    """``<path>: <problem>`` for an OS error, naming the path whenever the error carries one."""
    reason = _OS_REASONS.get(err.errno) if err.errno is not None else None
    # our own OSErrors carry a specific text (say "the written file differs from the data")
    own = err.strerror and err.strerror != os.strerror(err.errno or 0)
    reason = err.strerror if own or reason is None else reason
    reason = reason or str(err)
    if err.filename is not None and str(err.filename):
        where = os.fsdecode(err.filename)
        if err.filename2:
            where += f" -> {os.fsdecode(err.filename2)}"
        return f"{where}: {reason}"
    return reason


def error_line(err: BaseException) -> str:
    """The one line printed for ``err``: newlines folded, so nothing can look like a second
    message, and no markup (the text is printed as is)."""
    if isinstance(err, OSError) and not (isinstance(err, FileExistsError) and err.errno is None):
        text = os_error_line(err)
    elif isinstance(err, MemoryError):
        text = "out of memory"
    else:
        text = str(err)
    return "error: " + " ".join(text.split())


def print_error(err: BaseException) -> None:
    """Write ``error: …`` to stderr as plain text: not through rich, so ``[bold]`` in a file name
    stays as typed and a long line is not wrapped."""
    sys.stdout.flush()
    sys.stderr.write(error_line(err) + "\n")
    sys.stderr.flush()


def errors_exit_2(fn):
    """Bad input (:class:`~handmodel.errors.ToolkitError`), an output that would be overwritten,
    and any OS error (no space, read-only, permission, is-a-folder, …) become one plain line
    ``error: <path>: <problem>`` on stderr and exit code 2 -- never a traceback, and nothing is
    printed after it."""
    import typer

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from .errors import ToolkitError

        try:
            return fn(*args, **kwargs)
        except (ToolkitError, OSError, MemoryError) as err:
            print_error(err)
            raise typer.Exit(2) from None

    return wrapper
