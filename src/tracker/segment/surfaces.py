"""Surfaces: pixels grouped by depth continuity (:func:`surfaces`), their fronts and areas, and the
full-resolution refinement of a coarse mask's edges (:func:`refine`)."""
from __future__ import annotations

import numpy as np

from .._segment_kernels import (
    fronts_of_surfaces,
    refine_window,
    surface_labels,
    touches_border,
)
from . import constants as K
from .ops import bounds


def refine(coarse_mask, coarse_depth, depth, step, jump=0.02):
    """``(mask, window)``: the full-resolution mask from one found on every ``step``-th pixel.

    A pixel within ``step`` pixels (square window) of the (nearest-neighbour enlarged) coarse
    mask is kept when its depth lies within ``jump`` of the depths of the masked coarse samples
    there, so the edges
    follow the sensor's data again and the background between samples stays out; ``window`` is
    the slice pair outside which the mask is empty."""
    H, W = depth.shape
    (ya, yb), (xa, xb) = bounds(coarse_mask)
    y0, y1 = max((ya - 1) * step, 0), min((yb + 2) * step, H)
    x0, x1 = max((xa - 1) * step, 0), min((xb + 2) * step, W)
    win = (slice(y0, y1), slice(x0, x1))
    # the depth range of the masked samples around each pixel (separable min / max filters), compiled
    out = np.zeros((H, W), bool)
    out[win] = refine_window(np.ascontiguousarray(coarse_mask, dtype=np.bool_),
                             np.ascontiguousarray(coarse_depth, dtype=np.float64),
                             np.ascontiguousarray(depth, dtype=np.float64), y0, y1, x0, x1, int(step), float(jump))
    return out, win


def surfaces(depth, jump=0.02):
    """``(labels, n)``: 4-connected surfaces of a depth image (NaN = no data); neighbours whose
    depths differ by more than ``jump`` lie on different surfaces.

    A pixel is cut off from a neighbour across a step by leaving the step's far side out of the
    labelling (which splits the surfaces without changing the near one); such pixels then join the
    surface of their nearest-in-depth labelled neighbour within the jump (they are the far side of a
    step, not a surface of their own). Labels are numbered as ``scipy.ndimage.label`` numbers them;
    compiled (:func:`tracker._segment_kernels.surface_labels`): it runs several times a tracked frame.

    >>> d = np.array([[0.5, 0.5, 0.6], [0.5, np.nan, 0.6]])
    >>> lab, n = surfaces(d)
    >>> lab.tolist(), n
    ([[1, 1, 2], [1, 0, 2]], 2)
    """
    return surface_labels(np.ascontiguousarray(depth, dtype=np.float64), float(jump))


def focal_from_points(points):
    """The horizontal focal length (px) of back-projected points ``(H, W, 3)``: x/z grows by
    exactly 1/fx from one column to the next; :attr:`SegmentConstants.default_focal_px` when it cannot be read."""
    if points is None:
        return K.TUNING.default_focal_px
    P = np.asarray(points, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        step = np.nanmedian(np.diff(P[..., 0] / P[..., 2], axis=1)) if P.shape[1] > 1 else np.nan
    return float(1.0 / step) if np.isfinite(step) and step > 0 else K.TUNING.default_focal_px


def pixel_area(depth, focal):
    """Area (m²) each pixel covers on a fronto-parallel surface at its depth."""
    return (np.asarray(depth, float) / float(focal)) ** 2


def surface_fronts(lab, n, depth, focal, min_pixels=30, min_area=0.004):
    """``(ids, fronts)``: the surfaces of at least ``min_pixels`` pixels and ``min_area`` m², and the
    depth of each one's nearest part (its 1st percentile, so flying pixels on its edge don't
    count), nearest first. Compiled (:func:`tracker._segment_kernels.fronts_of_surfaces`; its numpy
    definition is :func:`_surface_fronts_numpy`)."""
    if n == 0:
        return np.zeros(0, int), np.zeros(0)
    return fronts_of_surfaces(np.ascontiguousarray(lab), int(n), np.ascontiguousarray(depth, dtype=np.float64),
                              float(focal), int(min_pixels), float(min_area))


def _surface_fronts_numpy(lab, n, depth, focal, min_pixels=30, min_area=0.004):
    """:func:`surface_fronts` in numpy (the definition the compiled one is tested against)."""
    if n == 0:
        return np.zeros(0, int), np.zeros(0)
    d = np.asarray(depth, float)
    on = lab > 0
    L = lab[on]
    z = d[on]
    count = np.bincount(L, minlength=n + 1)
    area = np.bincount(L, weights=pixel_area(z, focal), minlength=n + 1)
    ok = (count >= max(int(min_pixels), 1)) & (area >= min_area)
    ok[0] = False
    ids = np.flatnonzero(ok)
    if ids.size == 0:
        return ids, np.zeros(0)
    sel = ok[L]
    Ls, zs = L[sel], z[sel]
    order = np.lexsort((zs, Ls))
    Ls, zs = Ls[order], zs[order]
    starts = np.searchsorted(Ls, ids)
    fronts = zs[starts + (0.01 * count[ids]).astype(int)]
    o = np.argsort(fronts, kind="stable")
    return ids[o], fronts[o]


def _reaches(pixels, box) -> bool:
    """Whether any of the ``pixels`` (boolean image) lies in ``box`` (a ``(rows, cols)`` slice pair;
    None: no box, always true)."""
    return box is None or bool(pixels[box].any())


def _touches_border(mask, px=None):
    px = K.TUNING.border_px if px is None else px
    if px > 0 and np.ndim(mask) == 2:
        # compiled: one call instead of four slices' any() (several times a frame)
        return bool(touches_border(np.asarray(mask, dtype=np.bool_), int(px)))
    return bool(mask[:px].any() or mask[-px:].any() or mask[:, :px].any() or mask[:, -px:].any())
