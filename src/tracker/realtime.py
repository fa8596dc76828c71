"""Real time: a frame loop that keeps up with its sensor however long a fit takes.

A start search or a size calibration can take a second; a live loop that waited for it would freeze
and fall behind the sensor. :class:`FrameBudget` runs each fit on a worker thread and gives the loop
the fit's result only when it ends within the frame's budget; otherwise — or while the worker is
still busy with an earlier frame — the loop publishes a prediction (:func:`predicted_theta`: the last
fitted hand moved on by its last change) and goes on with the next frame, whose fit starts once the
worker is free (the newest frame, not a queue of old ones). :func:`paced` delivers a recording's
frames at its own rate, as a sensor would, dropping those the loop is too late for.

Used by :class:`tracker.stream.HandTracker` (``budget_ms``) and :func:`tracker.run.track_realtime`
(``tracker live --realtime``).

>>> b = FrameBudget(budget_ms=50)
>>> b(lambda x: x + 1, 41)  # a fit within the budget: its result
42
>>> import threading
>>> gate = threading.Event()
>>> b(gate.wait) is None  # a fit that overruns: None now (the loop predicts) ...
True
>>> b(lambda: 0) is None  # ... and while the worker is busy, no new fit starts
True
>>> gate.set(); b.wait()  # the late fit's own result, when the caller wants it
True
>>> b.close()
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FitTimeout

import numpy as np

from .errors import TrackerError


class FrameBudget:
    """Fits on one worker thread, each waited for at most ``budget_ms`` from the call.

    Parameters
    ----------
    budget_ms : float
        How long a call waits for its fit (ms); a sensor's frame period is the natural budget (33 ms
        at 30 fps).
    """

    def __init__(self, budget_ms: float):
        if not (isinstance(budget_ms, (int, float)) and budget_ms > 0 and np.isfinite(budget_ms)):
            raise TrackerError("budget_ms", f"must be a positive number of ms, got {budget_ms!r}")
        self.budget_ms = float(budget_ms)
        self._worker = ThreadPoolExecutor(1, thread_name_prefix="hand-fit")
        self._pending = None
        self.overruns_ = 0   # fits that did not end within their budget
        self.skipped_ = 0    # calls that found the worker busy (no fit started)

    @property
    def busy(self) -> bool:
        """Whether the worker is still fitting an earlier call's frame."""
        return self._pending is not None and not self._pending.done()

    def __call__(self, fit, *args):
        """``fit(*args)`` on the worker: its result if it ends within the budget, else None (then, or
        while the worker is busy with an earlier frame, the caller publishes a prediction)."""
        t0 = time.perf_counter()
        if self._pending is not None and self._pending.done():
            self._pending.result()  # a fit that failed raises here, not silently later
            self._pending = None
        if self._pending is not None:
            self.skipped_ += 1
            return None
        self._pending = self._worker.submit(fit, *args)
        try:
            r = self._pending.result(timeout=max(self.budget_ms / 1000.0 - (time.perf_counter() - t0), 0.0))
        except FitTimeout:
            self.overruns_ += 1
            return None
        self._pending = None
        return r

    def wait(self):
        """The result of the fit the worker is on (None when idle), waiting for it."""
        if self._pending is None:
            return None
        r, self._pending = self._pending.result(), None
        return r

    def close(self) -> None:
        """Stop the worker after the fit it is on."""
        self._worker.shutdown(wait=True)


def predicted_theta(last, before=None, turn=False) -> np.ndarray:
    """The hand of the last fit ``last`` moved on by its change since ``before`` (both θ, or None), the
    global rotation kept, or with ``turn`` turned on by its last turn (:func:`handmodel.rigid.turned_on`),
    as the tracker's own prediction does (``predict.turn``): what a frame gets whose fit is pending.

    >>> last, before = np.array([0.0, 0, 0, 0.1, 0, 0, 1.0]), np.array([0.0, 0, 0, 0.0, 0, 0, 0.8])
    >>> predicted_theta(last, before)
    array([0. , 0. , 0. , 0.1, 0. , 0. , 1.2])
    >>> np.round(predicted_theta(last, before, turn=True), 6)
    array([0. , 0. , 0. , 0.2, 0. , 0. , 1.2])
    """
    from handmodel.rigid import turned_on

    theta = np.array(last, float)
    if before is not None and np.all(np.isfinite(before)):
        before = np.asarray(before, float)
        moved = theta + (theta - before)
        moved[3:6] = turned_on(theta[3:6], before[3:6]) if turn else theta[3:6]
        theta = moved
    return theta


def paced(frames, fps: float, *, clock=time.monotonic, sleep=time.sleep, dropped=None):
    """The ``frames`` (each with ``time_s``) at their own times from the first one's delivery, as a
    sensor delivers them; a frame whose time has passed by more than one frame period when the loop
    asks for it is dropped (appended to ``dropped`` when given), as a sensor's would be."""
    period, start = 1.0 / fps, None
    for frame in frames:
        now = clock()
        if start is None:
            start = now - frame.time_s
        due = start + frame.time_s
        if now - due > period:
            if dropped is not None:
                dropped.append(frame.index)
            continue
        if due > now:
            sleep(due - now)
        yield frame
