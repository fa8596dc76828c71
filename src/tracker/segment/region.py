"""The hand's region before the wrist cut (:func:`hand_region`): the seed surface, the depth band, the
reach, fingertip blobs."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._segment_kernels import (
    blob_labels,
    components_holding,
    edge_hits,
    near_front,
)
from . import constants as K
from .fingers import _far_end, _fingered_end, _hand_end, _has_fingers
from .layers import _in_front
from .ops import _in_labels, _largest_in_window, _points, _sq_dist, _window_max, _window_min, bounds
from .surfaces import _reaches, _touches_border, pixel_area, surface_fronts, surfaces


class Region(NamedTuple):
    """:func:`hand_region`'s result: boolean masks of the image it was given, and one flag."""

    mask: np.ndarray  #: the hand's region (before the wrist cut)
    beyond: np.ndarray  #: the hand's surface left out by the band or the reach (where an arm leaves it)
    seed: np.ndarray  #: the seed's pixels (the hand's nearest part, or its fingers' end)
    behind: np.ndarray  #: a body close behind the hand along its outline (:func:`_in_front`; empty if none)
    layered: bool  #: the region stands in front of a surface close behind it (:func:`_in_front`'s outline test)


def hand_region(depth, focal, band=0.12, jump=0.02, min_pixels=30, min_area=0.004, margin_px=25,
                blob_area=0.003, reach=0.22, points=None, border_px=None, centre=None,
                fingers_first=False, fine=None, expected=None) -> Region:
    """The hand's region before the wrist cut.

    The seed is the nearest part (within 15 mm of the front) of the nearest surface of at least
    ``min_area`` whose nearest part does not touch the image border (an object cut off by the
    border is a poorer guess than a whole one; it is taken only when nothing else is there). The
    region is that surface within ``band`` behind the front and within ``reach`` metres (3-D) of
    the seed's centre — the arm leads to the body, so the body is reached along it only beyond
    the reach of a hand — connected to the seed (when every candidate is cut off by the border,
    the seed is the end of the nearest one farthest from the border, see :func:`_far_end`), plus the small surfaces (fingertip blobs) in
    that band within ``margin_px`` pixels of it: a :class:`Region`, which also holds the pixels of the
    hand's surface left out by the band or the reach (where an arm leaves the region), the seed's pixels,
    and the pixels of a body close behind the hand along its outline (:func:`_in_front`; empty when
    there is none). ``fingers_first`` (depth only, where no skin
    test removed objects): when that whole surface has no fingers (:func:`_has_fingers`: a box or a mug
    nearer than the hand — or a fist) and a farther one's hand end has (:func:`_fingered_end`), the
    farther one is the hand; ``fine``: ``(depth, step)``, the full-resolution image ``depth`` was sampled
    from every ``step``-th pixel, where that farther surface's fingers are looked for too. ``expected``: a ``(rows, cols)`` slice pair
    where the hand is predicted, when ``depth`` is a window round it (:meth:`Segmenter.in_window`,
    whose edges count as the border): when every candidate's nearest part is cut off, the nearest
    surface that reaches into that box is taken, not the nearest of all, and a surface's end taken
    over the seed for its fingers (an arm reaching in, ``fingers_first``) must reach into it too —
    an object beside the hand that the window's edge cuts to a strip has a finger-wide end, and a
    hand and its forearm at one depth run out of the window together (the realistic SR305
    ``forearm,box`` scene, depth only: the box's strip was taken on 9 of 30 frames, each of which
    then went to the whole frame)."""
    d = np.asarray(depth, float)
    lab, n = surfaces(d, jump)
    ids, fronts = surface_fronts(lab, n, d, focal, min_pixels, min_area)
    if ids.size == 0:
        # nothing hand-sized (a hand mostly outside the image, or far away): the biggest surface
        ids, fronts = surface_fronts(lab, n, d, focal, min_pixels, 0.0)
        if ids.size:
            on = lab > 0
            area = np.bincount(lab[on], weights=pixel_area(d[on], focal), minlength=n + 1)
            j = int(np.argmax(area[ids]))
            ids, fronts = ids[j:j + 1], fronts[j:j + 1]
    if ids.size == 0:
        empty = np.zeros(d.shape, bool)
        return Region(empty, empty, empty, empty, False)
    k, front, seed = 0, np.nan, None
    cut_off = []
    # the surfaces that reach into the predicted box (every one without a box)
    there = None if expected is None else set(np.unique(lab[expected]).tolist())
    for kk, ff in zip(ids, fronts):
        with np.errstate(invalid="ignore"):
            s = _largest_in_window((lab == kk) & (d <= ff + 0.015))
        inside = not _touches_border(s, border_px)
        if seed is None or inside or (there is not None and k not in there and int(kk) in there):
            k, front, seed = int(kk), float(ff), s
            if inside:
                break
        cut_off.append(int(kk))
    X = None
    if cut_off and not _touches_border(seed, border_px):
        # an arm reaching towards the camera from outside the image, nearer than the first whole
        # surface: when its far end has fingers and lies in front of that surface (a body a few
        # centimetres behind the hand), the far end is the hand; the far edge of a table, or the
        # head of a body cut off by the border, has no fingers or lies behind the hand
        X = _points(d, focal, centre) if points is None else np.asarray(points, float)
        for kk in cut_off:
            end, end_front = _far_end(lab == kk, d, X, focal, border_px, reach)
            if end_front < front and _reaches(end, expected) and _has_fingers(lab == kk, d, end, focal, reach):
                k, front, seed = kk, end_front, end
                break
    if fingers_first and ids.size > 1 and not _touches_border(seed, border_px) and not _has_fingers(
            lab == k, d, seed, focal, reach):
        if X is None:
            X = _points(d, focal, centre) if points is None else np.asarray(points, float)
        # the few surfaces nearest after it, within reach of a hand beside an object (each test costs
        # ~1 ms: a cluttered frame has dozens of surfaces)
        others = [(kk, ff) for kk, ff in zip(ids, fronts) if kk != k and abs(ff - front) <= K.TUNING.fingers_first_m]
        for kk, ff in others[:K.TUNING.fingers_first_tries]:
            end, end_front = _fingered_end(lab == kk, d, ff, band, X, focal, border_px, reach, fine=fine)
            if end is not None and _reaches(end, expected):
                k, front, seed = int(kk), end_front, end
                break
    surface = lab == k  # the hand's surface from here on (read, never written)
    if not _touches_border(seed, border_px):
        seed, front = _hand_end(surface, d, front, band, seed, focal, border_px)
    if _touches_border(seed, border_px):
        # every candidate's nearest part is cut off by the border, typically an arm reaching
        # towards the camera from outside the image: the hand is then the end of the surface
        # farthest from where it enters the image
        X = _points(d, focal, centre) if points is None else np.asarray(points, float)
        seed, front = _far_end(surface, d, X, focal, border_px, reach)
    if points is None:
        # compiled in one pass, the points back-projected on the fly (the seed's alone for its centre)
        c3 = np.zeros(3)
        cy, cx = ((d.shape[0] - 1) / 2, (d.shape[1] - 1) / 2) if centre is None else centre
        if reach is not None:
            c3 = (X[seed] if X is not None else _seed_points(d, seed, focal, cy, cx)).mean(axis=0)
        near = near_front(d, front - band, front + band, reach is not None, float(focal), float(cy), float(cx),
                          float(c3[0]), float(c3[1]), float(c3[2]), float(reach or 0.0) ** 2)
    else:
        with np.errstate(invalid="ignore"):
            near = np.isfinite(d) & (d <= front + band) & (d >= front - band)
            if reach is not None:
                X = np.asarray(points, float)
                near &= _sq_dist(X, X[seed].mean(axis=0)) <= reach ** 2
    near |= seed
    core = surface & near
    core = components_holding(np.ascontiguousarray(core), np.ascontiguousarray(seed, dtype=np.bool_))
    # a body a few centimetres behind the hand, joined to it by the arm: the hand is the layer in front
    core, behind, seed, layered = _in_front(core, d, seed, focal, jump, min_area, surface, border_px)
    # small surfaces close to the hand in the image and in depth: fingertip blobs
    (ya, yb), (xa, xb) = bounds(core)
    y0, y1 = max(ya - margin_px, 0), min(yb + margin_px + 1, d.shape[0])
    x0, x1 = max(xa - margin_px, 0), min(xb + margin_px + 1, d.shape[1])
    win = (slice(y0, y1), slice(x0, x1))
    zone = _window_max(core[win], 2 * int(margin_px) + 1) if margin_px > 0 else core[win]
    out = core.copy()
    # compiled: the candidates (in the zone and the band, off the core and the hand's surface) that cover
    # less than blob_area (tests/tracker/test_segment_wrist.py: against _blobs_reference)
    small = blob_labels(np.ascontiguousarray(lab[win]), np.ascontiguousarray(d[win]), np.ascontiguousarray(zone),
                        np.ascontiguousarray(near[win]), np.ascontiguousarray(core[win]), int(k), int(n), float(focal),
                        float(blob_area))
    others = ids[ids != k]
    if small.size and others.size:
        small = small[~_in_labels(small, _edge_pieces(lab[win], d[win], small, others, jump))]
    if small.size:
        out[win] |= _in_labels(lab[win], small) & near[win]
    # beyond: where the hand's surface goes on past the band or the reach (the arm, not a fingertip)
    return Region(out, surface & ~out & ~behind, seed, behind, layered)


