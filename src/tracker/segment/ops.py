"""Image operations the segmentation is built of: labels, bounds, morphology, distance transforms,
windowed extremes, back-projection (compiled kernels where they pay)."""
from __future__ import annotations

import numpy as np

from .._silhouette_kernels import feature_transform
from .._segment_kernels import (
    back_points,
    city_block,
    component_labels,
    largest_component as _largest_component,
    mask_bounds,
    nan_median,
    nearest_target,
    window_any,
    window_extreme,
)


def in_box(points, box_min=None, box_max=None) -> np.ndarray:
    """Boolean ``(...)``: points ``(..., 3)`` inside the axis-aligned box (bounds inclusive; None, a None
    entry or ±inf = open; NaN points are outside)."""
    p = np.asarray(points, float)
    lo = np.array([-np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_min, object), 3)], float)
    hi = np.array([np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_max, object), 3)], float)
    with np.errstate(invalid="ignore"):
        return np.all((p >= lo) & (p <= hi), axis=-1)


def bounds(mask):
    """``((row_min, row_max), (col_min, col_max))`` of a non-empty boolean mask (inclusive). A window
    (the segmenter asks ~10 times a tracked frame) is scanned compiled
    (:func:`tracker._segment_kernels.mask_bounds`); a whole frame by numpy (:func:`_frame_rows`, then
    ``any`` over those rows), which reads it faster than a pixel-by-pixel scan (a 640 × 480 frame:
    ~20 µs against 123 µs; a 150 × 150 window: 14 µs against 8 µs).

    >>> m = np.zeros((300, 200), bool); m[[3, 230], [150, 1]] = True
    >>> bounds(m), bounds(m[:100, :100] | True)
    (((3, 230), (1, 150)), ((0, 99), (0, 99)))
    """
    m = np.asarray(mask)
    m = m if m.dtype == np.bool_ else m.astype(bool)
    if m.size > BOUNDS_SCAN_MAX_PIXELS:
        rows = _frame_rows(m)
        if rows is None:
            raise ValueError("bounds of an empty mask")
        cols = np.flatnonzero(m[rows[0]:rows[1] + 1].any(axis=0))  # the columns over those rows only
        return rows, (int(cols[0]), int(cols[-1]))
    r0, r1, c0, c1 = mask_bounds(m)
    if r0 < 0:
        raise ValueError("bounds of an empty mask")
    return (int(r0), int(r1)), (int(c0), int(c1))


def _frame_rows(mask):
    """``(first, last)`` row of a 2-D bool ``mask`` holding a pixel, or None when it holds none: numpy's
    ``argmax`` stops at the first set pixel (~1 µs where ``any(axis=1)`` reads a VGA frame in ~20)."""
    flat = mask.reshape(-1)
    first = int(flat.argmax())
    if not flat[first]:
        return None
    first //= mask.shape[1]
    hi = mask.shape[0]
    # the last row from the bottom up, in blocks of rows (a reversed view would be copied)
    while True:
        lo = max(hi - 32, first)
        block = mask[lo:hi].reshape(-1)
        if block[block.argmax()]:
            return first, lo + int(np.flatnonzero(mask[lo:hi].any(1))[-1])
        hi = lo


# above this many pixels bounds() uses numpy's any (see there)
BOUNDS_SCAN_MAX_PIXELS = 40_000


def _label(mask, eight=False):
    """``scipy.ndimage.label(mask)``, or with ``structure=np.ones((3, 3))`` when ``eight``: ``(labels,
    n)``, the same numbering, compiled (:func:`tracker._segment_kernels.component_labels`; scipy's
    costs ~0.1 ms of call overhead on a hand's window, several times a tracked frame)."""
    return component_labels(np.ascontiguousarray(mask, dtype=np.bool_), bool(eight))


def _nanmedian(values) -> float:
    """``float(np.nanmedian(values))`` (the same value; NaN, without numpy's warning, when every value
    is NaN), compiled: numpy's takes ~50 µs on the few hundred depths the segmenter asks it for."""
    return float(nan_median(np.ravel(np.asarray(values, dtype=np.float64))))


def largest_component(mask):
    """The largest 4-connected component of a boolean mask (the first in raster order on ties;
    compiled: :func:`tracker._segment_kernels.largest_component`)."""
    return _largest_component(np.ascontiguousarray(mask, dtype=np.bool_))


# compiled morphology of the segmenter's small windows (scipy's calls cost mostly their overhead
# there; every tracked frame runs dozens): each equals the scipy call named in its docstring
# (tests/tracker/test_segment_real.py compares them)
def _dilate(mask, k):
    """``scipy.ndimage.binary_dilation(mask, iterations=k)`` (its cross)."""
    return city_block(np.ascontiguousarray(mask, dtype=np.bool_)) <= k


def _edt(targets):
    """``scipy.ndimage.distance_transform_edt(~targets)``: each pixel's distance to the nearest target."""
    t = np.ascontiguousarray(targets, dtype=np.bool_)
    dist = np.empty(t.shape)
    if not feature_transform(t, dist, np.empty(t.shape, np.int32), np.empty(t.shape, np.int32)):
        from scipy import ndimage  # the compiled transform's fallback only (scipy.ndimage: ~0.06 s to import)

        return ndimage.distance_transform_edt(~t)
    return dist


