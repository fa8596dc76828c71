"""Pipeline stage ``segment``: the hand's pixels in a depth (and colour) frame — working volume,
nearest hand-sized surface, fingertip blobs, wrist cut, skin colour.

No wristband is needed. The steps, each a small function over arrays:

1. working volume: valid depth within ``[z_min, z_max]`` (and inside ``box`` when given);
2. :func:`surfaces`: pixels grouped into surfaces by depth continuity (neighbours closer than
   ``jump``), so the body and objects behind or beside the hand, and a table the hand rests on
   but stands out of, fall into other surfaces;
3. :func:`hand_region`: among surfaces of at least ``min_area`` square metres (flying pixels
   and specks do not count), the one whose nearest part is nearest to the camera;
4. that surface, cut to ``band`` metres behind its nearest part, plus the small surfaces in that
   depth band within ``margin_px`` of it (fingertips curled towards the camera that the sensor
   cuts off by a depth jump or a no-data gap). The hand is the end of an arm with fingers: an
   arm reaching towards the camera from outside the image, nearer than that surface, is taken
   instead when its far end has fingers and lies in front of it (a body a few centimetres
   behind the hand); and when the surface is a whole arm in view (it does not reach the border
   and is much longer than a palm is wide), the search starts from its end with the fingers
   (:func:`_hand_end`), since a free-ended arm's nearest part can be its far end. A body a few
   centimetres behind the hand, which the arm joins to the hand's surface, is left out: the region
   is then the layer in front of its local background (:func:`_in_front`);
5. :func:`cut_forearm` (``forearm="cut"``): the palm is the largest inscribed circle of the
   region, the forearm the wide part leaving it that goes on (past the border, the band or the
   reach, or into another object met at its own depth: a table, the body); the cut goes across
   the arm where the width profile along the arm stops narrowing (the wrist);
6. with a colour frame (``use_color``), only skin-coloured pixels (HSV range of htrack's
   detector) are kept, when enough of them are;
7. without one (``plane="auto"``), the pixels of the frame's largest plane (a table, a floor, a
   wall: :func:`support_plane`) are left out as the skin test leaves them out: an arm resting on a
   table is then no longer one surface with it.

The body-sized surface of a person standing behind the hand is never picked over the hand
because its nearest part lies behind the hand; a surface that merely touches the hand in the
image is a different surface as soon as a depth step separates them.

>>> d = np.full((60, 80), 0.9)          # a wall
>>> d[10:40, 20:40] = 0.5               # a hand-sized patch (≈ 6 × 4 cm at f = 500 px) in front
>>> m = Segmenter(min_area=1e-4)(d, focal=500.0)
>>> int(m.sum()), bool(m[20, 30]), bool(m[5, 5])
(600, True, False)
"""
from __future__ import annotations

from dataclasses import dataclass

import matplotlib.colors as mcolors
import numpy as np
from scipy import ndimage

from ._silhouette_kernels import feature_transform
from ._segment_kernels import (
    back_points,
    plane_pixels,
    plane_ransac,
    plane_refit,
    plane_samples,
    city_block,
    closed_filled,
    component_labels,
    components_holding,
    fronts_of_surfaces,
    label_max,
    largest_component as _largest_component,
    mask_bounds,
    nan_median,
    nearest_target,
    refine_window,
    skin_channels,
    surface_labels,
    window_any,
    window_extreme,
)