def _seed_points(d, seed, focal, cy, cx):
    """The back-projected points ``(n, 3)`` of the ``seed`` pixels of ``d`` (raster order): the rows
    ``ops._points(d, focal, (cy, cx))[seed]`` has, with its arithmetic."""
    v, u = np.nonzero(seed)
    z = d[v, u]
    out = np.empty((v.size, 3))
    out[:, 0] = (u - cx) * z / focal
    out[:, 1] = (v - cy) * z / focal
    out[:, 2] = z
    return out


def _edge_pieces(lab, d, small, others, jump, gap_px=None):
    """The labels among ``small`` that are pieces of a surface in ``others`` (hand-sized surfaces
    other than the hand's): within ``gap_px`` of it at its depth (within ``jump``), split off by a
    seam of no data, not by a depth step — an object's face the sensor's edge dropouts cut off
    (a box's side face beside the hand, at the hand's depth: the realistic SR305 1.5× ``+object``
    scene took a strip of it, 145 pixels at the half-resolution search, for a fingertip and fitted
    the hand 12 % too large). A fingertip blob is cut off from its finger or stands in front of the
    palm or the body, a depth step from any surface it borders.

    >>> lab = np.array([[1, 1, 0, 2, 0, 0, 3]])
    >>> d = np.array([[0.5, 0.5, np.nan, 0.5, np.nan, np.nan, 0.7]])
    >>> _edge_pieces(lab, d, np.array([2, 3]), np.array([1]), 0.02).tolist()
    [2]
    """
    gap_px = K.TUNING.edge_gap_px if gap_px is None else gap_px
    lab = np.ascontiguousarray(lab)
    top = int(lab.max()) + 1 if lab.size else 1
    # compiled (tests/tracker/test_segment_wrist.py: against _edge_reference, the numpy expression)
    hit = edge_hits(lab, np.ascontiguousarray(d, dtype=np.float64), _label_table(small, top),
                    _label_table(others, top), float(jump), int(gap_px))
    return np.flatnonzero(hit)


