"""The :class:`Segmenter`: the working volume, the skin and plane filters, the coarse search and its
refinement, in the whole frame or in the predicted hand's window (:meth:`Segmenter.in_window`)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import constants as K
from .buffers import FrameBuffers
from .._segment_kernels import mask_sums, valid_depths, valid_pixels
from .constants import FIND, FOREARM_CHOICES, PLANE_CHOICES
from .forearm import cut_forearm
from .layers import _joins
from .ops import bounds, in_box
from .plane import support_plane
from .region import hand_region
from .skin import skin_mask
from .surfaces import focal_from_points, refine


@dataclass
class Segmenter:
    """Settings of the hand segmentation (metres, pixels).

    Parameters
    ----------
    z_min, z_max : working depth range
    box_min, box_max : optional axis-aligned box in the camera frame (None entries are open)
    band : how far behind the hand's nearest part the hand may reach
    min_pixels : smallest surface considered, in pixels
    min_area : smallest surface considered as the hand, in m² (a hand seen from the front is
        about 0.01–0.015 m²; specks, flying pixels and thin edges are smaller)
    jump : depth step between neighbouring pixels that separates two surfaces
    margin_px : how far (pixels) a fingertip blob may lie from the hand and still belong to it
    blob_area : surfaces smaller than this (m²) near the hand are fingertip blobs, larger ones are
        other objects
    reach : how far (m, 3-D) the hand may extend from its nearest part's centre (None: no limit)
    forearm : ``"cut"`` (remove the forearm beyond the wrist) or ``"keep"``
    use_color : keep only skin-coloured pixels when a colour frame is given
    plane : ``"auto"`` (leave out the frame's largest plane, :func:`support_plane`, when no colour
        frame is used), ``"cut"`` (always) or ``"keep"`` (never)
    coarse : search on every ``coarse``-th pixel in x and y, then refine the edges at full
        resolution (1: search at full resolution; used only for images of at least 40·coarse
        pixels each way)

    Attributes
    ----------
    buffers : the full-frame arrays its results are written to, reused from frame to frame when free
        (:class:`tracker.segment.buffers.FrameBuffers`; hold one segmenter for a sequence, as
        :func:`tracker.observe.observe`'s ``segmenter``)
    """

    z_min: float = 0.2
    z_max: float = 1.5
    box_min: tuple | None = None
    box_max: tuple | None = None
    band: float = 0.12
    min_pixels: int = 30
    min_area: float = 0.004
    jump: float = 0.02
    margin_px: int = 25
    blob_area: float = 0.003
    reach: float | None = 0.22
    forearm: str = "cut"
    use_color: bool = True
    coarse: int = 2
    plane: str = "auto"
    buffers: FrameBuffers = field(default_factory=FrameBuffers, init=False, repr=False, compare=False)

    def __post_init__(self):
        _check(self)

    def __call__(self, depth, color=None, points=None, *, focal=None, plane=FIND, prefer=None):
        """Boolean hand mask ``(H, W)`` for a depth image in metres (NaN = no data).

        ``points``: the back-projected ``(H, W, 3)`` image (needed for ``box``); ``focal``: the
        camera's focal length in pixels (for physical areas; read from ``points`` if None, else
        :attr:`SegmentConstants.default_focal_px`); ``plane``: this frame's :meth:`frame_plane` when the caller has it
        already (found here otherwise); ``prefer``: a ``(rows, cols)`` slice pair where the hand is
        expected (the tracker's prediction): the wrist cut's palm is looked for there first
        (:func:`cut_forearm`; an arm stub as wide as a half-closed hand's palm, farther from where the
        region goes on, took the palm and the hand was cut off as the arm: the realistic Kinect v1 1.0×
        table scene, noise seed 2, frame 22, lost for the rest of its run)."""
        d, f = self._inputs(depth, points, focal)
        return self._run(d, color, points, f, plane=self.frame_plane(d, color, focal=f) if plane is FIND else plane,
                         prefer=prefer)[0]

    def _skin(self, color) -> bool:
        """Whether the skin test runs (a colour frame given and ``use_color``)."""
        return color is not None and self.use_color

    def frame_plane(self, depth, color=None, *, focal):
        """The whole frame's :func:`support_plane` when it is to be left out (``plane``), else None."""
        if self.plane == "keep" or (self.plane == "auto" and self._skin(color)):
            return None
        return support_plane(depth, focal, z_min=self.z_min, z_max=self.z_max)

    def _inputs(self, depth, points, focal):
        """``(depth as float, focal length)``, refusing a box without the points it is tested on."""
        if (self.box_min is not None or self.box_max is not None) and points is None:
            raise ValueError("a segmentation box needs the back-projected points")
        return np.asarray(depth, float), (float(focal) if focal else focal_from_points(points))

    def in_window(self, depth, window, color=None, points=None, *, focal=None, expected=None, plane=FIND):
        """The hand mask ``(H, W)`` found in ``window`` alone (a ``(rows, cols)`` slice pair, e.g.
        :func:`tracker.observe.hand_window` of the hand predicted while tracking), or None when that result
        cannot be trusted and the whole frame must be segmented (:meth:`__call__`).

        Inside the window every rule runs as on the whole frame, on the same (coarse) pixels, and the
        window's edges count as image borders: an object the window cuts off is cut off, and the
        forearm goes on past them. That changes nothing for a hand well inside the window; so the
        result is refused when the mask is empty, when it comes within :attr:`SegmentConstants.border_px` of a window
        edge that is not an image edge (the hand, or an uncut arm, runs out of the window), when
        its centre lies outside ``expected`` (a slice pair: where the hand was predicted; None = not
        tested) — something else than the hand was found there —, or when the region stands in front of
        a surface close behind it (:func:`_in_front`'s outline test, whether or not the layer is then
        taken): the layer rule reads the body around the hand, and the window's edges cut that short
        (the realistic Kinect v1 1.5× scene with a torso 4 cm behind: in windows around the hand the
        torso was kept as the hand on 7 of 12 frames, in the whole frame the hand on all of them).
        ``plane``: as for :meth:`__call__`."""
        d, f = self._inputs(depth, points, focal)
        H, W = d.shape
        (y0, y1), (x0, x1) = _snapped(window, (H, W), self.coarse)
        if y1 - y0 < 2 or x1 - x0 < 2:
            return None
        win = (slice(y0, y1), slice(x0, x1))
        sub, layered = self._run(d[win], None if color is None else np.asarray(color)[win],
                        None if points is None else np.asarray(points)[win], f, (y0, x0), (H, W),
                        plane=self.frame_plane(d, color, focal=f) if plane is FIND else plane,
                        prefer=expected, in_window=True)
        if not sub.any() or layered or not _trusted(sub, (y0, y1, x0, x1), (H, W), expected):
            return None
        out = self.buffers.zeros("mask", (H, W))
        out[win] = sub
        return out

    def _run(self, d, color, points, f, origin=(0, 0), whole_shape=None, plane=None, prefer=None,
             in_window=False):
        """``(mask, layered)``: the mask of ``d``: the whole frame, or the window of a frame of ``whole_shape`` whose
        first pixel is ``origin`` (the search then runs on the whole frame's pixels, with its
        principal point); ``plane``: the whole frame's :class:`SupportPlane` to leave out, or None;
        ``layered``: as :meth:`_segment`'s; ``prefer``: as for :meth:`__call__` (the whole
        frame's pixels); ``in_window``: ``d`` is :meth:`in_window`'s window and ``prefer`` the hand
        predicted in it (:func:`hand_region`'s ``expected``)."""
        c = int(self.coarse)
        H, W = whole_shape or d.shape
        (y0, x0) = origin
        if c <= 1 or min(H, W) < 40 * c:
            return self._segment(d, color, points, f, centre=((H - 1) / 2 - y0, (W - 1) / 2 - x0), plane=plane,
                                 prefer=_sampled(prefer, origin, 1), in_window=in_window)
        # the search runs on every c-th pixel (c² times fewer pixels), the edges are then
        # refined at full resolution in the hand's window only
        sub = (slice(None, None, c), slice(None, None, c))
        dc = d[sub]
        mc, layered = self._segment(dc, None if color is None else np.asarray(color)[sub],
                           None if points is None else np.asarray(points)[sub], f / c, c,
                           centre=((-(-H // c) - 1) / 2 - y0 / c, (-(-W // c) - 1) / 2 - x0 / c), plane=plane,
                           full=d, prefer=_sampled(prefer, origin, c), in_window=in_window)
        if not mc.any():
            return np.zeros(d.shape, bool), layered
        out, win = refine(mc, dc, d, c, self.jump)
        out[win] &= self._valid(d[win], None if color is None else np.asarray(color)[win],
                                None if points is None else np.asarray(points)[win], skin_only=False, plane=plane,
                                at=(f, (H - 1) / 2 - y0 - win[0].start, (W - 1) / 2 - x0 - win[1].start))
        return out, layered

    def _valid(self, d, color, points, skin_only=True, plane=None, at=None):
        """The working volume's pixels of ``d``, skin-coloured ones only with a colour frame, those off
        ``plane`` (a :class:`SupportPlane`) when given; ``at``: ``(focal, cy, cx)`` of ``d``'s pixels."""
        args = self._compiled_valid(color, plane, at, skin_only)
        if args is not None:
            # compiled in one pass (three a tracked frame, on strided views: no copies)
            return valid_pixels(np.asarray(d, np.float64), *args)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(d) & (d > self.z_min) & (d < self.z_max)
        if self.box_min is not None or self.box_max is not None:
            valid &= in_box(points, self.box_min, self.box_max)
        if self._skin(color):
            skin = skin_mask(color) & valid
            if skin.sum() >= (self.min_pixels if skin_only else 1):
                valid = skin
        if plane is not None:
            valid &= ~plane.pixels(d, *at)
        return valid

    def _compiled_valid(self, color, plane, at, skin_only):
        """The arguments after the depth of :func:`tracker._segment_kernels.valid_pixels` for :meth:`_valid`, or
        None when it does not apply (a box, which needs the points; a hue range narrower than the circle)."""
        (h0, s0, v0), (h1, s1, v1) = K.TUNING.skin_hsv
        if self.box_min is not None or self.box_max is not None or h0 > 0 or h1 < 179:
            return None
        use_c = self._skin(color)
        c = np.asarray(color) if use_c else _NO_COLOUR
        c = c if c.dtype == np.uint8 else c.astype(np.uint8)
        nx, ny, nz, dn, band = (0.0,) * 5 if plane is None else (*plane.normal, plane.offset, plane.band)
        f, cy, cx = (1.0, 0.0, 0.0) if plane is None else at
        return (c, use_c, float(self.z_min), float(self.z_max), v0, v1, s0, s1, self.min_pixels if skin_only else 1,
                plane is not None, float(nx), float(ny), float(nz), float(dn), float(f), float(cy), float(cx),
                float(band))

    def _segment(self, d, color, points, f, step=1, centre=None, plane=None, full=None, prefer=None,
                 in_window=False):
        """``(mask, layered)``: the search on an image subsampled by ``step`` (pixel counts and distances scale);
        ``centre``: the principal point in its pixel coordinates (None: the image's centre);
        ``plane``: a :class:`SupportPlane` left out as the skin test leaves pixels out; ``full``: the
        full-resolution depth ``d`` was sampled from (a farther surface's fingers are looked for there
        too, :func:`_has_fingers`); ``layered``: whether the region stands in front of a surface close
        behind it (:class:`Region`); ``in_window``: ``d`` is a window and
        ``prefer`` the hand predicted in it (:func:`hand_region`'s ``expected``)."""
        if centre is None:
            centre = ((d.shape[0] - 1) / 2, (d.shape[1] - 1) / 2)
        # the frame before the skin filter (and the plane), d_all: where a table or the body meets the hand,
        # the arm goes on
        filtered = self._skin(color) or plane is not None
        args = self._compiled_valid(color, plane, (f, *centre), True)
        if args is not None:
            # the valid pixels, their depths and the working volume's depths in one compiled call
            valid, dv, d_all = valid_depths(np.asarray(d, np.float64), *args)
            if not valid.any():
                return valid, False
            d_all = d_all if filtered else dv
        else:
            valid = self._valid(d, color, points, plane=plane, at=(f, *centre))
            if not valid.any():
                return valid, False
            dv = np.where(valid, d, np.nan)
            d_all = np.where(self._valid(d, None, points), d, np.nan) if filtered else dv
        reg = hand_region(dv, f, band=self.band, jump=self.jump,
                           min_pixels=max(self.min_pixels // step ** 2, 1), min_area=self.min_area,
                           margin_px=int(np.ceil(self.margin_px / step)), blob_area=self.blob_area,
                           reach=self.reach, points=points, border_px=int(np.ceil(K.TUNING.border_px / step)),
                           centre=centre, fingers_first=not self._skin(color),
                           fine=None if full is None or step <= 1 else (full, step),
                           expected=prefer if in_window else None)
        mask = reg.mask
        if self.forearm == "cut" and mask.any():
            # where a table or the body meets the hand at its depth (seen before the skin filter)
            joins = _joins(mask, dv, mask | reg.beyond | reg.behind, d_all, f, jump=self.jump)
            mask = cut_forearm(mask, dv, f, reg.beyond, seed=reg.seed, joins=joins, prefer=prefer)
        return mask, reg.layered


_NO_COLOUR = np.zeros((1, 1, 3), np.uint8)


def _check(seg):
    """Refuse a :class:`Segmenter` with an unknown ``forearm`` or ``plane`` choice or an empty depth range."""
    if seg.forearm not in FOREARM_CHOICES:
        raise ValueError(f"forearm must be one of {', '.join(FOREARM_CHOICES)}, got {seg.forearm!r}")
    if seg.plane not in PLANE_CHOICES:
        raise ValueError(f"plane must be one of {', '.join(PLANE_CHOICES)}, got {seg.plane!r}")
    if not seg.z_max > seg.z_min:
        raise ValueError(f"depth range must have far > near, got {seg.z_min}, {seg.z_max}")


def _snapped(window, shape, coarse):
    """``((y0, y1), (x0, x1))``: the ``window`` (a ``(rows, cols)`` slice pair) within an image of ``shape``,
    its start snapped down to twice the ``coarse`` step: the window's coarse pixels are then the whole
    frame's, and so is refine's rounding of pixel / step to the nearest coarse pixel (halves go to even).

    >>> _snapped((slice(13, 40), slice(None, 99)), (60, 80), 2)
    ((12, 40), (0, 80))
    """
    g = 2 * max(int(coarse), 1)
    return tuple((max(int(s.start or 0), 0) // g * g, min(int(n if s.stop is None else s.stop), n))
                 for s, n in zip(window, shape))


def _trusted(sub, edges, shape, expected):
    """Whether the mask ``sub`` found in the window ``edges`` = ``(y0, y1, x0, x1)`` of a frame of ``shape``
    may stand for the whole frame's (:meth:`Segmenter.in_window`): it keeps :attr:`SegmentConstants.border_px`
    from every window edge that is not an image edge, and its centre lies in ``expected`` (a slice pair
    of the frame's pixels; None: not tested)."""
    y0, y1, x0, x1 = edges
    H, W = shape
    (ya, yb), (xa, xb) = bounds(sub)
    h, w = sub.shape
    if ((y0 > 0 and ya < K.TUNING.border_px) or (y1 < H and yb >= h - K.TUNING.border_px)
            or (x0 > 0 and xa < K.TUNING.border_px) or (x1 < W and xb >= w - K.TUNING.border_px)):
        return False
    if expected is not None:
        # the mask's centre (np.nonzero's means, compiled: integer sums, exact)
        n, sr, sc = mask_sums(np.ascontiguousarray(sub, dtype=np.bool_))
        cy, cx = sr / n + y0, sc / n + x0
        (ey, ex) = expected
        if not ((ey.start or 0) <= cy < (H if ey.stop is None else ey.stop)
                and (ex.start or 0) <= cx < (W if ex.stop is None else ex.stop)):
            return False
    return True


def _sampled(prefer, origin, step):
    """``prefer`` (a ``(rows, cols)`` slice pair of the whole frame's pixels, or None) in the pixels of
    an image sampled every ``step`` pixels from ``origin``.

    >>> _sampled((slice(10, 20), slice(5, 9)), (4, 0), 2)
    (slice(3, 8, None), slice(3, 5, None))
    """
    if prefer is None:
        return None
    def first(v, o):  # the first sample at or after full-frame pixel v
        return max(-(-(v - o) // step), 0)

    return tuple(slice(first(s.start or 0, o), first(1 << 30 if s.stop is None else s.stop, o))
                 for s, o in zip(prefer, origin))
