"""Fingers: whether a surface's end has fingers (:func:`_has_fingers`) and which end of an arm is its
hand (:func:`_hand_end`, :func:`_fingered_end`, :func:`_far_end`)."""
from __future__ import annotations

import numpy as np

from .._segment_kernels import (
    closed_filled,
    far_end_seed,
    fill_holes,
    finger_pieces,
    reach_part,
)
from . import constants as K
from .ops import (_dilate, _disk_opening, _edt, _in_labels, _label, _largest_in_window, _nanmedian, _nearest, _sq_dist,
                  bounds)
from .surfaces import _touches_border, pixel_area


def _fingered_end(surface, d, front, band, X, focal, border_px=None, reach=0.22, fine=None):
    """``(seed, front)`` of ``surface``'s hand end when it has fingers (:func:`_has_fingers`) and the
    surface is no bigger than :attr:`SegmentConstants.fingers_first_max_area_m2`, else ``(None, nan)``: its far end from the border when its nearest part is cut off by it
    (:func:`_far_end`), else its end with the fingers (:func:`_hand_end`); ``fine``: as for
    :func:`_has_fingers`."""
    if float(pixel_area(d[surface], focal).sum()) > K.TUNING.fingers_first_max_area_m2:
        return None, float("nan")
    with np.errstate(invalid="ignore"):
        seed = _largest_in_window(surface & (d <= front + 0.015))
    if _touches_border(seed, border_px):
        seed, front = _far_end(surface, d, X, focal, border_px, reach)
    else:
        seed, front = _hand_end(surface, d, front, band, seed, focal, border_px)
    return (seed, front) if _has_fingers(surface, d, seed, focal, reach, fine) else (None, float("nan"))


def _far_end(surface, d, X, focal, border_px=None, reach=0.22):
    """``(seed, front)`` at the end of ``surface`` farthest (in the image) from its pixels at the
    image border: the pixels within 2 cm of that end, and the nearest depth (1st percentile) of
    the surface within ``reach`` of them."""
    px = K.TUNING.border_px if border_px is None else border_px
    H, W = surface.shape
    # the distances within the surface's bounds only: the border pixels it is measured from lie there
    (ya, yb), (xa, xb) = bounds(surface)
    rows, cols = np.arange(ya, yb + 1), np.arange(xa, xb + 1)
    edge = ((rows < px) | (rows >= H - px))[:, None] | ((cols < px) | (cols >= W - px))[None, :]
    if px <= 0:
        edge = np.ones_like(edge)  # as the slices [-0:] had it
    dist = _edt(edge & surface[ya:yb + 1, xa:xb + 1])
    # compiled: the far end's piece, its centre, the depths within reach of it and their 1st percentile
    # (tests/tracker/test_segment_wrist.py: against _far_end_reference, the numpy expressions)
    seed, front = far_end_seed(np.ascontiguousarray(surface, dtype=np.bool_), dist, ya, xa,
                               np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(X, dtype=np.float64),
                               float(focal), (reach or 0.22) ** 2)
    return seed, float(front)


def _far_end_reference(surface, d, X, focal, border_px=None, reach=0.22):
    """:func:`_far_end` in numpy."""
    px = K.TUNING.border_px if border_px is None else border_px
    edge = np.zeros_like(surface)
    edge[:px], edge[-px:], edge[:, :px], edge[:, -px:] = True, True, True, True
    dist = np.full(surface.shape, -1.0)
    # the distances within the surface's bounds only: the border pixels it is measured from lie there
    (ya, yb), (xa, xb) = bounds(surface)
    win = (slice(ya, yb + 1), slice(xa, xb + 1))
    dist[win] = _edt(edge[win] & surface[win])
    dist[~surface] = -1.0
    z = _nanmedian(d[surface])
    seed = _largest_in_window(surface & (dist >= dist.max() - 0.02 * focal / z))
    centre = X[seed].mean(axis=0)
    with np.errstate(invalid="ignore"):
        around = surface & (_sq_dist(X, centre) <= (reach or 0.22) ** 2)
    return seed, float(np.percentile(d[around], 1))



