"""The ``isolated`` marker's runner (tests/conftest.py): a test whose process a native crash kills (a
segfault in librealsense's threads) runs once more; a crash every time still fails."""
from __future__ import annotations

import os
import signal
import tempfile
from pathlib import Path

import pytest


def _crash():
    os.kill(os.getpid(), signal.SIGSEGV)


@pytest.mark.isolated
@pytest.mark.filterwarnings("ignore:.*passed on its second run")
def test_a_crash_once_is_run_again():
    """Crashes on its first run and passes on its second (both runs are children of the same worker): a
    runner without the retry fails here."""
    mark = Path(tempfile.gettempdir()) / f"sht-crash-once-{os.getppid()}"
    if not mark.exists():
        mark.write_text("crashed once")
        _crash()
    mark.unlink()


@pytest.mark.isolated
@pytest.mark.xfail(strict=True, reason="a crash on every run must fail the test, retry or not")
def test_a_crash_every_time_fails():
    _crash()
