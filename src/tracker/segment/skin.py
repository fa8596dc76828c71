"""Skin colour: the HSV range of htrack's detector (:func:`skin_mask`), without matplotlib."""
from __future__ import annotations

import numpy as np

from .._segment_kernels import skin_channels
from . import constants as K


def skin_mask(color):
    """Pixels inside the skin HSV range (colour ``(H, W, 3)`` uint8 RGB).

    V is the largest channel and S the channel spread over it, so both bounds are tested in
    integers on the channels; the hue is computed only when its range is not the whole circle
    (htrack's is), which makes this several times faster than a full HSV conversion.

    >>> skin_mask(np.array([[[224, 172, 140], [40, 40, 40], [255, 255, 255]]], np.uint8)).tolist()
    [[True, False, False]]
    """
    c = np.asarray(color)
    (h0, s0, v0), (h1, s1, v1) = K.TUNING.skin_hsv
    if h0 > 0 or h1 < 179:
        hsv = rgb_to_hsv(c.astype(float) / 255.0)
        h, s, v = hsv[..., 0] * 179.0, hsv[..., 1] * 255.0, hsv[..., 2] * 255.0
        return (h >= h0) & (h <= h1) & (s >= s0) & (s <= s1) & (v >= v0) & (v <= v1)
    # S·255 >= s0 ⇔ (V − min)·255 >= s0 · V, in integers, compiled (twice a tracked frame)
    return skin_channels(np.ascontiguousarray(c, dtype=np.uint8), v0, v1, s0, s1)


def rgb_to_hsv(rgb):
    """HSV ``(..., 3)`` of RGB ``(..., 3)`` in [0, 1], each channel in [0, 1]: the arithmetic of
    ``matplotlib.colors.rgb_to_hsv``, step for step (the same floats), without importing matplotlib.

    >>> rgb_to_hsv(np.array([[1.0, 0.5, 0.0], [0.2, 0.2, 0.2]])).round(4).tolist()
    [[0.0833, 1.0, 1.0], [0.0, 0.0, 0.2]]
    """
    arr = np.asarray(rgb, float)
    out = np.zeros_like(arr)
    arr_max = arr.max(-1)
    delta = np.ptp(arr, -1)
    s = np.zeros_like(delta)
    ipos = arr_max > 0
    s[ipos] = delta[ipos] / arr_max[ipos]
    ipos = delta > 0
    # the later channel wins where two are the largest (red, then green, then blue), as matplotlib
    idx = (arr[..., 0] == arr_max) & ipos
    out[idx, 0] = (arr[idx, 1] - arr[idx, 2]) / delta[idx]
    idx = (arr[..., 1] == arr_max) & ipos
    out[idx, 0] = 2.0 + (arr[idx, 2] - arr[idx, 0]) / delta[idx]
    idx = (arr[..., 2] == arr_max) & ipos
    out[idx, 0] = 4.0 + (arr[idx, 0] - arr[idx, 1]) / delta[idx]
    out[..., 0] = (out[..., 0] / 6.0) % 1.0
    out[..., 1] = s
    out[..., 2] = arr_max
    return out
