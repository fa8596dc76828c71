"""The wrist cut (:func:`cut_forearm`): the palm, the forearm leaving it, the cut across it where the
width stops narrowing."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._segment_kernels import (
    closed_filled,
    disk_counts,
    filled_places,
    label_max,
    palm_place,
    wrist_cut,
)
from . import constants as K
from .ops import _dilate, _disk_closing, _edt, _in_labels, _label, _nanmedian, _uniform1d, bounds


def _widest_piece(owner, piece_size, j, r):
    """The label (on :func:`cut_forearm`'s ring around the palm) of part ``j``'s widest piece there,
    among its pieces of at least 0.05 r² (``owner``: each ring piece's part; ``piece_size``: its
    pixels), or None when it has fewer than two."""
    mine = np.flatnonzero((owner == j + 1) & (piece_size >= 0.05 * r * r))
    return None if mine.size < 2 else int(mine[np.argmax(piece_size[mine])])


def _opposite_fingers(py, px, width, cy_p, cx_p, fingers, r) -> bool:
    """Whether the direction ``(py, px)`` from the palm's centre lies opposite (cos < −0.5) the parts
    ``fingers`` of :func:`cut_forearm`, weighted by their ``width`` (``cy_p``/``cx_p``: each part's mean
    offset where it leaves the palm circle); False when they are less than 0.3 ``r`` wide in all
    (noise specks at the outline are no fingers)."""
    if width[fingers].sum() < 0.3 * r:
        return False
    fy, fx = np.sum(width[fingers] * cy_p[fingers]), np.sum(width[fingers] * cx_p[fingers])
    return (py * fy + px * fx) / (np.hypot(py, px) * np.hypot(fy, fx) + 1e-12) < -0.5


def _arm_a_finger_touches(j, ring_lab, owner, piece_size, vy, vx, r, m_px, width, cy_p, cx_p, fingers) -> bool:
    """Whether part ``j`` of :func:`cut_forearm`, which crosses the ring around the palm in several
    pieces and goes on past the region, is an arm that a finger (the thumb) touches outside the palm
    circle rather than spread fingers: its widest piece on the ring (:func:`_widest_piece`) is wider
    than a finger (:attr:`SegmentConstants.finger_max_m`; ``m_px``: metres per pixel) and lies opposite the parts
    ``fingers`` that end in the region (:func:`_opposite_fingers`)."""
    k = _widest_piece(owner, piece_size, j, r)
    # the ring is 0.4 r thick: a piece's area over that is its chord across the ring
    if k is None or piece_size[k] / (0.4 * r) * m_px <= K.TUNING.finger_max_m:
        return False
    on_k = ring_lab == k
    return _opposite_fingers(vy[on_k].mean(), vx[on_k].mean(), width, cy_p, cx_p, fingers, r)


class _Parts(NamedTuple):
    """The parts of :func:`cut_forearm`'s region outside the palm circle (1.6 r), 8-connected, with what the
    rules read of them (index ``j`` is part ``j + 1`` of ``lab``)."""

    lab: np.ndarray  # the parts' labels in the crop
    n: int  # how many
    width: np.ndarray  # each part's width where it leaves the palm (its chord across a ring 0.3 r wide)
    cy_p: np.ndarray  # each part's mean offset from the palm's centre where it leaves it, rows …
    cx_p: np.ndarray  # … and columns
    reach_r: np.ndarray  # how far each part reaches from the palm's centre (px)
    ring_lab: np.ndarray  # the pieces of the parts on a ring 2.0-2.4 r around the palm
    piece_size: np.ndarray  # each ring piece's pixels
    owner: np.ndarray  # each ring piece's part
    pieces: np.ndarray  # how many big pieces (>= 0.05 r²) each part has on the ring


def cut_forearm(mask, depth, focal, beyond=None, palm_radius_m=(0.02, 0.07), wrist_range=(0.9, 2.6), seed=None,
                joins=None, prefer=None):
    """The hand mask without the forearm beyond the wrist.

    The palm is the largest inscribed circle of the region (centre c, radius r) — among circles
    nearly as large that the mask before closing fills nearly as well as the best-filled one
    (:func:`_filled_places`), the one farthest from where the region goes on. Where the region reaches
    farther past that circle than fingers can (:attr:`SegmentConstants.arm_reach_r` r to its far end
    from where it goes on), the circle is on the arm and the hand is at that far end: the palm is then the
    largest circle from which the far end is within fingers' reach, when it is at least
    :attr:`SegmentConstants.hand_end_width_share` as wide as the largest (a fist seen from its thumb side
    is narrower than the forearm, and every circle nearly as large was on the arm; the fingers of a hand
    seen edge-on are far narrower, and the first circle stays) (:func:`_hand_end_palm`). Such a palm
    (a side fist) may be as thin as :attr:`SegmentConstants.side_fist_radius_m`, and its wrist ends the
    hand's heel, the narrowest stretch beyond it (:func:`_heel_end`) — the rules below would cut at
    the fist's edge. Outside 1.6 r, the
    parts that leave the circle are fingers or the forearm; the forearm is at least 0.45 r wide
    and goes on past the region — it reaches the image border or ``beyond`` (pixels of the same
    surface left out of the region), where fingers end in an edge (fingers held together are as
    wide as an arm). The widest such part is the forearm, its direction from c the arm axis a — or
    its own direction, from where it leaves the circle to its far end, when that is more than
    :attr:`SegmentConstants.arm_bend_deg` off (a wrist bent sideways puts c off the arm's axis). The
    region's width across a, measured at each distance t along a within ``wrist_range`` · r, is
    smallest at the wrist: the cut goes where it stops narrowing — where a slow taper ends when it
    narrows only slowly (over at least :attr:`SegmentConstants.taper_min_samples` samples), and at least
    :attr:`SegmentConstants.no_narrowing_wrist` r out then — and everything beyond it
    in a strip of ±2.5 r around the axis is removed.
    Nothing is cut when the circle is not palm-sized (``palm_radius_m``) or no forearm leaves it.
    ``joins``: pixels where another object meets the region at its depth (:func:`_joins`); a part
    they touch goes on too (an arm entering a table the sensor's shadow separates from it); where
    nothing goes on past the region, a contact about a palm wide (the table where the skin test ends
    the arm) keeps the palm away from it as the arm's side would, a finger-wide one does not move the
    palm (fingertips touch the body as well). ``prefer``: a ``(rows, cols)`` slice
    pair where the hand is expected (the tracker's prediction): palm places inside it come first."""
    m = np.asarray(mask, bool)
    crop = _crop(m)
    y0, y1, x0, x1 = crop
    sub = m[y0:y1, x0:x1]
    # close one-pixel no-data cracks and fill the holes the sensor leaves inside the hand (Kinect v1:
    # dropouts and shadows inside a fist) so that neither splits nor shrinks the palm circle: a
    # circle shrunk by a hole makes every finger reach "farther than a finger can" (an arm)
    solid = closed_filled(np.ascontiguousarray(sub))
    dt = _edt(~solid)
    go_on = _going_on(beyond, solid, dt, crop, m.shape)
    touch = None if joins is None else _dilate(np.asarray(joins, bool)[y0:y1, x0:x1], 2) & solid
    cy, cx, at_end = _palm_centre(sub, dt, solid, go_on, touch, crop, m.shape, seed, prefer)
    r = float(dt[cy, cx])
    zc = _palm_depth(depth, m, crop, cy, cx)
    r_m = r * zc / focal
    least = min(palm_radius_m[0], K.TUNING.side_fist_radius_m) if at_end else palm_radius_m[0]
    if not (least <= r_m <= palm_radius_m[1]):
        return m
    # compiled from here on: the parts leaving the palm, which go on, the arm's axis, the wrist along it
    # (the rules of _parts, _going_on_parts, _arm_axis, _wrist_distance and _heel_end, to the bit:
    # _cut_reference is them in numpy, tests/tracker/test_segment_wrist.py compares the two)
    T = K.TUNING
    made, cut = wrist_cut(solid, int(cy), int(cx), r, go_on, _NO_TOUCH if touch is None else touch, touch is not None,
                          float(zc / focal), bool(at_end), float(wrist_range[0]), float(wrist_range[1]),
                          float(T.arm_reach_r), float(T.opposite_arm_reach_r), float(T.sure_arm_reach_r),
                          float(T.finger_max_m), float(np.cos(np.radians(T.arm_bend_deg))), float(T.taper_window_r),
                          int(T.taper_min_samples), float(T.no_narrowing_wrist), float(T.heel_reach_r),
                          float(T.heel_width_tol))
    if not made:
        return m
    out = m.copy()
    out[y0:y1, x0:x1] &= ~cut
    return out


_NO_TOUCH = np.zeros((1, 1), bool)


def _cut_reference(solid, cy, cx, r, go_on, touch, m_px, at_end, wrist_range=(0.9, 2.6)):
    """The pixels of the crop :func:`cut_forearm` removes beyond the wrist, or None when it cuts nothing:
    its rules from the palm on in numpy (:func:`_parts`, :func:`_going_on_parts`, :func:`_arm_axis`,
    :func:`_wrist_distance`, :func:`_heel_end`), the definition
    :func:`tracker._segment_kernels.wrist_cut` computes compiled (tests compare them)."""
    # offsets from the palm's centre as broadcast views (np.mgrid's full grids cost more than the math)
    vy, vx = np.broadcast_arrays(np.arange(solid.shape[0])[:, None] - cy, np.arange(solid.shape[1])[None, :] - cx)
    rho = np.hypot(vy, vx)
    parts = _parts(solid, rho, vy, vx, r)
    if parts is None:
        return None
    continues, several = _going_on_parts(parts, go_on, touch, vy, vx, r, m_px)
    width = parts.width.copy()
    width[~continues[1:]] = 0.0
    j = int(np.argmax(width))
    if width[j] < 0.45 * r:
        return None
    axis = _arm_axis(parts, j, vy, vx, rho, r)
    if axis is None:
        return None
    ay, ax = axis
    t = vy * ay + vx * ax
    strip = solid & (np.abs(-vy * ax + vx * ay) <= 2.5 * r)
    t_w = _heel_end(t, strip, r) if at_end else _wrist_distance(t, strip, r, wrist_range)
    if t_w is None:
        return None
    return strip & (t > t_w)


def _crop(m):
    """``(y0, y1, x0, x1)``: the box of mask ``m`` grown by 2 px, within the image."""
    (ya, yb), (xa, xb) = bounds(m)
    pad = 2
    y0, x0 = max(ya - pad, 0), max(xa - pad, 0)
    y1, x1 = min(yb + pad + 1, m.shape[0]), min(xb + pad + 1, m.shape[1])
    return y0, y1, x0, x1


def _going_on(beyond, solid, dt, crop, shape):
    """Where :func:`cut_forearm`'s region goes on, in the crop: the image border, or the surface
    ``beyond`` it (the arm's side; only its pieces outside the region's outline, :func:`_outside_pieces`)."""
    y0, y1, x0, x1 = crop
    go_on = np.zeros(solid.shape, bool)
    if beyond is not None:
        go_on |= _dilate(_outside_pieces(np.asarray(beyond, bool)[y0:y1, x0:x1], solid, 0.5 * float(dt.max())), 2)
    H, W = shape
    go_on[:, :1] |= x0 == 0
    go_on[:, -1:] |= x1 == W
    go_on[:1, :] |= y0 == 0
    go_on[-1:, :] |= y1 == H
    go_on &= solid
    return go_on


def _palm_centre(sub, dt, solid, go_on, touch, crop, shape, seed, prefer):
    """``(cy, cx, at_end)`` in the crop: the palm's centre, the widest place — among places nearly as wide (a
    fist is hardly wider than a forearm) and filled by the mask before closing (``sub``), the one farthest from
    where the region goes on (``go_on``), or from a contact about a palm wide (``touch``: where another
    object meets the region) when nothing goes on, or nearest the ``seed`` when neither; inside ``prefer``
    first (the tracker's prediction, whole-frame slices). Away from where the region goes on, the palm
    may be found at the region's far end instead (:func:`_hand_end_palm`; ``at_end``)."""
    y0, y1, x0, x1 = crop
    cand = _filled_places(dt >= K.TUNING.palm_width_share * dt.max(), sub, float(dt.max()))
    if prefer is not None:
        # while tracking: an arm stub as wide as the palm, farther from where the region goes on, is no
        # palm when the hand was predicted elsewhere
        there = np.zeros(shape, bool)
        there[prefer] = True
        there = there[y0:y1, x0:x1] & cand
        if there.any():
            cand = there
    away = go_on
    if not go_on.any() and touch is not None:
        # nothing goes on past the region, but an object meets it along an arm's width (the table
        # where the skin test ends the arm): the palm is away from there too; a fingertip touching the
        # body meets it along a finger's width only and does not move the palm
        tl, tn = _label(touch, eight=True)
        if tn:
            # a contact's size: its pixels in the band (the contact dilated by 2 px, inside the region)
            # over 5, against the widest place's radius: the band is 2-3 px deep, so this passes a
            # contact about a palm wide (an arm's) and not a finger wide one (a fingertip's)
            wide = np.flatnonzero(np.bincount(tl[tl > 0], minlength=tn + 1)[1:] / 5.0 >= float(dt.max())) + 1
            away = _in_labels(tl, wide)
    if away.any():
        far = _edt(away)
        # compiled: the farthest candidate, then _hand_end_palm (tests/tracker/test_segment_wrist.py compares them)
        T = K.TUNING
        cy, cx, at_end = palm_place(np.ascontiguousarray(cand), far, dt, np.ascontiguousarray(sub, dtype=np.bool_),
                                    solid, float(T.arm_reach_r), float(T.hand_end_width_share),
                                    float(T.palm_width_share), float(T.palm_fill_slack), float(T.palm_fill_min))
        return cy, cx, bool(at_end)
    if seed is not None and np.asarray(seed, bool)[y0:y1, x0:x1].any():
        # nothing goes on (an arm ending in view): of the places nearly as wide, the one nearest
        # the hand's nearest part (a fist's knuckles face the camera, an arm's far end does not)
        near = _edt(np.asarray(seed, bool)[y0:y1, x0:x1])
        return (*np.unravel_index(int(np.argmin(np.where(cand, near, np.inf))), dt.shape), False)
    return (*np.unravel_index(int(np.argmax(dt)), dt.shape), False)


def _hand_end_palm(cy, cx, dt, sub, solid, far):
    """``(cy, cx, at_end)``: the palm :func:`_palm_centre` chose, or (``at_end`` True) the palm at the region's far
    end from where it goes on (``far``: the distance from there) when the region reaches farther past
    ``(cy, cx)`` than fingers can (:attr:`SegmentConstants.arm_reach_r` of its radius ``dt``): the widest
    places — nearly as wide and filled, as in :func:`_palm_centre` — among those from which that far end is
    within fingers' reach, when they are at least :attr:`SegmentConstants.hand_end_width_share` as wide as the
    widest place. A fist seen from the thumb's side is narrower than the forearm, so every place nearly as
    wide as the widest was on the arm (the realistic fist-side scenes, 1.0x, Kinect v1: the palm placed
    10 r down the arm and the fist cut off as the arm's end); the fingers of a hand seen edge-on, thinner
    than its arm, are far narrower (0.3-0.4 of it) and leave the first choice (there the widest place
    nearest them is the arm's end at the wrist, and the cut beyond it keeps the hand).

    >>> solid = np.zeros((40, 12), bool); solid[2:10, 2:9] = True; solid[10:40, 3:11] = True   # fist, arm
    >>> dt = _edt(~solid); far = 39.0 - np.arange(40.0)[:, None] + 0 * dt                        # goes on below
    >>> [int(v) for v in _hand_end_palm(30, 6, dt, solid, solid, far)]   # the arm's place -> the fist's
    [5, 5, 1]
    >>> solid = np.zeros((70, 12), bool); solid[2:32, 6:8] = True; solid[32:70, 3:11] = True   # finger, arm
    >>> far = 69.0 - np.arange(70.0)[:, None] + np.zeros((1, 12))
    >>> [int(v) for v in _hand_end_palm(60, 6, _edt(~solid), solid, solid, far)]
    [60, 6, 0]
    """
    ey, ex = np.unravel_index(int(np.argmax(np.where(solid, far, -1.0))), dt.shape)
    reach = K.TUNING.arm_reach_r
    if np.hypot(cy - ey, cx - ex) <= reach * dt[cy, cx]:
        return cy, cx, False
    vy, vx = np.broadcast_arrays(np.arange(dt.shape[0])[:, None] - ey, np.arange(dt.shape[1])[None, :] - ex)
    # the places a hand's palm can be: its fingers reach the far end from there
    near = solid & (np.hypot(vy, vx) <= reach * dt)
    top = float(dt[near].max()) if near.any() else 0.0
    if top < K.TUNING.hand_end_width_share * float(dt.max()):
        # only fingers reach the far end (a hand seen edge-on, thinner than its arm): the palm is not there
        return cy, cx, False
    cand = _filled_places(near & (dt >= K.TUNING.palm_width_share * top), sub, top)
    return (*np.unravel_index(int(np.argmax(np.where(cand, far, -1.0))), dt.shape), True)


def _palm_depth(depth, m, crop, cy, cx):
    """The palm's depth: the median of the 5 x 5 pixels round its centre, else of the whole mask ``m``."""
    y0, y1, x0, x1 = crop
    zc = _nanmedian(np.asarray(depth, float)[y0:y1, x0:x1][max(cy - 2, 0):cy + 3, max(cx - 2, 0):cx + 3])
    if not np.isfinite(zc):
        zc = _nanmedian(np.asarray(depth, float)[m])
    return zc


def _parts(solid, rho, vy, vx, r):
    """The :class:`_Parts` of ``solid`` outside 1.6 ``r`` of the palm's centre, or None when there are none."""
    outside = solid & (rho > 1.6 * r)
    lab, n = _label(outside, eight=True)
    if n == 0:
        return None
    # a part's width where it leaves the palm (its chord across a ring 0.3 r wide), not its
    # widest place: an arm the region's reach cuts short is no wider inside the region than a finger
    base = (rho <= 1.9 * r) & (lab > 0)
    width = np.bincount(lab[base], minlength=n + 1)[1:] / (0.3 * r) / 2.0
    reach_r = label_max(rho, lab, n)
    nb = np.maximum(np.bincount(lab[base], minlength=n + 1)[1:], 1)
    cy_p = np.bincount(lab[base], weights=vy[base], minlength=n + 1)[1:] / nb
    cx_p = np.bincount(lab[base], weights=vx[base], minlength=n + 1)[1:] / nb
    # spread fingers cross a ring around the palm as several pieces, an arm as one
    ring_lab, _ = _label(outside & (rho >= 2.0 * r) & (rho <= 2.4 * r), eight=True)
    on = ring_lab > 0
    piece_size = np.bincount(ring_lab[on])
    big = np.flatnonzero(piece_size >= 0.05 * r * r)
    owner = np.zeros(piece_size.size, int)
    owner[ring_lab[on]] = lab[on]
    pieces = np.bincount(owner[big[big > 0]], minlength=n + 1)[1:]
    return _Parts(lab, n, width, cy_p, cx_p, reach_r, ring_lab, piece_size, owner, pieces)


def _going_on_parts(p, go_on, touch, vy, vx, r, m_px):
    """``(continues, several)``: which parts (``continues[j + 1]``) are an arm going on past the region,
    and which cross the ring around the palm in several pieces (``several[j]``, spread fingers)."""
    continues = np.zeros(p.n + 1, bool)
    continues[np.unique(p.lab[go_on & (p.lab > 0)])] = True
    if touch is not None:
        # a part another object meets at its depth goes on into it (an arm into a table or the
        # body); not used for the palm's place: fingertips touch the body too
        continues[np.unique(p.lab[touch & (p.lab > 0)])] = True
    # a part reaching farther from the palm's centre than any finger can is an arm even where it
    # ends inside the region (a forearm seen end-on, or one cut off by a no-data gap)
    continues[1:] |= p.reach_r > K.TUNING.arm_reach_r * r
    # a part that crosses the ring in several pieces is the fingers even where it reaches beyond the
    # region (fingertips past the reach) — unless it is an arm a finger touches
    several = p.pieces >= 2
    for j in np.flatnonzero(several & continues[1:]):
        several[j] = not _arm_a_finger_touches(j, p.ring_lab, p.owner, p.piece_size, vy, vx, r, m_px, p.width,
                                               p.cy_p, p.cx_p, ~continues[1:] & ~several)
    continues[1:] &= ~several
    # … and so is a wide part opposite the fingers (an arm receding from the camera, short in the image)
    ends = ~continues[1:]
    wide = p.width >= 0.45 * r
    for j in np.flatnonzero(ends & wide & (p.reach_r >= K.TUNING.opposite_arm_reach_r * r)):
        # the other parts that end here, weighted by their width: the fingers' side of the palm
        # (at least a finger's width of them: noise specks at the outline are no fingers, and a hand
        # seen alone ends at its wrist in a stub that reaches less far than any visible forearm)
        others = ends.copy()
        others[j] = False
        # a part as wide as an arm that reaches less far than one is no finger to weigh: an arm stub the
        # region's reach cut short (in front of a body 4 cm behind) outweighed the fingers and put a group of
        # fingers "opposite the fingers"
        others &= ~(wide & (p.reach_r < K.TUNING.opposite_arm_reach_r * r))
        continues[j + 1] |= _opposite_fingers(p.cy_p[j], p.cx_p[j], p.width, p.cy_p, p.cx_p, others, r)
    # spread fingers stay fingers whichever rule called them an arm — unless the part reaches
    # farther than any hand: an arm whose thumb or finger touches it outside the palm circle
    # crosses the ring in pieces too
    continues[1:] &= ~several | (p.reach_r > K.TUNING.sure_arm_reach_r * r)
    return continues, several


def _arm_axis(p, j, vy, vx, rho, r):
    """``(ay, ax)``: the unit direction of the arm (part ``j``) from the palm's centre, or None."""
    arm = p.lab == j + 1
    ring = arm & (rho < 2.6 * r)
    if p.pieces[j] >= 2:
        # an arm with a finger touching it: its direction is that of its widest piece on the ring
        ring = ring & _dilate(p.ring_lab == _widest_piece(p.owner, p.piece_size, j, r), 2)
    if not ring.any():
        ring = arm
    ay, ax = vy[ring].mean(), vx[ring].mean()
    norm = np.hypot(ay, ax)
    if norm == 0:
        return None
    ay, ax = ay / norm, ax / norm
    # the cut goes across the arm: its direction is the arm's own, from where it leaves the palm circle to
    # its far end in the region, when that is long enough to tell (half a palm radius) and more than
    # arm_bend_deg off the direction from the palm's centre (a wrist bent sideways puts the centre off
    # the arm's axis: real frame 230536_70, 22°, where a cut across the centre's direction took a 648 px
    # triangle of the palm's heel); closer than that the two agree within their noise and the centre's,
    # the steadier one, is kept; beyond 60° the far end is no straight arm's
    leave = ring & (rho <= 2.4 * r) if p.pieces[j] >= 2 else arm & (rho <= 1.9 * r)
    far = arm & (rho >= float(rho[arm].max()) - 0.5 * r)
    if leave.any() and far.any():
        dy, dx = vy[far].mean() - vy[leave].mean(), vx[far].mean() - vx[leave].mean()
        n_arm = np.hypot(dy, dx)
        cos = (dy * ay + dx * ax) / max(n_arm, 1e-12)
        if n_arm >= 0.5 * r and 0.5 <= cos < np.cos(np.radians(K.TUNING.arm_bend_deg)):
            ay, ax = dy / n_arm, dx / n_arm
    return ay, ax


def _wrist_distance(t, strip, r, wrist_range):
    """How far along the arm (px, ``t``) the wrist lies: where the width of ``strip`` across it stops
    narrowing within ``wrist_range`` · ``r``; None when the strip has no pixels there."""
    lo, hi = int(np.floor(wrist_range[0] * r)), int(np.ceil(wrist_range[1] * r))
    ti = np.round(t[strip]).astype(int)
    keep = (ti >= lo) & (ti <= hi)
    if not keep.any():
        return None
    prof = np.bincount(ti[keep] - lo, minlength=hi - lo + 1).astype(float)
    prof = _uniform1d(prof, 5)
    # the wrist is where the narrowing from the palm stops: the first distance beyond which the
    # width shrinks by less than 10 % over the next 0.3 r (a forearm further out may still taper,
    # recede or be cropped, so the global minimum would cut too late)
    i = _end_of_narrowing(prof, max(int(round(0.3 * r)), 2))
    if i > 0:
        return lo + i
    # no sharp narrowing: a slow taper (a small hand at the coarse search's resolution, r ≈ 7 px,
    # narrows by less than a pixel a sample: the realistic ×0.8 SR305 scene's cut went ~1 cm into
    # the palm) ends where the width stops falling over taper_window_r; and the wrist lies at least
    # no_narrowing_wrist r from the palm's centre (an arm as wide as the palm in the image, e.g. a
    # tilted palm; the rendered hand/forearm boundary lies at 1.17 r, median of ~1150 rendered frames,
    # but 1.2 r cut into the palm of realistic-scene frames the size is calibrated on: 0.977 -> 0.954)
    taper = _end_of_taper(prof, max(int(round(K.TUNING.taper_window_r * r)), K.TUNING.taper_min_samples))
    return max(lo + taper, int(round(K.TUNING.no_narrowing_wrist * r)))


def _heel_end(t, strip, r):
    """How far along the arm (px, ``t``) the wrist of a fist seen from its side lies (:func:`cut_forearm`'s
    palm at the region's far end, radius ``r``): where the narrowest stretch of ``strip`` — widths within
    :attr:`SegmentConstants.heel_width_tol` of the least — ends, looked for from 0.9 r out to
    :attr:`SegmentConstants.heel_reach_r` past the region's far end; None when the strip has no pixels there.

    The hand's heel narrows away from the fist and widens into the forearm at the wrist, so the end of the
    narrowing (:func:`_wrist_distance`) lies at the fist's edge: it cut off 34-49 % of the hand in the
    realistic fist-side scenes, this 9-21 %.

    >>> t = np.arange(60.0)[:, None] - 10 + np.zeros((1, 30)); strip = np.zeros((60, 30), bool)
    >>> strip[:20, 5:25] = True; strip[20:38, 10:20] = True; strip[38:, 8:22] = True   # fist, heel, arm
    >>> _heel_end(t, strip, 8.0)   # the heel's last row is t = 27 (the 5-sample smoothing ends it a sample early)
    26
    """
    t0 = float(t[strip].min())
    lo, hi = int(np.floor(0.9 * r)), int(np.ceil(t0 + K.TUNING.heel_reach_r * r))
    ti = np.round(t[strip]).astype(int)
    keep = (ti >= lo) & (ti <= hi)
    if hi <= lo or not keep.any():
        return None
    prof = _uniform1d(np.bincount(ti[keep] - lo, minlength=hi - lo + 1).astype(float), 5)
    i = int(np.argmin(prof))
    wider = np.flatnonzero(prof[i:] > (1.0 + K.TUNING.heel_width_tol) * prof[i])
    return lo + i + (int(wider[0]) - 1 if wider.size else prof.size - 1 - i)


def _filled_places(cand, raw, rad, slack=None, least=None):
    """The places of ``cand`` whose disk of radius ``rad`` the ``raw`` mask (before closing) fills
    within ``slack`` of the best-filled one or at least ``least``. A 0.8× hand's spread
    fingers lie a pixel or two apart at the search's resolution, and the closing that mends no-data
    cracks joins their bases into a blob as wide as the palm; the raw mask leaves the gaps between them
    (Kinect v1, torso 4 cm behind, frame 0: that blob's places filled 0.66–0.77, the palm's 0.99; the
    palm placed there cut the hand mid-palm). Curled fingers leave gaps at a right palm's edge too
    (0.88 on a 1.0× hand's half-closed frame, where the relative test alone moved the palm and the cut
    kept 2 cm of forearm), hence the absolute floor.

    >>> raw = np.ones((9, 20), bool); raw[:, 2:7:2] = False        # the left part "fingers" with gaps
    >>> cand = np.zeros_like(raw); cand[4, 4] = cand[4, 14] = True
    >>> np.argwhere(_filled_places(cand, raw, 3.0)).tolist()
    [[4, 14]]
    """
    slack = K.TUNING.palm_fill_slack if slack is None else slack
    least = K.TUNING.palm_fill_min if least is None else least
    # compiled (tests/tracker/test_segment_wrist.py: against _filled_reference, the numpy expression)
    return filled_places(np.ascontiguousarray(cand, dtype=np.bool_), np.ascontiguousarray(raw, dtype=np.bool_),
                         float(rad), float(slack), float(least))


def _filled_reference(cand, raw, rad, slack, least):
    """:func:`_filled_places` in numpy (the disk's rows by :func:`tracker._segment_kernels.disk_counts`)."""
    ys, xs = np.nonzero(cand)
    if ys.size < 2:
        return cand
    k = int(np.ceil(rad))
    disk = np.hypot(*np.ogrid[-k:k + 1, -k:k + 1]) <= rad  # open grids: the same values, broadcast
    # each disk row's columns (a disk's rows are runs; an empty row's lo > hi); the share of the disk the
    # mask fills, as its mean was
    cols = np.arange(-k, k + 1)
    lo, hi = np.where(disk, cols, k + 1).min(1), np.where(disk, cols, -k - 1).max(1)
    fill = disk_counts(np.ascontiguousarray(raw, dtype=np.bool_), ys.astype(np.int64), xs.astype(np.int64),
                       lo, hi) / np.count_nonzero(disk)
    keep = fill >= min(fill.max() - slack, least)
    out = np.zeros_like(cand)
    out[ys[keep], xs[keep]] = True
    return out


def _outside_pieces(pieces, solid, rad):
    """The pieces of ``pieces`` (pixels of the hand's surface outside the region ``solid``) that lie
    mostly outside ``solid`` closed with a disk of radius ``rad``: an arm goes on away from the hand;
    a piece held in a notch of its outline is the body behind seen through a gap in the hand, which
    sensor noise joined to the hand's surface (between a rendered thumb and palm with the torso 4 cm
    behind, 27 px: the hand's side "went on" like an arm, the palm was placed on the forearm and the
    whole forearm kept, SR305 1.0×, frame 0).

    >>> solid = np.zeros((12, 12), bool); solid[2:10, 2:5] = True; solid[2:10, 7:10] = True; solid[7:10, 2:10] = True
    >>> pieces = np.zeros_like(solid); pieces[2:7, 5:7] = True; pieces[10:12, 7:10] = True  # in the notch; below
    >>> _outside_pieces(pieces, solid, 2.0)[:, 5:10].astype(int)[[3, 10]]
    array([[0, 0, 0, 0, 0],
           [0, 0, 1, 1, 1]])
    """
    if not pieces.any() or rad < 1.0:
        return pieces
    closed = _disk_closing(solid, rad)
    lab, n = _label(pieces)
    total = np.bincount(lab.ravel(), minlength=n + 1)
    inside = np.bincount(lab[closed & pieces], minlength=n + 1)
    keep = inside < 0.5 * total
    keep[0] = False
    return keep[lab]


def _end_of_narrowing(profile, window, drop=0.10):
    """First index from which ``profile`` falls by less than ``drop`` (relative) over the next
    ``window`` samples; the last index when it keeps falling."""
    p = np.asarray(profile, float)
    for i in range(p.size - window):
        if p[i] - p[i + window] < drop * p[i]:
            return i
    return p.size - 1


def _end_of_taper(profile, window, drop=0.10):
    """First index from which ``profile`` never falls more than ``drop`` (relative) below its value
    there within the next ``window`` samples; the last index when it keeps falling.

    Unlike :func:`_end_of_narrowing` (the width ``window`` samples on), the lowest width within the
    window counts, so a slow taper that ends in a flat stretch ends where the flat stretch starts.

    >>> _end_of_taper([17, 17, 16, 15, 14, 13, 12, 12, 12, 12, 12, 11], 3)   # 13 is within 10 % of the flat 12
    5
    >>> _end_of_taper([12, 12, 12, 12], 3), _end_of_taper([9, 8, 7, 6], 2)
    (0, 3)
    """
    p = np.asarray(profile, float)
    for i in range(p.size - 1):
        if p[i] - p[i:i + window + 1].min() < drop * p[i]:
            return i
    return p.size - 1