def _hand_end(surface, d, front, band, seed, focal, border_px=None):
    """``(seed, front)`` at the fingers' end of an arm whose whole length is in view.

    An arm ends in view at both ends when the renderer (or a cropped depth range) gives it a free
    far end; a real forearm goes on to the elbow and the body, past the border or into ``beyond``,
    and then this changes nothing. When the seed's surface within ``band`` of the front does not
    reach the border and is longer than :attr:`SegmentConstants.arm_length_palms` palm widths (a hand with its arm,
    not a hand), the nearest part may be the arm's far end (an elbow held nearer the camera than
    the wrist). The hand is the end with the fingers: the parts narrower than
    :attr:`SegmentConstants.finger_max_m` (a morphological opening removes them), clearly more of them on one
    half along the object's long axis than on the other. That half's nearest part becomes the
    seed; otherwise (a fist, a hand seen edge-on: no finger-like parts) the seed stays."""
    with np.errstate(invalid="ignore"):
        obj = surface & (d <= front + band) & (d >= front - band)
    if not obj.any():
        return seed, front
    (ya, yb), (xa, xb) = bounds(obj)
    win = (slice(ya, yb + 1), slice(xa, xb + 1))
    lab_o, _ = _label(obj[win])
    hit = np.unique(lab_o[seed[win]])
    obj = np.zeros_like(obj)
    obj[win] = _in_labels(lab_o, hit[hit > 0])
    if not obj.any() or _touches_border(obj, border_px):
        return seed, front
    (ya, yb), (xa, xb) = bounds(obj)
    win = (slice(ya, yb + 1), slice(xa, xb + 1))
    o = closed_filled(np.ascontiguousarray(obj[win]))
    yy, xx = np.nonzero(o)
    P = np.stack([yy, xx], 1).astype(float)
    c = P.mean(axis=0)
    w, V = np.linalg.eigh(np.cov((P - c).T))
    t = (P - c) @ V[:, -1]
    palm = 2.0 * float(_edt(~np.pad(o, 1)).max())  # padded: the window is the bounds
    if t.max() - t.min() < K.TUNING.arm_length_palms * palm:
        return seed, front
    z = _nanmedian(d[win][o])
    px_m = focal / z
    lab_t, size, big = _finger_pieces(o, px_m)
    if not big.any():
        return seed, front
    thin = lab_t > 0
    tt = np.zeros(o.shape)
    tt[yy, xx] = t
    side = np.bincount(lab_t[thin], weights=tt[thin], minlength=size.size) > 0  # mean t > 0: the + half
    plus, minus = size[big & side].sum(), size[big & ~side].sum()
    if max(plus, minus) < K.TUNING.finger_min_area_m2 * px_m ** 2 * 2 or max(plus, minus) < 3 * min(plus, minus):
        return seed, front
    half = np.zeros(d.shape, bool)
    half[win] = o & ((tt > 0) if plus > minus else (tt < 0)) & obj[win]
    zh = float(np.percentile(d[half], 1))
    with np.errstate(invalid="ignore"):
        new = _largest_in_window(half & (d <= zh + 0.015))
    return (new, zh) if new.any() else (seed, front)


