"""Point clouds from depth images: back-projection with stride sampling, masks and crops.

Points are in the camera frame: x right, y down, z forward (metres); pixel ``(row, col)`` =
``(v, u)`` has its centre at integer coordinates, ``x = (u − cx)/fx · z``, ``y = (v − cy)/fy · z``.
Everything is vectorised numpy.

"Stride K" keeps every K-th pixel in x and in y, starting at pixel (0, 0): ``ceil(H/K)·ceil(W/K)``
pixels, about 1/K² of the image (the original code's "1/3 sampling" is K = 3, i.e. 1/9 of the pixels).

Examples
--------
>>> import numpy as np
>>> from tracker.cameras import Camera
>>> cam = Camera(4, 3, 2.0, 2.0, 1.5, 1.0)
>>> pts, pix = backproject(np.full((3, 4), 2.0), cam, stride=2)
>>> pts.shape, pix.tolist()
((4, 3), [[0, 0], [0, 2], [2, 0], [2, 2]])
>>> kept_fraction((3, 4), 2)
0.3333333333333333
"""
from __future__ import annotations

import math

import numpy as np


def _check_stride(stride) -> int:
    if isinstance(stride, bool) or int(stride) != stride or stride < 1:
        raise ValueError(f"stride must be a positive integer, got {stride!r}")
    return int(stride)


def stride_mask(shape, stride: int) -> np.ndarray:
    """Boolean image ``shape`` that is True on every ``stride``-th pixel in x and y."""
    stride = _check_stride(stride)
    m = np.zeros(shape, bool)
    m[::stride, ::stride] = True
    return m


def kept_fraction(shape, stride: int) -> float:
    """Exact fraction of an image's pixels a stride keeps: ``ceil(H/K)·ceil(W/K) / (H·W)`` (≈ 1/K²)."""
    stride = _check_stride(stride)
    H, W = shape
    return math.ceil(H / stride) * math.ceil(W / stride) / (H * W)


def stride_for_density(fraction: float) -> int:
    """Largest stride K whose nominal density 1/K² is still at least ``fraction`` (0 < fraction ≤ 1).

    >>> stride_for_density(1 / 9), stride_for_density(0.1), stride_for_density(1.0)
    (3, 3, 1)
    """
    f = float(fraction)
    if not 0 < f <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction!r}")
    # the tolerance keeps exact densities exact (1/sqrt(1/9) is 2.9999999999999996)
    return max(int(math.floor(1.0 / math.sqrt(f) + 1e-9)), 1)


def backproject(depth, camera, stride: int = 1, mask=None, dtype=np.float64):
    """Back-project the valid pixels of a depth image.

    Parameters
    ----------
    depth : (H, W) array
        Metres; NaN, inf and values ≤ 0 mean no data.
    camera : Camera
        Pinhole intrinsics (``fx fy cx cy width height``).
    stride : int
        Keep every ``stride``-th pixel in x and y.
    mask : (H, W) bool array, optional
        Pixels to consider (e.g. a hand segmentation).
    dtype : float32 or float64

    Returns
    -------
    points : (N, 3) array of ``dtype``
        Camera-frame points in metres, in row-major pixel order.
    pixels : (N, 2) int64 array
        ``(row, col)`` of each point, so ``depth[pixels[:, 0], pixels[:, 1]]`` is its z.
    """
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f"depth must be an (H, W) image, got shape {d.shape}")
    if d.shape != (camera.height, camera.width):
        raise ValueError(f"depth shape {d.shape} does not match the camera's {(camera.height, camera.width)}")
    stride = _check_stride(stride)
    dtype = np.dtype(dtype).type
    sub = d[::stride, ::stride].astype(dtype, copy=False)
    with np.errstate(invalid="ignore"):
        keep = np.isfinite(sub) & (sub > 0)
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != d.shape:
            raise ValueError(f"mask shape {m.shape} does not match depth {d.shape}")
        keep &= m[::stride, ::stride]
    r, c = np.nonzero(keep)
    rows, cols = r * stride, c * stride
    z = sub[r, c]
    pts = np.empty((len(z), 3), dtype)
    pts[:, 0] = (cols.astype(dtype) - dtype(camera.cx)) / dtype(camera.fx) * z
    pts[:, 1] = (rows.astype(dtype) - dtype(camera.cy)) / dtype(camera.fy) * z
    pts[:, 2] = z
    return pts, np.stack([rows, cols], 1).astype(np.int64)


def depth_range(depth, near=None, far=None) -> np.ndarray:
    """Copy of ``depth`` with NaN outside ``[near, far]`` metres (None = open end)."""
    d = np.array(depth, dtype=np.result_type(np.asarray(depth).dtype, np.float32))
    with np.errstate(invalid="ignore"):
        if near is not None:
            d[d < near] = np.nan
        if far is not None:
            d[d > far] = np.nan
    return d


def in_box(points, box_min, box_max) -> np.ndarray:
    """Boolean ``(N,)``: points inside the axis-aligned box (bounds inclusive; None or ±inf = open)."""
    p = np.asarray(points, float)
    lo = np.array([-np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_min, object), 3)], float)
    hi = np.array([np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_max, object), 3)], float)
    with np.errstate(invalid="ignore"):
        return np.all((p >= lo) & (p <= hi), axis=-1)


def crop(points, box_min, box_max, *others):
    """Points inside an axis-aligned box (see :func:`in_box`).

    Arrays in ``others`` (e.g. the pixel indices from :func:`backproject`) are cut the same way;
    then a tuple ``(points, *others)`` is returned.
    """
    keep = in_box(points, box_min, box_max)
    p = np.asarray(points)[keep]
    if not others:
        return p
    return (p, *(np.asarray(o)[keep] for o in others))


def crop_depth(points, near=None, far=None, *others):
    """Points with ``near ≤ z ≤ far`` (a box open in x and y); ``others`` as in :func:`crop`."""
    return crop(points, (None, None, near), (None, None, far), *others)