def _label_table(ids, top):
    """A boolean table over the labels below ``top``: True at ``ids`` (those below ``top``)."""
    ids = np.asarray(ids).ravel()
    table = np.zeros(top, bool)
    table[ids[(ids >= 0) & (ids < top)]] = True
    return table


def _blobs_reference(lab, d, zone, near, core, k, focal, blob_area):
    """:func:`tracker._segment_kernels.blob_labels` in numpy (``hand_region``'s window's arrays)."""
    cand = zone & near & ~core & (lab > 0) & (lab != k)
    if not cand.any():
        return np.zeros(0, np.int64)
    area = np.bincount(lab[near], weights=pixel_area(d[near], focal), minlength=lab.max() + 1)
    small = np.unique(lab[cand])
    return small[area[small] < blob_area]


def _edge_reference(lab, d, small, others, jump, gap_px):
    """:func:`_edge_pieces` in numpy (minimum and maximum filters)."""
    big = _in_labels(lab, others)
    size = 2 * int(gap_px) + 1
    with np.errstate(invalid="ignore"):
        lo = _window_min(np.where(big, d, np.inf), size)
        hi = _window_max(np.where(big, d, -np.inf), size)
        touch = _in_labels(lab, small) & (d >= lo - jump) & (d <= hi + jump)
    return np.unique(lab[touch])