def _finger_pieces(o, px_m, origin=(0, 0)):
    """``(labels, sizes, big)``: the pieces of the solid mask ``o`` narrower than
    :attr:`SegmentConstants.finger_max_m` (a morphological opening with a disk that wide removes them; ``px_m``:
    pixels per metre at the mask's depth) and farther than :attr:`SegmentConstants.finger_rim_m` from what the opening
    keeps (measured: a 0.8× open hand beside a box, depth only, whose fingers the opening's rim joined
    into one U-shaped piece), their sizes (pixels, index 0 = none) and which are
    finger-sized (:attr:`SegmentConstants.finger_min_area_m2`; noise at the outline leaves slivers a few pixels big).
    ``origin``: where ``o``'s first pixel lies in the window the moments are taken in (a crop of it: the same
    moments, to the bit)."""
    T = K.TUNING
    rad = max(int(round(0.5 * T.finger_max_m * px_m)), 1)
    rim = int(round(T.finger_rim_m * px_m))
    o = np.asarray(o, bool)
    if not o.any():
        return np.zeros(o.shape, np.int32), np.array([o.size]), np.zeros(1, bool)
    # on the mask's bounding box alone (the part's circle's window is several times larger): the opening
    # and the distances are the same there (the box's outside is background, and nothing nearer lies
    # past it), the pieces numbered alike and their moments taken in the window's coordinates
    (ya, yb), (xa, xb) = bounds(o)
    crop = o[ya:yb + 1, xa:xb + 1]
    # the pixels farther than the rim from the opened shape: the opening rounds off the palm's corners
    # and leaves a sliver along its edge that joins every finger into one U-shaped piece, no finger
    opened = _disk_opening(crop, rad)
    thin = crop & ~opened
    if rim > 0 and opened.any():
        thin &= _edt(opened) > rim
    # compiled: the pieces and their moments (tests/tracker/test_segment_wrist.py: against _pieces_reference)
    lab_c, size, big = finger_pieces(np.ascontiguousarray(thin), T.finger_min_area_m2 * px_m ** 2,
                                     T.finger_elongation ** 2, T.finger_min_length_m * px_m, ya + int(origin[0]),
                                     xa + int(origin[1]))
    lab_t = np.zeros(o.shape, np.int32)
    lab_t[ya:yb + 1, xa:xb + 1] = lab_c
    size[0] = o.size - size[1:].sum()  # the window's pixels in no piece
    return lab_t, size, big


def _finger_reference(o, px_m):
    """:func:`_finger_pieces` on the whole window ``o``, its pieces by :func:`_pieces_reference` (numpy)."""
    rad = max(int(round(0.5 * K.TUNING.finger_max_m * px_m)), 1)
    rim = int(round(K.TUNING.finger_rim_m * px_m))
    opened = _disk_opening(o, rad)
    thin = o & ~opened
    if rim > 0 and opened.any():
        thin &= _edt(opened) > rim
    return _pieces_reference(thin, px_m)


def _pieces_reference(thin, px_m):
    """:func:`_finger_pieces`'s pieces of its ``thin`` pixels in numpy: ``(labels, sizes, big)``, the
    definition :func:`tracker._segment_kernels.finger_pieces` computes compiled."""
    lab_t, n = _label(thin)
    size = np.bincount(lab_t.ravel(), minlength=n + 1)
    # a finger is long and thin; clothing that the skin filter leaves in patches is not
    yy, xx = np.nonzero(thin)
    L = lab_t[yy, xx]
    cnt = np.maximum(size, 1).astype(float)
    my, mx = np.bincount(L, yy, n + 1) / cnt, np.bincount(L, xx, n + 1) / cnt
    syy = np.bincount(L, (yy - my[L]) ** 2, n + 1) / cnt
    sxx = np.bincount(L, (xx - mx[L]) ** 2, n + 1) / cnt
    sxy = np.bincount(L, (yy - my[L]) * (xx - mx[L]), n + 1) / cnt
    half_gap = np.sqrt(((syy - sxx) / 2) ** 2 + sxy ** 2)
    major, minor = (syy + sxx) / 2 + half_gap, np.maximum((syy + sxx) / 2 - half_gap, 1e-9)
    big = ((size >= K.TUNING.finger_min_area_m2 * px_m ** 2) & (major >= K.TUNING.finger_elongation ** 2 * minor)
           & (4.0 * np.sqrt(major) >= K.TUNING.finger_min_length_m * px_m))
    big[0] = False
    return lab_t, size, big