def _disk_opening(mask, rad):
    """``scipy.ndimage.binary_opening(mask, structure=disk)`` with the disk of offsets ``hypot ≤ rad`` (the
    outside counting as background, as scipy's has it), by two distance transforms: an erosion keeps the
    pixels farther than ``rad`` from the background, a dilation the pixels within ``rad`` of those. The
    same pixels; at a full-resolution image's finger widths (``rad`` ~11) ~10× faster than scipy's.

    >>> from scipy import ndimage
    >>> m = np.zeros((9, 12), bool); m[1:8, 1:8] = True; m[3:5, 8:11] = True  # a square and a thin stub
    >>> bool((_disk_opening(m, 2) == ndimage.binary_opening(m, structure=np.hypot(*np.mgrid[-2:3, -2:3]) <= 2)).all())
    True
    """
    m = np.asarray(mask, bool)
    p = int(rad) + 1
    padded = np.pad(m, p)
    eroded = _edt(~padded) > rad
    if not eroded.any():
        return np.zeros(m.shape, bool)
    return (_edt(eroded) <= rad)[p:-p, p:-p]


def _disk_closing(mask, rad):
    """``mask`` closed with the disk of offsets ``hypot ≤ rad``, by two distance transforms as
    :func:`_disk_opening` (a dilation into a margin of ``rad`` + 1 pixels, then an erosion): notches
    narrower than the disk are filled, the outline elsewhere kept.

    >>> m = np.zeros((7, 9), bool); m[1:6, 1:4] = True; m[1:6, 5:8] = True; m[4:6, 1:8] = True  # a U
    >>> _disk_closing(m, 1.5)[2].astype(int).tolist()  # the notch between its arms is filled
    [0, 1, 1, 1, 1, 1, 1, 1, 0]
    """
    p = int(np.ceil(rad)) + 1
    grown = _edt(np.pad(np.asarray(mask, bool), p)) <= rad
    return (_edt(~grown) > rad)[p:-p, p:-p]


def _nearest(targets):
    """``(dist, rows, cols)``: ``scipy.ndimage.distance_transform_edt(~targets, return_indices=True)``,
    the nearest target of every pixel as scipy names it on ties."""
    t = np.ascontiguousarray(targets, dtype=np.bool_)
    dist, iv, iu = np.empty(t.shape), np.empty(t.shape, np.int32), np.empty(t.shape, np.int32)
    if not nearest_target(t, dist, iv, iu):
        from scipy import ndimage  # the compiled transform's fallback only

        dist, (iv, iu) = ndimage.distance_transform_edt(~t, return_indices=True)
    return dist, iv, iu


def _window_max(a, size):
    """``scipy.ndimage.maximum_filter(a, size)`` for an odd ``size``, an array without NaN and a border
    mode that cannot win (``reflect``, ``nearest``, ``constant`` at −inf or 0 for masks); boolean in,
    boolean out."""
    a = np.asarray(a)
    if a.dtype == np.bool_:
        return window_any(np.ascontiguousarray(a), (int(size) - 1) // 2)
    return window_extreme(np.ascontiguousarray(a, dtype=np.float64), (int(size) - 1) // 2, 1.0)


def _window_min(a, size):
    """``scipy.ndimage.minimum_filter(a, size, mode="constant", cval=np.inf)`` (odd ``size``, no NaN)."""
    return window_extreme(np.ascontiguousarray(a, dtype=np.float64), (int(size) - 1) // 2, -1.0)


def _uniform1d(x, size):
    """``scipy.ndimage.uniform_filter1d(x, size, mode="nearest")`` of a 1-D array, to the bit, without
    loading ``scipy.ndimage`` (~0.05 s of a tracking command's start-up; the wrist profile calls it on
    every cut frame): scipy's running sum — the first window summed in order, then each step adds its
    entering minus its leaving value, in sequence (``np.cumsum``) — divided by ``size`` at each output."""
    x = np.asarray(x, dtype=np.float64)
    before = int(size) // 2
    ext = np.concatenate([np.full(before, x[0]), x, np.full(int(size) - before - 1, x[-1])])
    steps = np.empty(len(x))
    steps[0] = np.add.accumulate(ext[:size])[-1]
    steps[1:] = ext[size:] - ext[:-size]
    return np.cumsum(steps) / size


def _in_labels(lab, ids):
    """``np.isin(lab, ids)`` for non-negative integer labels (an image of them, or a list): by a table
    of the labels up to the largest (``np.isin`` sorts both, ~50 µs of overhead a call; the segmenter
    asks it several times a frame)."""
    lab = np.asarray(lab)
    ids = np.asarray(ids).ravel()
    if lab.size == 0 or ids.size == 0:
        return np.zeros(lab.shape, bool)
    table = np.zeros(max(int(lab.max()), int(ids.max())) + 1, bool)
    table[ids[ids >= 0]] = True
    return table[lab]


def _largest_in_window(mask):
    """:func:`largest_component`, labelling only the mask's bounding box."""
    out = np.zeros_like(mask)
    if mask.any():
        (y0, y1), (x0, x1) = bounds(mask)
        win = (slice(y0, y1 + 1), slice(x0, x1 + 1))
        out[win] = largest_component(mask[win])
    return out


def _sq_dist(X, c):
    """Squared distances of points ``(..., 3)`` to ``c``, component by component (numpy's
    reduction over a last axis of 3 is several times slower; the sum's order is the same)."""
    return (X[..., 0] - c[0]) ** 2 + (X[..., 1] - c[1]) ** 2 + (X[..., 2] - c[2]) ** 2


def _points(depth, focal, centre=None):
    """Back-projection with the principal point ``centre`` (row, col; None: the image centre) when
    no points are given."""
    H, W = depth.shape
    cy, cx = ((H - 1) / 2, (W - 1) / 2) if centre is None else centre
    # compiled: np.stack([(u - cx) * depth / focal, (v - cy) * depth / focal, depth], -1) on np.mgrid's u, v
    return back_points(np.ascontiguousarray(depth, dtype=np.float64), float(focal), float(cy), float(cx))
