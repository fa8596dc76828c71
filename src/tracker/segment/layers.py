"""Layers: a body close behind the hand (:func:`_in_front`) and the surfaces the hand's region meets at
its depth (:func:`_joins`)."""
from __future__ import annotations

import numpy as np

from .._segment_kernels import (
    closed_filled,
    front_layer,
    join_surfaces,
    label_extents,
    touch_close,
)
from . import constants as K
from .fingers import _hand_end
from .ops import _disk_opening, _label, _nanmedian, _nearest, _window_max, _window_min, bounds
from .surfaces import pixel_area, surfaces


def _in_front(region, d, seed, focal, jump=0.02, min_area=0.004, surface=None, border_px=None):
    """``(region, behind, seed, layered)``: the layer of ``region`` in front of a surface it stands out of.

    Each pixel's local background is the grey closing of the region's depth (the farthest depth
    within :attr:`SegmentConstants.front_window_m`, then the nearest of those; no data ignored): a tilted body keeps
    its own depth, a hand or an arm narrower than the window takes the depth of the body around it.
    The pixels nearer than their background by more than :attr:`SegmentConstants.front_step_m` fall into pieces
    (neighbours closer than ``jump``); the largest, when it covers ``min_area`` (m²), is the layer in
    front (the seed may lie on flying pixels at the body's edge, which curves away). It replaces the region when the region's pixels
    next to it lie behind it by that step over at least :attr:`SegmentConstants.front_outline_share` of its outline and
    the region behind it covers at least :attr:`SegmentConstants.front_behind_area_m2` — a hand held in front of the
    body, which the arm joins to the hand's surface. A hand alone, with its arm or on its own, has no
    such layer (its outline borders no data, another surface or its own pixels at its own depth) and
    keeps its region, ``behind`` empty and ``seed`` unchanged. ``behind``: the surface's pixels outside
    the layer (the body, past the region's reach too) except where the hand's surface goes on
    (:func:`_goes_on`: an arm receding into the body meets it without a step across its width; a finger
    leaning back to within the step of the body does not go on, nor does a part beside it); ``seed``:
    the layer's part of the seed, or its nearest 15 mm, moved to the fingers' end when the layer is the
    hand with its whole forearm (:func:`_hand_end`, ``border_px`` as there; the arm then goes on at its
    other end). ``layered``: whether the region stands in front of a surface over enough of its outline,
    whether or not that surface was big enough to be a body."""
    none = np.zeros(region.shape, bool)
    if not (region & seed).any():
        return region, none, seed, False
    (ya, yb), (xa, xb) = bounds(region)
    z = _nanmedian(d[seed])
    half = max(int(round(K.TUNING.front_window_m * focal / z)), 1)
    H, W = d.shape
    # the background is read from the whole surface around the region (the reach cuts the body off
    # beside a big hand's palm), the layer sought in the region only
    big = (slice(max(ya - half, 0), min(yb + half + 1, H)), slice(max(xa - half, 0), min(xb + half + 1, W)))
    back = region[big] if surface is None else (surface | region)[big]
    win = (slice(max(ya - 3, 0), min(yb + 4, H)), slice(max(xa - 3, 0), min(xb + 4, W)))
    T = K.TUNING
    # compiled (tests/tracker/test_segment_wrist.py: against _front_reference, the numpy expressions); the
    # kernel reads the background within the box only (half >= 3: 8 cm at any depth of the working range)
    if all(b.start <= w.start and w.stop <= b.stop for b, w in zip(big, win)):
        status, layer, ring, step = front_layer(
            np.ascontiguousarray(d, dtype=np.float64), np.ascontiguousarray(back), np.ascontiguousarray(region),
            big[0].start, big[0].stop, big[1].start, big[1].stop, win[0].start, win[0].stop, win[1].start,
            win[1].stop, half, float(T.front_step_m), float(jump), float(focal), float(min_area),
            float(T.front_outline_share), float(T.front_behind_area_m2))
    else:
        status, layer, ring, step = _front_reference(region, d, back, big, win, half, jump, focal, min_area)
    if status < 3:
        # no hand-sized layer (a thumb or knuckles nearer than the rest of the hand are no hand), or one
        # that does not stand out over enough of its outline, or too little of the region behind it
        return region, none, seed, status == 2
    dw = d[win]
    rw = region[win]
    out, goes_on = none.copy(), none.copy()
    out[win] = layer
    goes_on[win] = _goes_on(layer, rw & ring & ~step, dw, focal)
    # everywhere else the surface is the body behind the layer, past the region's reach too: a finger
    # leaning back to within the step of it, or the body beside the fingertips, is no arm going on
    behind = (region if surface is None else surface | region) & ~out & ~goes_on
    new_seed = seed & out
    if not new_seed.any():
        with np.errstate(invalid="ignore"):
            new_seed = out & (d <= float(np.percentile(d[out], 1)) + 0.015)
    # the layer may be the hand with its whole forearm, free-ended in front of the body (a turning hand
    # held out): the seed is then its fingers' end, not the forearm's end nearer the camera, and the arm
    # goes on at its other end (to the elbow and the body, whether or not a step shows there)
    fingers, _ = _hand_end(out, d, float(np.nanmin(d[out])), np.inf, new_seed, focal, border_px)
    if not np.array_equal(fingers, new_seed):
        new_seed = fingers
        yy, xx = np.nonzero(layer)
        cy, cx = (float(v.mean()) + s.start for v, s in zip(np.nonzero(fingers[win]), win))
        dist = np.hypot(yy + win[0].start - cy, xx + win[1].start - cx)
        end = np.zeros(layer.shape, bool)
        end[yy, xx] = dist >= dist.max() - 0.03 * focal / _nanmedian(dw[layer])
        arm_end = none.copy()
        arm_end[win] = rw & ring & _window_max(end, 7)
        behind &= ~arm_end
    return out, behind, new_seed, True