def _enough_fingers(o, px_m, origin=(0, 0)) -> bool:
    """Whether the solid mask ``o`` (``px_m`` pixels per metre; ``origin``: its first pixel in the image its
    pieces' moments are taken in, :func:`_finger_pieces`) has finger-like pieces of at least twice
    :attr:`SegmentConstants.finger_min_area_m2` in all."""
    _, size, big = _finger_pieces(o, px_m, origin)
    return bool(size[big].sum() >= 2 * K.TUNING.finger_min_area_m2 * px_m ** 2)


def _has_fingers(surface, d, seed, focal, reach=0.22, fine=None):
    """Whether the part of ``surface`` within ``reach`` metres (in the image, at the seed's depth)
    of ``seed``'s centre has finger-like parts (:func:`_finger_pieces`) of at least twice
    :attr:`SegmentConstants.finger_min_area_m2` in all. ``fine``: ``(depth, step)``, the full-resolution image ``d``
    was sampled from every ``step``-th pixel; when the part has no fingers in ``d`` they are looked for
    there too, in the part's pixels within :attr:`SegmentConstants.fine_finger_m` of the pixel they were sampled with,
    and then in the part grown by :attr:`SegmentConstants.fine_finger_grow` coarse pixels, each within that of its
    nearest part pixel (a 0.8× hand's spread fingers lie 1-2 px apart in a Kinect v1 frame's
    half-resolution image, and its noise joins them into pieces too stubby to be fingers, or breaks
    them off the hand's surface)."""
    if not seed.any():
        return False
    z = _nanmedian(d[seed])
    px_m = focal / z
    cy, cx = (float(v.mean()) for v in np.nonzero(seed))
    r = int(np.ceil((reach or 0.22) * px_m))
    H, W = surface.shape
    y0, y1, x0, x1 = max(int(cy) - r, 0), min(int(cy) + r + 1, H), max(int(cx) - r, 0), min(int(cx) + r + 1, W)
    # compiled: surface[y0:y1, x0:x1] & ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r) on np.ogrid's yy, xx, and its box
    part, ya, yb, xa, xb = reach_part(np.ascontiguousarray(surface, dtype=np.bool_), y0, y1, x0, x1, cy, cx, r)
    if ya < 0:
        return False
    # closed and filled in its box grown by a pixel (clipped to the window): the same pixels as in the whole
    # window (outside the box nothing closes, and the grown box's rim is background reaching the edge)
    ya, xa = max(ya - 1, 0), max(xa - 1, 0)
    box = part[ya:min(yb + 2, part.shape[0]), xa:min(xb + 2, part.shape[1])]
    if _enough_fingers(closed_filled(np.ascontiguousarray(box)), px_m, (ya, xa)):
        return True
    if fine is None:
        return False
    full, c = fine
    fz = np.asarray(full, float)[y0 * c:y1 * c, x0 * c:x1 * c]
    h, w = fz.shape
    zc = np.repeat(np.repeat(d[y0:y1, x0:x1], c, 0), c, 1)[:h, :w]
    for grow in dict.fromkeys((0, K.TUNING.fine_finger_grow)):
        if grow:
            # the part grown by coarse pixels, each at its nearest part pixel's depth: the sensor's
            # dropouts break a small hand's fingers into fragments the part's surface does not hold.
            # Only when the part alone has none: growing can also bridge two fingers (seed 1's frame)
            _, ny, nx = _nearest(part)
            zc = np.repeat(np.repeat(d[y0:y1, x0:x1][ny, nx], c, 0), c, 1)[:h, :w]
        up = np.repeat(np.repeat(_dilate(part, grow) if grow else part, c, 0), c, 1)[:h, :w]
        with np.errstate(invalid="ignore"):
            fpart = up & (np.abs(fz - zc) <= K.TUNING.fine_finger_m)
        # holes filled but gaps not closed: closing would join the fingers again
        if _enough_fingers(fill_holes(np.ascontiguousarray(fpart)), px_m * c):
            return True
    return False