# HSV skin range of htrack's Detector (OpenCV scale: H 0–179, S and V 0–255)
SKIN_HSV = ((0, 56, 113), (179, 174, 255))
FOREARM_CHOICES = ("cut", "keep")
PLANE_CHOICES = ("auto", "cut", "keep")
FIND = object()  # Segmenter's ``plane`` argument when the frame's plane is to be found there
PLANE_SAMPLES = 5000  # pixels of the frame the plane search samples (every 8th pixel each way of 640 x 480)
PLANE_TRIES = 256  # planes through three sampled points tried (a table on a third of the samples: no triplet of it in 1 of 16,000 frames)
PLANE_PREEMPT, PLANE_KEEP = 8, 6  # each tried plane weighed on every 8th sample, the best 6 on all
PLANE_TOL_M = 0.012  # a sample this close to a tried plane is on it (Kinect v1 noise and steps at 1.5 m: ~7 mm)
PLANE_MIN_AREA_M2 = 0.1  # a plane is a support surface when it covers this much (a 1.5x hand: 0.027 m²) …
# … and is seen this far off face-on (the rendered table: 42°). A surface facing the camera behind the
# hand is left to the layer rule (_in_front): leaving out a flat torso 4 cm behind lost the SR305 hands
PLANE_MIN_TILT_DEG = 30.0
PLANE_BAND_M = (0.008, 0.02)  # the band left out around it: 3 robust SDs of its points, within these
DEFAULT_FOCAL_PX = 500.0  # pixel size for physical areas when the camera is not given
EDGE_GAP_PX = 2  # a small piece this close to another hand-sized surface at its depth is a piece of it (_edge_pieces)
PALM_WIDTH_SHARE = 0.93  # places at least this share of the widest count as palm candidates …
PALM_FILL_SLACK = 0.1  # … when the mask fills their disk within this share of the best-filled one …
PALM_FILL_MIN = 0.85  # … or at least this share of it (_filled_places)
NO_NARROWING_WRIST = 1.3  # least wrist distance (palm radii) from the palm centre when nothing narrows sharply
TAPER_WINDOW_R = 0.4  # … and how far (palm radii) a slow taper must stop falling for its end to be the wrist …
TAPER_MIN_SAMPLES = 4  # … and over at least this many samples (_end_of_taper's window)
ARM_REACH_R = 4.5  # a part leaving the palm farther than this many palm radii from its centre is no finger
SURE_ARM_REACH_R = 8.0  # a part leaving the palm farther than this is an arm even when it crosses the finger ring in pieces
OPPOSITE_ARM_REACH_R = 2.6  # a wide part opposite the fingers is an arm when it reaches at least this far
ARM_BEND_DEG = 10.0  # the arm's own direction sets the cut when it is this far off the palm centre's (see cut_forearm)
ARM_LENGTH_PALMS = 3.5  # an object longer than this many palm widths is a hand with its arm
FINGER_MAX_M = 0.035  # parts narrower than this are finger-like (fingers of 0.8-1.5x hands: 14-27 mm; a forearm 30-70 mm)
FINGER_MIN_AREA_M2 = 1.5e-4  # a finger-like part is at least this big (a finger's last 1-2 cm; outline noise is smaller) …
TOUCH_PX = 3  # another surface this close in the image (sensor shadows between them are 1-3 px) …
TOUCH_M = 0.02  # … and in depth joins the hand's region there …
TOUCH_AREA_M2 = 0.0015  # … when it is this big near the hand (a table, the body; shading specks are smaller)
TOUCH_WINDOW_M = 0.06  # how far around the hand that size is measured
FINGER_ELONGATION = 2.5  # … at least this many times longer than wide (rendered and real fingers: 3.4-7) …
FINGER_MIN_LENGTH_M = 0.025  # … and this long (4 standard deviations along it)
FINGER_RIM_M = 0.003  # … counted from this far off the rest of the shape (_finger_pieces)
FINE_FINGER_M = 0.015  # a full-resolution pixel belongs to its coarse pixel's surface within this depth (_has_fingers)
FINE_FINGER_GROW = 1  # … and, when none are found there, this many coarse pixels beyond the surface too (fragments)
FRONT_WINDOW_M = 0.08  # a pixel's local background is the farthest depth this close (> half a 1.5x hand's palm width)
FRONT_STEP_M = 0.01  # the hand's layer is nearer than its local background by more than this
FRONT_OUTLINE_SHARE = 0.3  # … the region lies behind it across that step over this share of its outline (hand and arm alone, or the table scenes: ≤ 0.22 with colour; a torso 3-5 cm behind: 0.27-0.95)
FRONT_BEHIND_AREA_M2 = 0.035  # … and the region behind it is bigger than any hand (1.5x: 0.027 m²; a torso within reach: 0.04-0.1)
# depth only, when the nearest whole surface has no fingers: the surfaces tried instead, at most this many,
# whose nearest part lies within this depth of its own (the rendered boxes: 5 mm; a torso 18 cm behind a
# fist, split by the arm's shadow into finger-like strips, was taken) and no bigger than a hand with its
# forearm (rendered 1x: 0.02 m²; that torso's visible part 0.09)
FINGERS_FIRST_TRIES, FINGERS_FIRST_M, FINGERS_FIRST_MAX_AREA_M2 = 4, 0.1, 0.06
BORDER_PX = 12  # a seed this close to the image border counts as cut off by it (sensors leave the last pixels empty)


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

    def __post_init__(self):
        if self.forearm not in FOREARM_CHOICES:
            raise ValueError(f"forearm must be one of {', '.join(FOREARM_CHOICES)}, got {self.forearm!r}")
        if self.plane not in PLANE_CHOICES:
            raise ValueError(f"plane must be one of {', '.join(PLANE_CHOICES)}, got {self.plane!r}")
        if not self.z_max > self.z_min:
            raise ValueError(f"depth range must have far > near, got {self.z_min}, {self.z_max}")

    def __call__(self, depth, color=None, points=None, *, focal=None, plane=FIND, prefer=None):
        """Boolean hand mask ``(H, W)`` for a depth image in metres (NaN = no data).

        ``points``: the back-projected ``(H, W, 3)`` image (needed for ``box``); ``focal``: the
        camera's focal length in pixels (for physical areas; read from ``points`` if None, else
        :data:`DEFAULT_FOCAL_PX`); ``plane``: this frame's :meth:`frame_plane` when the caller has it
        already (found here otherwise); ``prefer``: a ``(rows, cols)`` slice pair where the hand is
        expected (the tracker's prediction): the wrist cut's palm is looked for there first
        (:func:`cut_forearm`; an arm stub as wide as a half-closed hand's palm, farther from where the
        region goes on, took the palm and the hand was cut off as the arm: the realistic Kinect v1 1.0×
        table scene, noise seed 2, frame 22, lost for the rest of its run)."""
        d, f = self._inputs(depth, points, focal)
        return self._run(d, color, points, f, plane=self.frame_plane(d, color, focal=f) if plane is FIND else plane,
                         prefer=prefer)

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
        result is refused when the mask is empty, when it comes within :data:`BORDER_PX` of a window
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
        # snapped to twice the coarse step: the window's coarse pixels are then the whole frame's, and
        # so is refine's rounding of pixel / step to the nearest coarse pixel (halves go to even)
        g = 2 * max(int(self.coarse), 1)
        (y0, y1), (x0, x1) = ((max(int(s.start or 0), 0) // g * g, min(int(n if s.stop is None else s.stop), n))
                              for s, n in zip(window, (H, W)))
        if y1 - y0 < 2 or x1 - x0 < 2:
            return None
        win = (slice(y0, y1), slice(x0, x1))
        notes = {}
        sub = self._run(d[win], None if color is None else np.asarray(color)[win],
                        None if points is None else np.asarray(points)[win], f, (y0, x0), (H, W),
                        plane=self.frame_plane(d, color, focal=f) if plane is FIND else plane, notes=notes,
                        prefer=expected, in_window=True)
        if not sub.any() or notes.get("layered"):
            return None
        (ya, yb), (xa, xb) = bounds(sub)
        h, w = sub.shape
        if ((y0 > 0 and ya < BORDER_PX) or (y1 < H and yb >= h - BORDER_PX)
                or (x0 > 0 and xa < BORDER_PX) or (x1 < W and xb >= w - BORDER_PX)):
            return None
        if expected is not None:
            cy, cx = (float(v.mean()) + o for v, o in zip(np.nonzero(sub), (y0, x0)))
            (ey, ex) = expected
            if not ((ey.start or 0) <= cy < (H if ey.stop is None else ey.stop)
                    and (ex.start or 0) <= cx < (W if ex.stop is None else ex.stop)):
                return None
        out = np.zeros((H, W), bool)
        out[win] = sub
        return out

    def _run(self, d, color, points, f, origin=(0, 0), whole_shape=None, plane=None, notes=None, prefer=None,
             in_window=False):
        """The mask of ``d``: the whole frame, or the window of a frame of ``whole_shape`` whose
        first pixel is ``origin`` (the search then runs on the whole frame's pixels, with its
        principal point); ``plane``: the whole frame's :class:`SupportPlane` to leave out, or None;
        ``notes``: a dict :meth:`_segment` fills in; ``prefer``: as for :meth:`__call__` (the whole
        frame's pixels); ``in_window``: ``d`` is :meth:`in_window`'s window and ``prefer`` the hand
        predicted in it (:func:`hand_region`'s ``expected``)."""
        c = int(self.coarse)
        H, W = whole_shape or d.shape
        (y0, x0) = origin
        if c <= 1 or min(H, W) < 40 * c:
            return self._segment(d, color, points, f, centre=((H - 1) / 2 - y0, (W - 1) / 2 - x0), plane=plane,
                                 notes=notes, prefer=_sampled(prefer, origin, 1), in_window=in_window)
        # the search runs on every c-th pixel (c² times fewer pixels), the edges are then
        # refined at full resolution in the hand's window only
        sub = (slice(None, None, c), slice(None, None, c))
        dc = d[sub]
        mc = self._segment(dc, None if color is None else np.asarray(color)[sub],
                           None if points is None else np.asarray(points)[sub], f / c, c,
                           centre=((-(-H // c) - 1) / 2 - y0 / c, (-(-W // c) - 1) / 2 - x0 / c), plane=plane,
                           full=d, notes=notes, prefer=_sampled(prefer, origin, c), in_window=in_window)
        if not mc.any():
            return np.zeros(d.shape, bool)
        out, win = refine(mc, dc, d, c, self.jump)
        out[win] &= self._valid(d[win], None if color is None else np.asarray(color)[win],
                                None if points is None else np.asarray(points)[win], skin_only=False, plane=plane,
                                at=(f, (H - 1) / 2 - y0 - win[0].start, (W - 1) / 2 - x0 - win[1].start))
        return out

    def _valid(self, d, color, points, skin_only=True, plane=None, at=None):
        """The working volume's pixels of ``d``, skin-coloured ones only with a colour frame, those off
        ``plane`` (a :class:`SupportPlane`) when given; ``at``: ``(focal, cy, cx)`` of ``d``'s pixels."""
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

    def _segment(self, d, color, points, f, step=1, centre=None, plane=None, full=None, notes=None, prefer=None,
                 in_window=False):
        """The search on an image subsampled by ``step`` (pixel counts and distances scale);
        ``centre``: the principal point in its pixel coordinates (None: the image's centre);
        ``plane``: a :class:`SupportPlane` left out as the skin test leaves pixels out; ``full``: the
        full-resolution depth ``d`` was sampled from (a farther surface's fingers are looked for there
        too, :func:`_has_fingers`); ``notes``: a dict that gets ``"layered"`` when the region stands in
        front of a surface close behind it (:func:`_in_front`); ``in_window``: ``d`` is a window and
        ``prefer`` the hand predicted in it (:func:`hand_region`'s ``expected``)."""
        if centre is None:
            centre = ((d.shape[0] - 1) / 2, (d.shape[1] - 1) / 2)
        valid = self._valid(d, color, points, plane=plane, at=(f, *centre))
        if not valid.any():
            return valid
        dv = np.where(valid, d, np.nan)
        # the frame before the skin filter (and the plane): where a table or the body meets the hand,
        # the arm goes on
        filtered = self._skin(color) or plane is not None
        d_all = np.where(self._valid(d, None, points), d, np.nan) if filtered else dv
        mask, beyond = hand_region(dv, f, band=self.band, jump=self.jump,
                           min_pixels=max(self.min_pixels // step ** 2, 1), min_area=self.min_area,
                           margin_px=int(np.ceil(self.margin_px / step)), blob_area=self.blob_area,
                           reach=self.reach, points=points, border_px=int(np.ceil(BORDER_PX / step)),
                           with_beyond=True, centre=centre, fingers_first=not self._skin(color),
                           fine=None if full is None or step <= 1 else (full, step), notes=notes,
                           expected=prefer if in_window else None)
        beyond, seed, behind = beyond
        if self.forearm == "cut" and mask.any():
            # where a table or the body meets the hand at its depth (seen before the skin filter)
            joins = _joins(mask, dv, mask | beyond | behind, d_all, f, jump=self.jump)
            mask = cut_forearm(mask, dv, f, beyond, seed=seed, joins=joins, prefer=prefer)
        return mask


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


@dataclass(frozen=True)
class SupportPlane:
    """A plane ``normal · x = offset`` (camera frame, metres; ``normal`` unit) that covers ``area`` m²
    of the frame, and the ``band`` (m) around it whose pixels :meth:`pixels` gives."""

    normal: tuple
    offset: float
    band: float
    area: float

    def pixels(self, depth, focal, cy, cx) -> np.ndarray:
        """Boolean ``(H, W)``: the pixels of ``depth`` (metres, NaN = none; principal point ``cy, cx``
        in its pixels) within ``band`` of the plane."""
        nx, ny, nz = self.normal
        return plane_pixels(np.ascontiguousarray(depth, dtype=np.float64), float(nx), float(ny), float(nz),
                            float(self.offset), float(focal), float(cy), float(cx), float(self.band))


def support_plane(depth, focal, *, z_min=0.2, z_max=1.5, min_area=PLANE_MIN_AREA_M2, min_tilt_deg=PLANE_MIN_TILT_DEG,
                  seed=0):
    """The largest plane of the depth frame (metres, NaN = none) seen at least ``min_tilt_deg`` off
    face-on (a table or floor; not a wall or torso facing the camera), as a :class:`SupportPlane`, or
    None when none covers ``min_area`` m² (fronto-parallel pixel areas, so a tilted table counts low).

    RANSAC on about :data:`PLANE_SAMPLES` pixels of a grid over the frame (principal point at the
    image centre, as the segmenter's back-projection): :data:`PLANE_TRIES` planes through three
    samples (drawn with ``seed``: the same frame gives the same plane), each weighed by the area of
    the samples within :data:`PLANE_TOL_M`; the best one is refitted to its samples by least squares
    (twice), and its band is 3 robust standard deviations of their distances, within
    :data:`PLANE_BAND_M`. A hand is never the plane: 0.01–0.03 m².

    >>> v, u = np.mgrid[0:240, 0:320]
    >>> table = 0.6 / (0.6 * (v - 119.5) / 300.0 + 0.8) + 0 * u   # the plane (0, 0.6, 0.8) · x = 0.6
    >>> table[100:140, 150:180] = 0.45                               # something standing in front of it
    >>> p = support_plane(table, 300.0)
    >>> (np.round(p.normal, 3) + 0.0).tolist(), round(p.offset, 3), p.band
    ([0.0, 0.6, 0.8], 0.6, 0.008)
    >>> on = p.pixels(table, 300.0, 119.5, 159.5)
    >>> int(on.sum()), bool(on[120, 160])
    (75600, False)
    """
    d = np.ascontiguousarray(depth, dtype=np.float64)
    H, W = d.shape
    step = max(int(round(np.sqrt(H * W / PLANE_SAMPLES))), 1)
    # compiled: the segmenter runs it on every frame without colour
    P, w = plane_samples(d, step, float(focal), (H - 1) / 2, (W - 1) / 2, float(z_min), float(z_max))
    if len(P) < 3 or w.sum() < min_area:
        return None
    tries = np.random.default_rng(seed).integers(0, len(P), size=(PLANE_TRIES, 3))
    max_cos = float(np.cos(np.radians(min_tilt_deg)))
    n, dn, got = plane_ransac(P, w, tries, PLANE_TOL_M, PLANE_PREEMPT, PLANE_KEEP, max_cos)
    if got < min_area:
        return None
    for _ in range(2):
        n, dn, area, mad, c = plane_refit(P, w, n, dn, PLANE_TOL_M)
    # seen obliquely from the camera (the triplets were; the refitted plane must be too)
    if area < min_area or abs(float(n @ c)) > max_cos * float(np.linalg.norm(c)):
        return None
    sd = 1.4826 * mad
    band = float(np.clip(3.0 * sd, *PLANE_BAND_M))
    if dn < 0:  # the camera on the normal's negative side: what stands in front has normal · x < offset
        n, dn = -n, -dn
    return SupportPlane(tuple(float(x) + 0.0 for x in n), float(dn), band, float(area))


def in_box(points, box_min=None, box_max=None) -> np.ndarray:
    """Boolean ``(...)``: points ``(..., 3)`` inside the axis-aligned box (bounds inclusive; None, a None
    entry or ±inf = open; NaN points are outside)."""
    p = np.asarray(points, float)
    lo = np.array([-np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_min, object), 3)], float)
    hi = np.array([np.inf if v is None else v for v in np.broadcast_to(np.asarray(box_max, object), 3)], float)
    with np.errstate(invalid="ignore"):
        return np.all((p >= lo) & (p <= hi), axis=-1)


def skin_mask(color):
    """Pixels inside the skin HSV range (colour ``(H, W, 3)`` uint8 RGB).

    V is the largest channel and S the channel spread over it, so both bounds are tested in
    integers on the channels; the hue is computed only when its range is not the whole circle
    (htrack's is), which makes this several times faster than a full HSV conversion.

    >>> skin_mask(np.array([[[224, 172, 140], [40, 40, 40], [255, 255, 255]]], np.uint8)).tolist()
    [[True, False, False]]
    """
    c = np.asarray(color)
    (h0, s0, v0), (h1, s1, v1) = SKIN_HSV
    if h0 > 0 or h1 < 179:
        hsv = mcolors.rgb_to_hsv(c.astype(float) / 255.0)
        h, s, v = hsv[..., 0] * 179.0, hsv[..., 1] * 255.0, hsv[..., 2] * 255.0
        return (h >= h0) & (h <= h1) & (s >= s0) & (s <= s1) & (v >= v0) & (v <= v1)
    # S·255 >= s0 ⇔ (V − min)·255 >= s0 · V, in integers, compiled (twice a tracked frame)
    return skin_channels(np.ascontiguousarray(c, dtype=np.uint8), v0, v1, s0, s1)


def bounds(mask):
    """``((row_min, row_max), (col_min, col_max))`` of a non-empty boolean mask (inclusive). A window
    (the segmenter asks ~10 times a tracked frame) is scanned compiled
    (:func:`tracker._segment_kernels.mask_bounds`); a whole frame by numpy's vectorised ``any``, which
    reads it faster than a pixel-by-pixel scan (a 640 × 480 frame: 38 µs against 123 µs; a 150 × 150
    window: 14 µs against 8 µs)."""
    m = np.asarray(mask)
    if m.size > BOUNDS_SCAN_MAX_PIXELS:
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        return (int(rows[0]), int(rows[-1])), (int(cols[0]), int(cols[-1]))
    r0, r1, c0, c1 = mask_bounds(m if m.dtype == np.bool_ else m.astype(bool))
    if r0 < 0:
        raise ValueError("bounds of an empty mask")
    return (int(r0), int(r1)), (int(c0), int(c1))


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
        return ndimage.distance_transform_edt(~t)
    return dist


def _disk_opening(mask, rad):
    """``scipy.ndimage.binary_opening(mask, structure=disk)`` with the disk of offsets ``hypot ≤ rad`` (the
    outside counting as background, as scipy's has it), by two distance transforms: an erosion keeps the
    pixels farther than ``rad`` from the background, a dilation the pixels within ``rad`` of those. The
    same pixels; at a full-resolution image's finger widths (``rad`` ~11) ~10× faster than scipy's.

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


def _largest_in_window(mask):
    """:func:`largest_component`, labelling only the mask's bounding box."""
    out = np.zeros_like(mask)
    if mask.any():
        (y0, y1), (x0, x1) = bounds(mask)
        win = (slice(y0, y1 + 1), slice(x0, x1 + 1))
        out[win] = largest_component(mask[win])
    return out


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
    exactly 1/fx from one column to the next; :data:`DEFAULT_FOCAL_PX` when it cannot be read."""
    if points is None:
        return DEFAULT_FOCAL_PX
    P = np.asarray(points, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        step = np.nanmedian(np.diff(P[..., 0] / P[..., 2], axis=1)) if P.shape[1] > 1 else np.nan
    return float(1.0 / step) if np.isfinite(step) and step > 0 else DEFAULT_FOCAL_PX


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
    px = BORDER_PX if px is None else px
    return bool(mask[:px].any() or mask[-px:].any() or mask[:, :px].any() or mask[:, -px:].any())


def hand_region(depth, focal, band=0.12, jump=0.02, min_pixels=30, min_area=0.004, margin_px=25,
                blob_area=0.003, reach=0.22, points=None, border_px=None, with_beyond=False, centre=None,
                fingers_first=False, fine=None, notes=None, expected=None):
    """The hand's region before the wrist cut.

    The seed is the nearest part (within 15 mm of the front) of the nearest surface of at least
    ``min_area`` whose nearest part does not touch the image border (an object cut off by the
    border is a poorer guess than a whole one; it is taken only when nothing else is there). The
    region is that surface within ``band`` behind the front and within ``reach`` metres (3-D) of
    the seed's centre — the arm leads to the body, so the body is reached along it only beyond
    the reach of a hand — connected to the seed (when every candidate is cut off by the border,
    the seed is the end of the nearest one farthest from the border, see :func:`_far_end`), plus the small surfaces (fingertip blobs) in
    that band within ``margin_px`` pixels of it. With ``with_beyond``, ``(region, (beyond, seed, behind))``:
    also the pixels of the hand's surface left out by the band or the reach (where an arm leaves
    the region), the seed's pixels, and the pixels of a body close behind the hand along its
    outline (:func:`_in_front`; empty when there is none). ``fingers_first`` (depth only, where no skin
    test removed objects): when that whole surface has no fingers (:func:`_has_fingers`: a box or a mug
    nearer than the hand — or a fist) and a farther one's hand end has (:func:`_fingered_end`), the
    farther one is the hand; ``fine``: ``(depth, step)``, the full-resolution image ``depth`` was sampled
    from every ``step``-th pixel, where that farther surface's fingers are looked for too. ``notes``: a
    dict that gets ``"layered"`` from :func:`_in_front`. ``expected``: a ``(rows, cols)`` slice pair
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
        return (empty, (empty, empty, empty)) if with_beyond else empty
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
        others = [(kk, ff) for kk, ff in zip(ids, fronts) if kk != k and abs(ff - front) <= FINGERS_FIRST_M]
        for kk, ff in others[:FINGERS_FIRST_TRIES]:
            end, end_front = _fingered_end(lab == kk, d, ff, band, X, focal, border_px, reach, fine=fine)
            if end is not None and _reaches(end, expected):
                k, front, seed = int(kk), end_front, end
                break
    if not _touches_border(seed, border_px):
        seed, front = _hand_end(lab == k, d, front, band, seed, focal, border_px)
    if _touches_border(seed, border_px):
        # every candidate's nearest part is cut off by the border, typically an arm reaching
        # towards the camera from outside the image: the hand is then the end of the surface
        # farthest from where it enters the image
        X = _points(d, focal, centre) if points is None else np.asarray(points, float)
        seed, front = _far_end(lab == k, d, X, focal, border_px, reach)
    with np.errstate(invalid="ignore"):
        near = np.isfinite(d) & (d <= front + band) & (d >= front - band)
        if reach is not None:
            if X is None:
                X = _points(d, focal, centre) if points is None else np.asarray(points, float)
            centre = X[seed].mean(axis=0)
            near &= _sq_dist(X, centre) <= reach ** 2
    near |= seed
    core = (lab == k) & near
    core = components_holding(np.ascontiguousarray(core), np.ascontiguousarray(seed, dtype=np.bool_))
    # a body a few centimetres behind the hand, joined to it by the arm: the hand is the layer in front
    core, behind, seed = _in_front(core, d, seed, focal, jump, min_area, lab == k, border_px, notes)
    # small surfaces close to the hand in the image and in depth: fingertip blobs
    (ya, yb), (xa, xb) = bounds(core)
    y0, y1 = max(ya - margin_px, 0), min(yb + margin_px + 1, d.shape[0])
    x0, x1 = max(xa - margin_px, 0), min(xb + margin_px + 1, d.shape[1])
    win = (slice(y0, y1), slice(x0, x1))
    zone = _window_max(core[win], 2 * int(margin_px) + 1) if margin_px > 0 else core[win]
    cand = zone & near[win] & ~core[win] & (lab[win] > 0) & (lab[win] != k)
    out = core.copy()
    if cand.any():
        area = np.bincount(lab[win][near[win]], weights=pixel_area(d[win][near[win]], focal),
                           minlength=lab.max() + 1)
        small = np.unique(lab[win][cand])
        small = small[area[small] < blob_area]
        others = ids[ids != k]
        if small.size and others.size:
            small = small[~np.isin(small, _edge_pieces(lab[win], d[win], small, others, jump))]
        if small.size:
            out[win] |= np.isin(lab[win], small) & near[win]
    if with_beyond:
        # where the hand's surface goes on past the band or the reach: the arm, not a fingertip
        return out, ((lab == k) & ~out & ~behind, seed, behind)
    return out


def _edge_pieces(lab, d, small, others, jump, gap_px=EDGE_GAP_PX):
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
    big = np.isin(lab, others)
    size = 2 * int(gap_px) + 1
    with np.errstate(invalid="ignore"):
        lo = _window_min(np.where(big, d, np.inf), size)
        hi = _window_max(np.where(big, d, -np.inf), size)
        touch = np.isin(lab, small) & (d >= lo - jump) & (d <= hi + jump)
    return np.unique(lab[touch])


def _in_front(region, d, seed, focal, jump=0.02, min_area=0.004, surface=None, border_px=None, notes=None):
    """``(region, behind, seed)``: the layer of ``region`` in front of a surface it stands out of.

    Each pixel's local background is the grey closing of the region's depth (the farthest depth
    within :data:`FRONT_WINDOW_M`, then the nearest of those; no data ignored): a tilted body keeps
    its own depth, a hand or an arm narrower than the window takes the depth of the body around it.
    The pixels nearer than their background by more than :data:`FRONT_STEP_M` fall into pieces
    (neighbours closer than ``jump``); the largest, when it covers ``min_area`` (m²), is the layer in
    front (the seed may lie on flying pixels at the body's edge, which curves away). It replaces the region when the region's pixels
    next to it lie behind it by that step over at least :data:`FRONT_OUTLINE_SHARE` of its outline and
    the region behind it covers at least :data:`FRONT_BEHIND_AREA_M2` — a hand held in front of the
    body, which the arm joins to the hand's surface. A hand alone, with its arm or on its own, has no
    such layer (its outline borders no data, another surface or its own pixels at its own depth) and
    keeps its region, ``behind`` empty and ``seed`` unchanged. ``behind``: the surface's pixels outside
    the layer (the body, past the region's reach too) except where the hand's surface goes on
    (:func:`_goes_on`: an arm receding into the body meets it without a step across its width; a finger
    leaning back to within the step of the body does not go on, nor does a part beside it); ``seed``:
    the layer's part of the seed, or its nearest 15 mm, moved to the fingers' end when the layer is the
    hand with its whole forearm (:func:`_hand_end`, ``border_px`` as there; the arm then goes on at its
    other end). ``notes``: a dict whose ``"layered"`` is set True when the region stands in front of a
    surface over enough of its outline, whether or not that surface was big enough to be a body."""
    none = np.zeros(region.shape, bool)
    if not (region & seed).any():
        return region, none, seed
    (ya, yb), (xa, xb) = bounds(region)
    z = _nanmedian(d[seed])
    half = max(int(round(FRONT_WINDOW_M * focal / z)), 1)
    size = 2 * half + 1
    H, W = d.shape
    # the background is read from the whole surface around the region (the reach cuts the body off
    # beside a big hand's palm), the layer sought in the region only
    big = (slice(max(ya - half, 0), min(yb + half + 1, H)), slice(max(xa - half, 0), min(xb + half + 1, W)))
    back = region[big] if surface is None else (surface | region)[big]
    with np.errstate(invalid="ignore"):
        far = _window_max(np.where(back, d[big], -np.inf), size)
        far = _window_min(np.where(np.isfinite(far), far, np.inf), size)
    win = (slice(max(ya - 3, 0), min(yb + 4, H)), slice(max(xa - 3, 0), min(xb + 4, W)))
    far = far[win[0].start - big[0].start:win[0].stop - big[0].start, win[1].start - big[1].start:win[1].stop - big[1].start]
    dw = d[win]
    rw = region[win]
    with np.errstate(invalid="ignore"):
        front = rw & (dw < far - FRONT_STEP_M)
    if not front.any():
        return region, none, seed
    lab, n = surfaces(np.where(front, dw, np.nan), jump)
    if n == 0:
        return region, none, seed
    area = np.bincount(lab[lab > 0], weights=pixel_area(dw[lab > 0], focal), minlength=n + 1)
    area[0] = 0.0
    best = int(np.argmax(area))
    if area[best] < min_area:
        # no hand-sized layer: a thumb or knuckles nearer than the rest of the hand are no hand
        return region, none, seed
    layer = lab == best
    # the outline: pixels within 3 px of the layer, and how far behind its farthest pixel there each lies
    layer_far = _window_max(np.where(layer, dw, -np.inf), 7)
    ring = np.isfinite(layer_far) & ~layer & np.isfinite(dw)
    with np.errstate(invalid="ignore"):
        step = rw & ring & (dw - layer_far > FRONT_STEP_M)
    stands_out = step.sum() >= FRONT_OUTLINE_SHARE * ring.sum()
    if stands_out and notes is not None:
        notes["layered"] = True
    if not stands_out or pixel_area(dw[rw & ~layer], focal).sum() < FRONT_BEHIND_AREA_M2:
        return region, none, seed
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
    return out, behind, new_seed


def _goes_on(layer, contact, d, focal):
    """The pixels of ``contact`` (the region's pixels next to ``layer`` without a depth step) where the
    hand's surface goes on past the layer: beside the layer's wide part (an opening with a disk
    :data:`FINGER_MAX_M` across removes the fingers), in pieces spanning more than that (an arm receding
    into the body meets it across its width; a finger leaning back, lying along the palm or the thumb,
    meets it over a finger's width or along its length beside the wide part in a thin band)."""
    o = closed_filled(layer)
    px_m = focal / _nanmedian(d[layer])
    rad = max(int(round(0.5 * FINGER_MAX_M * px_m)), 1)
    wide = _disk_opening(o, rad)
    out = contact & _window_max(wide, 7)
    lab, n = _label(out, eight=True)
    if n == 0:
        return out
    span = np.array([0.0] + [np.hypot(a.stop - a.start, b.stop - b.start) for a, b in ndimage.find_objects(lab)])
    return (span >= FINGER_MAX_M * px_m)[lab] & out


def _joins(region, d, surface, depth_all, focal, px=None, dz=None, min_area=None, jump=0.02):
    """Pixels where another object meets ``region`` at its own depth: pixels of ``depth_all`` (the
    frame before the skin filter; NaN = no data) off the hand's ``surface``, within ``px`` pixels of
    the region and within ``dz`` metres of its nearest pixel's depth, whose surface (depth
    continuity, in a window :data:`TOUCH_WINDOW_M` around the region) covers at least ``min_area``
    m² — a table or the body, not the shading specks at the hand's outline that fail the skin test
    or the hand's own fingertip blobs."""
    px = TOUCH_PX if px is None else px
    dz = TOUCH_M if dz is None else dz
    min_area = TOUCH_AREA_M2 if min_area is None else min_area
    out = np.zeros(region.shape, bool)
    if not region.any():
        return out
    (ya, yb), (xa, xb) = bounds(region)
    H, W = region.shape
    z = _nanmedian(d[region])
    m = px + int(np.ceil(TOUCH_WINDOW_M * focal / z))
    win = (slice(max(ya - m, 0), min(yb + m + 1, H)), slice(max(xa - m, 0), min(xb + m + 1, W)))
    r = region[win]
    dist, iy, ix = _nearest(r)
    da = np.asarray(depth_all, float)[win]
    with np.errstate(invalid="ignore"):
        close = (dist <= px) & (np.abs(da - d[win][iy, ix]) <= dz)
    if not close.any():
        return out
    other = np.where(np.isfinite(da) & ~surface[win], da, np.nan)
    lab, n = surfaces(other, jump)
    if n == 0:
        return out
    on = lab > 0
    big = np.bincount(lab[on], weights=pixel_area(other[on], focal), minlength=n + 1) >= min_area
    big[0] = False
    out[win] = close & big[lab]
    return out


def _fingered_end(surface, d, front, band, X, focal, border_px=None, reach=0.22, fine=None):
    """``(seed, front)`` of ``surface``'s hand end when it has fingers (:func:`_has_fingers`) and the
    surface is no bigger than :data:`FINGERS_FIRST_MAX_AREA_M2`, else ``(None, nan)``: its far end from the border when its nearest part is cut off by it
    (:func:`_far_end`), else its end with the fingers (:func:`_hand_end`); ``fine``: as for
    :func:`_has_fingers`."""
    if float(pixel_area(d[surface], focal).sum()) > FINGERS_FIRST_MAX_AREA_M2:
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
    px = BORDER_PX if border_px is None else border_px
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
    reach the border and is longer than :data:`ARM_LENGTH_PALMS` palm widths (a hand with its arm,
    not a hand), the nearest part may be the arm's far end (an elbow held nearer the camera than
    the wrist). The hand is the end with the fingers: the parts narrower than
    :data:`FINGER_MAX_M` (a morphological opening removes them), clearly more of them on one
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
    obj[win] = np.isin(lab_o, hit[hit > 0])
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
    if t.max() - t.min() < ARM_LENGTH_PALMS * palm:
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
    if max(plus, minus) < FINGER_MIN_AREA_M2 * px_m ** 2 * 2 or max(plus, minus) < 3 * min(plus, minus):
        return seed, front
    half = np.zeros(d.shape, bool)
    half[win] = o & ((tt > 0) if plus > minus else (tt < 0)) & obj[win]
    zh = float(np.percentile(d[half], 1))
    with np.errstate(invalid="ignore"):
        new = _largest_in_window(half & (d <= zh + 0.015))
    return (new, zh) if new.any() else (seed, front)


def _finger_pieces(o, px_m):
    """``(labels, sizes, big)``: the pieces of the solid mask ``o`` narrower than
    :data:`FINGER_MAX_M` (a morphological opening with a disk that wide removes them; ``px_m``:
    pixels per metre at the mask's depth) and farther than :data:`FINGER_RIM_M` from what the opening
    keeps (measured: a 0.8× open hand beside a box, depth only, whose fingers the opening's rim joined
    into one U-shaped piece), their sizes (pixels, index 0 = none) and which are
    finger-sized (:data:`FINGER_MIN_AREA_M2`; noise at the outline leaves slivers a few pixels big)."""
    rad = max(int(round(0.5 * FINGER_MAX_M * px_m)), 1)
    rim = int(round(FINGER_RIM_M * px_m))
    # the pixels farther than the rim from the opened shape: the opening rounds off the palm's corners
    # and leaves a sliver along its edge that joins every finger into one U-shaped piece, no finger
    opened = _disk_opening(o, rad)
    thin = o & ~opened
    if rim > 0 and opened.any():
        thin &= _edt(opened) > rim
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
    big = ((size >= FINGER_MIN_AREA_M2 * px_m ** 2) & (major >= FINGER_ELONGATION ** 2 * minor)
           & (4.0 * np.sqrt(major) >= FINGER_MIN_LENGTH_M * px_m))
    big[0] = False
    return lab_t, size, big


def _enough_fingers(o, px_m) -> bool:
    """Whether the solid mask ``o`` (``px_m`` pixels per metre) has finger-like pieces
    (:func:`_finger_pieces`) of at least twice :data:`FINGER_MIN_AREA_M2` in all."""
    _, size, big = _finger_pieces(o, px_m)
    return bool(size[big].sum() >= 2 * FINGER_MIN_AREA_M2 * px_m ** 2)


def _has_fingers(surface, d, seed, focal, reach=0.22, fine=None):
    """Whether the part of ``surface`` within ``reach`` metres (in the image, at the seed's depth)
    of ``seed``'s centre has finger-like parts (:func:`_finger_pieces`) of at least twice
    :data:`FINGER_MIN_AREA_M2` in all. ``fine``: ``(depth, step)``, the full-resolution image ``d``
    was sampled from every ``step``-th pixel; when the part has no fingers in ``d`` they are looked for
    there too, in the part's pixels within :data:`FINE_FINGER_M` of the pixel they were sampled with,
    and then in the part grown by :data:`FINE_FINGER_GROW` coarse pixels, each within that of its
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
    yy, xx = np.mgrid[y0:y1, x0:x1]
    part = surface[y0:y1, x0:x1] & ((yy - cy) ** 2 + (xx - cx) ** 2 <= r * r)
    if not part.any():
        return False
    if _enough_fingers(closed_filled(np.ascontiguousarray(part, dtype=np.bool_)), px_m):
        return True
    if fine is None:
        return False
    full, c = fine
    fz = np.asarray(full, float)[y0 * c:y1 * c, x0 * c:x1 * c]
    h, w = fz.shape
    zc = np.repeat(np.repeat(d[y0:y1, x0:x1], c, 0), c, 1)[:h, :w]
    for grow in dict.fromkeys((0, FINE_FINGER_GROW)):
        if grow:
            # the part grown by coarse pixels, each at its nearest part pixel's depth: the sensor's
            # dropouts break a small hand's fingers into fragments the part's surface does not hold.
            # Only when the part alone has none: growing can also bridge two fingers (seed 1's frame)
            _, ny, nx = _nearest(part)
            zc = np.repeat(np.repeat(d[y0:y1, x0:x1][ny, nx], c, 0), c, 1)[:h, :w]
        up = np.repeat(np.repeat(_dilate(part, grow) if grow else part, c, 0), c, 1)[:h, :w]
        with np.errstate(invalid="ignore"):
            fpart = up & (np.abs(fz - zc) <= FINE_FINGER_M)
        # holes filled but gaps not closed: closing would join the fingers again
        if _enough_fingers(ndimage.binary_fill_holes(fpart), px_m * c):
            return True
    return False


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
    than a finger (:data:`FINGER_MAX_M`; ``m_px``: metres per pixel) and lies opposite the parts
    ``fingers`` that end in the region (:func:`_opposite_fingers`)."""
    k = _widest_piece(owner, piece_size, j, r)
    # the ring is 0.4 r thick: a piece's area over that is its chord across the ring
    if k is None or piece_size[k] / (0.4 * r) * m_px <= FINGER_MAX_M:
        return False
    on_k = ring_lab == k
    return _opposite_fingers(vy[on_k].mean(), vx[on_k].mean(), width, cy_p, cx_p, fingers, r)


def cut_forearm(mask, depth, focal, beyond=None, palm_radius_m=(0.02, 0.07), wrist_range=(0.9, 2.6), seed=None,
                joins=None, prefer=None):
    """The hand mask without the forearm beyond the wrist.

    The palm is the largest inscribed circle of the region (centre c, radius r) — among circles
    nearly as large that the mask before closing fills nearly as well as the best-filled one
    (:func:`_filled_places`), the one farthest from where the region goes on. Outside 1.6 r, the
    parts that leave the circle are fingers or the forearm; the forearm is at least 0.45 r wide
    and goes on past the region — it reaches the image border or ``beyond`` (pixels of the same
    surface left out of the region), where fingers end in an edge (fingers held together are as
    wide as an arm). The widest such part is the forearm, its direction from c the arm axis a — or
    its own direction, from where it leaves the circle to its far end, when that is more than
    :data:`ARM_BEND_DEG` off (a wrist bent sideways puts c off the arm's axis). The
    region's width across a, measured at each distance t along a within ``wrist_range`` · r, is
    smallest at the wrist: the cut goes where it stops narrowing — where a slow taper ends when it
    narrows only slowly (over at least :data:`TAPER_MIN_SAMPLES` samples), and at least
    :data:`NO_NARROWING_WRIST` r out then — and everything beyond it
    in a strip of ±2.5 r around the axis is removed.
    Nothing is cut when the circle is not palm-sized (``palm_radius_m``) or no forearm leaves it.
    ``joins``: pixels where another object meets the region at its depth (:func:`_joins`); a part
    they touch goes on too (an arm entering a table the sensor's shadow separates from it); where
    nothing goes on past the region, a contact about a palm wide (the table where the skin test ends
    the arm) keeps the palm away from it as the arm's side would, a finger-wide one does not move the
    palm (fingertips touch the body as well). ``prefer``: a ``(rows, cols)`` slice
    pair where the hand is expected (the tracker's prediction): palm places inside it come first."""
    m = np.asarray(mask, bool)
    (ya, yb), (xa, xb) = bounds(m)
    pad = 2
    y0, x0 = max(ya - pad, 0), max(xa - pad, 0)
    y1, x1 = min(yb + pad + 1, m.shape[0]), min(xb + pad + 1, m.shape[1])
    sub = m[y0:y1, x0:x1]
    # close one-pixel no-data cracks and fill the holes the sensor leaves inside the hand (Kinect v1:
    # dropouts and shadows inside a fist) so that neither splits nor shrinks the palm circle: a
    # circle shrunk by a hole makes every finger reach "farther than a finger can" (an arm)
    solid = closed_filled(np.ascontiguousarray(sub))
    dt = _edt(~solid)
    # where the region goes on: the image border or the surface beyond it (the arm's side)
    go_on = np.zeros(sub.shape, bool)
    if beyond is not None:
        go_on |= _dilate(_outside_pieces(np.asarray(beyond, bool)[y0:y1, x0:x1], solid, 0.5 * float(dt.max())), 2)
    H, W = m.shape
    go_on[:, :1] |= x0 == 0
    go_on[:, -1:] |= x1 == W
    go_on[:1, :] |= y0 == 0
    go_on[-1:, :] |= y1 == H
    go_on &= solid
    # the palm: the widest place, and among places nearly as wide (a fist is hardly wider than a
    # forearm) and filled by the mask before closing, the one farthest from where the region goes on
    cand = _filled_places(dt >= PALM_WIDTH_SHARE * dt.max(), sub, float(dt.max()))
    if prefer is not None:
        # while tracking: an arm stub as wide as the palm, farther from where the region goes on, is no
        # palm when the hand was predicted elsewhere
        there = np.zeros(m.shape, bool)
        there[prefer] = True
        there = there[y0:y1, x0:x1] & cand
        if there.any():
            cand = there
    away = go_on
    if not go_on.any() and joins is not None:
        # nothing goes on past the region, but an object meets it along an arm's width (the table
        # where the skin test ends the arm): the palm is away from there too; a fingertip touching the
        # body meets it along a finger's width only and does not move the palm
        touch = _dilate(np.asarray(joins, bool)[y0:y1, x0:x1], 2) & solid
        tl, tn = _label(touch, eight=True)
        if tn:
            # a contact's size: its pixels in the band (the contact dilated by 2 px, inside the region)
            # over 5, against the widest place's radius: the band is 2-3 px deep, so this passes a
            # contact about a palm wide (an arm's) and not a finger wide one (a fingertip's)
            wide = np.flatnonzero(np.bincount(tl[tl > 0], minlength=tn + 1)[1:] / 5.0 >= float(dt.max())) + 1
            away = np.isin(tl, wide)
    if away.any():
        far = _edt(away)
        cy, cx = np.unravel_index(int(np.argmax(np.where(cand, far, -1.0))), dt.shape)
    elif seed is not None and np.asarray(seed, bool)[y0:y1, x0:x1].any():
        # nothing goes on (an arm ending in view): of the places nearly as wide, the one nearest
        # the hand's nearest part (a fist's knuckles face the camera, an arm's far end does not)
        near = _edt(np.asarray(seed, bool)[y0:y1, x0:x1])
        cy, cx = np.unravel_index(int(np.argmin(np.where(cand, near, np.inf))), dt.shape)
    else:
        cy, cx = np.unravel_index(int(np.argmax(dt)), dt.shape)
    r = float(dt[cy, cx])
    zc = _nanmedian(np.asarray(depth, float)[y0:y1, x0:x1][max(cy - 2, 0):cy + 3, max(cx - 2, 0):cx + 3])
    if not np.isfinite(zc):
        zc = _nanmedian(np.asarray(depth, float)[m])
    r_m = r * zc / focal
    if not (palm_radius_m[0] <= r_m <= palm_radius_m[1]):
        return m
    # offsets from the palm's centre as broadcast views (np.mgrid's full grids cost more than the math)
    vy, vx = np.broadcast_arrays(np.arange(sub.shape[0])[:, None] - cy, np.arange(sub.shape[1])[None, :] - cx)
    rho = np.hypot(vy, vx)
    outside = solid & (rho > 1.6 * r)
    lab, n = _label(outside, eight=True)
    if n == 0:
        return m
    idx = np.arange(1, n + 1)
    # a part's width where it leaves the palm (its chord across a ring 0.3 r wide), not its
    # widest place: an arm the region's reach cuts short is no wider inside the region than a finger
    base = (rho <= 1.9 * r) & (lab > 0)
    width = np.bincount(lab[base], minlength=n + 1)[1:] / (0.3 * r) / 2.0
    continues = np.zeros(n + 1, bool)
    continues[np.unique(lab[go_on & (lab > 0)])] = True
    if joins is not None:
        # a part another object meets at its depth goes on into it (an arm into a table or the
        # body); not used for the palm's place: fingertips touch the body too
        touch = _dilate(np.asarray(joins, bool)[y0:y1, x0:x1], 2) & solid
        continues[np.unique(lab[touch & (lab > 0)])] = True
    # a part reaching farther from the palm's centre than any finger can is an arm even where it
    # ends inside the region (a forearm seen end-on, or one cut off by a no-data gap)
    reach_r = label_max(rho, lab, n)
    continues[1:] |= reach_r > ARM_REACH_R * r
    # … and so is a wide part opposite the fingers (an arm receding from the camera, short in the image)
    nb = np.maximum(np.bincount(lab[base], minlength=n + 1)[1:], 1)
    cy_p = np.bincount(lab[base], weights=vy[base], minlength=n + 1)[1:] / nb
    cx_p = np.bincount(lab[base], weights=vx[base], minlength=n + 1)[1:] / nb
    # spread fingers cross a ring around the palm as several pieces, an arm as one: a part that
    # does is the fingers even where it reaches beyond the region (fingertips past the reach)
    ring_lab, _ = _label(outside & (rho >= 2.0 * r) & (rho <= 2.4 * r), eight=True)
    on = ring_lab > 0
    piece_size = np.bincount(ring_lab[on])
    big = np.flatnonzero(piece_size >= 0.05 * r * r)
    owner = np.zeros(piece_size.size, int)
    owner[ring_lab[on]] = lab[on]
    pieces = np.bincount(owner[big[big > 0]], minlength=n + 1)[1:]
    several = pieces >= 2
    for j in np.flatnonzero(several & continues[1:]):
        several[j] = not _arm_a_finger_touches(j, ring_lab, owner, piece_size, vy, vx, r, zc / focal, width,
                                               cy_p, cx_p, ~continues[1:] & ~several)
    continues[1:] &= ~several
    ends = ~continues[1:]
    for j in np.flatnonzero(ends & (width >= 0.45 * r) & (reach_r >= OPPOSITE_ARM_REACH_R * r)):
        # the other parts that end here, weighted by their width: the fingers' side of the palm
        # (at least a finger's width of them: noise specks at the outline are no fingers, and a hand
        # seen alone ends at its wrist in a stub that reaches less far than any visible forearm)
        others = ends.copy()
        others[j] = False
        # a part as wide as an arm that reaches less far than one is no finger to weigh: an arm stub the
        # region's reach cut short (in front of a body 4 cm behind) outweighed the fingers and put a group of
        # fingers "opposite the fingers"
        others &= ~((width >= 0.45 * r) & (reach_r < OPPOSITE_ARM_REACH_R * r))
        continues[j + 1] |= _opposite_fingers(cy_p[j], cx_p[j], width, cy_p, cx_p, others, r)
    # spread fingers stay fingers whichever rule called them an arm — unless the part reaches
    # farther than any hand: an arm whose thumb or finger touches it outside the palm circle
    # crosses the ring in pieces too
    continues[1:] &= ~several | (reach_r > SURE_ARM_REACH_R * r)
    width[~continues[1:]] = 0.0
    j = int(np.argmax(width))
    if width[j] < 0.45 * r:
        return m
    arm = lab == j + 1
    ring = arm & (rho < 2.6 * r)
    if pieces[j] >= 2:
        # an arm with a finger touching it: its direction is that of its widest piece on the ring
        ring = ring & _dilate(ring_lab == _widest_piece(owner, piece_size, j, r), 2)
    if not ring.any():
        ring = arm
    ay, ax = vy[ring].mean(), vx[ring].mean()
    norm = np.hypot(ay, ax)
    if norm == 0:
        return m
    ay, ax = ay / norm, ax / norm
    # the cut goes across the arm: its direction is the arm's own, from where it leaves the palm circle to
    # its far end in the region, when that is long enough to tell (half a palm radius) and more than
    # ARM_BEND_DEG off the direction from the palm's centre (a wrist bent sideways puts the centre off
    # the arm's axis: real frame 230536_70, 22°, where a cut across the centre's direction took a 648 px
    # triangle of the palm's heel); closer than that the two agree within their noise and the centre's,
    # the steadier one, is kept; beyond 60° the far end is no straight arm's
    leave = ring & (rho <= 2.4 * r) if pieces[j] >= 2 else arm & (rho <= 1.9 * r)
    far = arm & (rho >= float(rho[arm].max()) - 0.5 * r)
    if leave.any() and far.any():
        dy, dx = vy[far].mean() - vy[leave].mean(), vx[far].mean() - vx[leave].mean()
        n_arm = np.hypot(dy, dx)
        cos = (dy * ay + dx * ax) / max(n_arm, 1e-12)
        if n_arm >= 0.5 * r and 0.5 <= cos < np.cos(np.radians(ARM_BEND_DEG)):
            ay, ax = dy / n_arm, dx / n_arm
    t = vy * ay + vx * ax
    s = -vy * ax + vx * ay
    strip = solid & (np.abs(s) <= 2.5 * r)
    lo, hi = int(np.floor(wrist_range[0] * r)), int(np.ceil(wrist_range[1] * r))
    ti = np.round(t[strip]).astype(int)
    keep = (ti >= lo) & (ti <= hi)
    if not keep.any():
        return m
    prof = np.bincount(ti[keep] - lo, minlength=hi - lo + 1).astype(float)
    prof = ndimage.uniform_filter1d(prof, 5, mode="nearest")
    # the wrist is where the narrowing from the palm stops: the first distance beyond which the
    # width shrinks by less than 10 % over the next 0.3 r (a forearm further out may still taper,
    # recede or be cropped, so the global minimum would cut too late)
    i = _end_of_narrowing(prof, max(int(round(0.3 * r)), 2))
    if i > 0:
        t_w = lo + i
    else:
        # no sharp narrowing: a slow taper (a small hand at the coarse search's resolution, r ≈ 7 px,
        # narrows by less than a pixel a sample: the realistic ×0.8 SR305 scene's cut went ~1 cm into
        # the palm) ends where the width stops falling over TAPER_WINDOW_R; and the wrist lies at least
        # NO_NARROWING_WRIST r from the palm's centre (an arm as wide as the palm in the image, e.g. a
        # tilted palm; the rendered hand/forearm boundary lies at 1.17 r, median of ~1150 rendered frames,
        # but 1.2 r cut into the palm of realistic-scene frames the size is calibrated on: 0.977 -> 0.954)
        taper = _end_of_taper(prof, max(int(round(TAPER_WINDOW_R * r)), TAPER_MIN_SAMPLES))
        t_w = max(lo + taper, int(round(NO_NARROWING_WRIST * r)))
    cut = strip & (t > t_w)
    out = m.copy()
    out[y0:y1, x0:x1] &= ~cut
    return out



def _filled_places(cand, raw, rad, slack=PALM_FILL_SLACK, least=PALM_FILL_MIN):
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
    ys, xs = np.nonzero(cand)
    if ys.size < 2:
        return cand
    k = int(np.ceil(rad))
    dy, dx = np.nonzero(np.hypot(*np.mgrid[-k:k + 1, -k:k + 1]) <= rad)
    padded = np.pad(np.asarray(raw, bool), k)
    fill = padded[ys[:, None] + dy[None, :], xs[:, None] + dx[None, :]].mean(axis=1)
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