def _goes_on(layer, contact, d, focal):
    """The pixels of ``contact`` (the region's pixels next to ``layer`` without a depth step) where the
    hand's surface goes on past the layer: beside the layer's wide part (an opening with a disk
    :attr:`SegmentConstants.finger_max_m` across removes the fingers), in pieces spanning more than that (an arm receding
    into the body meets it across its width; a finger leaning back, lying along the palm or the thumb,
    meets it over a finger's width or along its length beside the wide part in a thin band)."""
    o = closed_filled(layer)
    px_m = focal / _nanmedian(d[layer])
    rad = max(int(round(0.5 * K.TUNING.finger_max_m * px_m)), 1)
    wide = _disk_opening(o, rad)
    out = contact & _window_max(wide, 7)
    lab, n = _label(out, eight=True)
    if n == 0:
        return out
    # each piece's bounding box diagonal (scipy.ndimage.find_objects' slices, compiled)
    rows, cols = label_extents(lab, n)
    span = np.concatenate([[0.0], np.hypot(rows, cols)])
    return (span >= K.TUNING.finger_max_m * px_m)[lab] & out


def _joins(region, d, surface, depth_all, focal, px=None, dz=None, min_area=None, jump=0.02):
    """Pixels where another object meets ``region`` at its own depth: pixels of ``depth_all`` (the
    frame before the skin filter; NaN = no data) off the hand's ``surface``, within ``px`` pixels of
    the region and within ``dz`` metres of its nearest pixel's depth, whose surface (depth
    continuity, in a window :attr:`SegmentConstants.touch_window_m` around the region) covers at least ``min_area``
    m² — a table or the body, not the shading specks at the hand's outline that fail the skin test
    or the hand's own fingertip blobs."""
    px = K.TUNING.touch_px if px is None else px
    dz = K.TUNING.touch_m if dz is None else dz
    min_area = K.TUNING.touch_area_m2 if min_area is None else min_area
    out = np.zeros(region.shape, bool)
    if not region.any():
        return out
    (ya, yb), (xa, xb) = bounds(region)
    H, W = region.shape
    z = _nanmedian(d[region])
    m = px + int(np.ceil(K.TUNING.touch_window_m * focal / z))
    win = (slice(max(ya - m, 0), min(yb + m + 1, H)), slice(max(xa - m, 0), min(xb + m + 1, W)))
    da = np.asarray(depth_all, float)[win]
    # the pixels within px of the region and their nearest region pixels lie in its box grown by px: the
    # transform there gives them as over the whole window (the same targets in each column and each row;
    # tests/tracker/test_segment_wrist.py), at a fraction of the pixels
    p = int(np.ceil(px))
    near = (slice(max(ya - p, 0), min(yb + p + 1, H)), slice(max(xa - p, 0), min(xb + p + 1, W)))
    dist, iy, ix = _nearest(region[near])
    # compiled: np.abs(da - d[win][iy, ix]) <= dz within px, without the gather over the whole window
    close = np.zeros(da.shape, bool)
    close[near[0].start - win[0].start:near[0].stop - win[0].start,
          near[1].start - win[1].start:near[1].stop - win[1].start] = touch_close(
        dist, iy, ix, np.asarray(depth_all, float)[near], np.asarray(d, float)[near], float(px), float(dz))
    if not close.any():
        return out
    # compiled (tests/tracker/test_segment_wrist.py: against _join_reference, the numpy expressions)
    out[win] = join_surfaces(np.ascontiguousarray(da), np.ascontiguousarray(surface[win], dtype=np.bool_), close,
                             float(jump), float(focal), float(min_area))
    return out


