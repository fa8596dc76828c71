"""Low-pass filtering of marker trajectories (shared by the calibration and the IK)."""
from __future__ import annotations

import numpy as np
from scipy.signal import butter, filtfilt

from .errors import SynergyError


def lowpass_markers(points, rate, cutoff_hz, order=4):
    """Zero-phase Butterworth low-pass of marker trajectories ``(F, M, 3)``, gap-aware: each
    contiguous run of valid samples is filtered on its own; runs too short to filter stay raw, and so
    does everything when the rate is unknown (0) or the cut-off at or above the Nyquist frequency.

    >>> t = np.arange(200) / 100.0
    >>> x = np.sin(2 * np.pi * t)[:, None, None] * np.ones((1, 1, 3))
    >>> noisy = x + 0.01 * np.random.default_rng(0).normal(size=x.shape)
    >>> bool(np.abs(lowpass_markers(noisy, 100.0, 6.0) - x)[20:-20].max() < 0.01)
    True
    """
    if cutoff_hz is not None and not cutoff_hz >= 0:
        raise SynergyError("--smooth-hz", f"the low-pass cut-off must be 0 (off) or positive (Hz), got {cutoff_hz}")
    if not cutoff_hz or cutoff_hz >= rate / 2:
        return points
    b, a = butter(order, cutoff_hz / (rate / 2))
    pad = 3 * max(len(a), len(b))
    out = points.copy()
    valid = ~np.isnan(points[..., 0])
    for m in range(points.shape[1]):
        v = np.r_[False, valid[:, m], False].astype(np.int8)
        starts, ends = np.flatnonzero(np.diff(v) == 1), np.flatnonzero(np.diff(v) == -1)
        for s, e in zip(starts, ends):
            if e - s > pad:
                out[s:e, m] = filtfilt(b, a, points[s:e, m], axis=0)
    return out