def _join_reference(da, surface, close, jump, focal, min_area):
    """:func:`tracker._segment_kernels.join_surfaces` in numpy (``_joins``' window's arrays)."""
    other = np.where(np.isfinite(da) & ~surface, da, np.nan)
    lab, n = surfaces(other, jump)
    if n == 0:
        return np.zeros(da.shape, bool)
    on = lab > 0
    big = np.bincount(lab[on], weights=pixel_area(other[on], focal), minlength=n + 1) >= min_area
    big[0] = False
    return close & big[lab]


def _front_reference(region, d, back, big, win, half, jump, focal, min_area):
    """:func:`tracker._segment_kernels.front_layer` in numpy: ``(status, layer, ring, step)``."""
    size = 2 * half + 1
    with np.errstate(invalid="ignore"):
        far = _window_max(np.where(back, d[big], -np.inf), size)
        far = _window_min(np.where(np.isfinite(far), far, np.inf), size)
    far = far[win[0].start - big[0].start:win[0].stop - big[0].start, win[1].start - big[1].start:win[1].stop - big[1].start]
    dw = d[win]
    rw = region[win]
    none = np.zeros(dw.shape, bool)
    with np.errstate(invalid="ignore"):
        front = rw & (dw < far - K.TUNING.front_step_m)
    if not front.any():
        return 0, none, none, none
    lab, n = surfaces(np.where(front, dw, np.nan), jump)
    if n == 0:
        return 0, none, none, none
    area = np.bincount(lab[lab > 0], weights=pixel_area(dw[lab > 0], focal), minlength=n + 1)
    area[0] = 0.0
    best = int(np.argmax(area))
    if area[best] < min_area:
        return 0, none, none, none
    layer = lab == best
    # the outline: pixels within 3 px of the layer, and how far behind its farthest pixel there each lies
    layer_far = _window_max(np.where(layer, dw, -np.inf), 7)
    ring = np.isfinite(layer_far) & ~layer & np.isfinite(dw)
    with np.errstate(invalid="ignore"):
        step = rw & ring & (dw - layer_far > K.TUNING.front_step_m)
    if not step.sum() >= K.TUNING.front_outline_share * ring.sum():
        return 1, layer, ring, step
    if pixel_area(dw[rw & ~layer], focal).sum() < K.TUNING.front_behind_area_m2:
        return 2, layer, ring, step
    return 3, layer, ring, step
