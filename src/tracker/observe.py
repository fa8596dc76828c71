"""Pipeline stage ``observe``: from a depth frame to what the tracker fits — the segmented hand's 3-D
points (every ``stride``-th pixel in x and y), their surface normals, and the silhouette.

Pixel (u, v) has its centre at integer coordinates: x = (u − cx)/fx · z, y = (v − cy)/fy · z (camera
frame: x right, y down, z forward, metres). "Stride K" keeps every K-th pixel in x and in y, starting
at pixel (0, 0): ``ceil(H/K)·ceil(W/K)`` pixels, about 1/K² of the image (the paper's "linear
subsampling 1/3" is K = 3 in the original code, i.e. 1/9 of the pixels).

>>> import numpy as np
>>> from types import SimpleNamespace
>>> cam = SimpleNamespace(fx=2.0, fy=2.0, cx=1.5, cy=1.0)
>>> backproject(np.full((3, 4), 2.0), cam)[0, 0].tolist()
[-1.5, -1.0, 2.0]
>>> kept_fraction((3, 4), 2)
0.3333333333333333
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ._observe_kernels import SMOOTH_MAX_DIFF_M, gate_kernel, observe_window
from ._segment_kernels import dropout_band_kernel
from .errors import TrackerError
from .segment import Segmenter, bounds
from .segment.buffers import FrameBuffers
from .settings_base import SettingsGroup


@dataclass(frozen=True)
class ObserveSettings(SettingsGroup):
    """How a frame becomes the hand's points (why each default: ``docs/tracker.md``).

    stride : every stride-th pixel in x and y (px; 3)
    target_points : the largest stride ≤ ``stride`` that keeps about this many points (None: ``stride``; 600)
    smooth : radius of the edge-preserving depth smoothing before sampling (px; 0 = off, the paper's; 1)
    normal_max_jump : depth step across which no normal is computed (m; 0.01)
    gate_mm : while tracking, points farther than this from the predicted hand are dropped
        (:func:`gate`; 0 = off; 30) …
    gate_min_share : … unless less than this share of the predicted surface has data that near (0.5)
    arm_gate_mm : points more than this past the predicted wrist are left out of the fit (:func:`past_wrist`;
        None = off; off without the safety net; 2)
    edge_px : pixels without depth this close to the mask count as hand in the silhouette
        (:func:`dropout_band`; 0 = the mask alone; 1)
    window_m : while tracking, the frame is segmented only in the predicted hand's image box grown by this
        (m; :func:`hand_window`; 0 = the whole frame; 0.08)
    """

    stride: int = 3
    target_points: int | None = 600
    smooth: int = 1
    normal_max_jump: float = 0.01
    gate_mm: float = 30.0
    gate_min_share: float = 0.5
    arm_gate_mm: float | None = 2.0
    edge_px: int = 1
    window_m: float = 0.08

    @classmethod
    def paper(cls):
        """Every 3rd pixel in x and y, no smoothing, no gate, the segmented mask alone."""
        return cls(stride=3, target_points=None, smooth=0, gate_mm=0.0, edge_px=0)

    def check(self):
        if self.stride < 1:
            raise TrackerError("observe.stride", f"must be positive, got {self.stride!r}")


def backproject(depth, camera):
    """Camera-frame points ``(H, W, 3)`` of a depth image in metres (NaN where no depth); any object with
    ``fx fy cx cy`` serves as the camera. float32 depth gives float32 points, anything else float64."""
    d = np.asarray(depth)
    dt = np.float32 if d.dtype == np.float32 else np.float64
    d = d.astype(dt, copy=False)
    H, W = d.shape
    out = np.empty((H, W, 3), dt)
    out[..., 0] = d * ((np.arange(W, dtype=dt) - camera.cx) / camera.fx)[None, :]
    out[..., 1] = d * ((np.arange(H, dtype=dt) - camera.cy) / camera.fy)[:, None]
    out[..., 2] = d
    return out


def kept_fraction(shape, stride: int) -> float:
    """Exact fraction of an image's pixels a stride keeps: ``ceil(H/K)·ceil(W/K) / (H·W)`` (≈ 1/K²)."""
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


def image_normals(X, max_jump=0.01):
    """Unit normals ``(H, W, 3)`` from central differences of back-projected points, oriented
    towards the camera; NaN where a neighbour is missing or a depth jump exceeds ``max_jump`` m."""
    dx = np.full_like(X, np.nan)
    dy = np.full_like(X, np.nan)
    dx[:, 1:-1] = X[:, 2:] - X[:, :-2]
    dy[1:-1] = X[2:] - X[:-2]
    with np.errstate(invalid="ignore"):
        bad = (np.abs(dx[..., 2]) > max_jump) | (np.abs(dy[..., 2]) > max_jump)
    n = np.cross(dx, dy)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-300
    n *= -np.sign(np.einsum("...i,...i->...", n, X))[..., None]
    n[bad] = np.nan
    return n


def smooth_depth(depth, radius=1, max_diff=0.01):
    """Edge-preserving smoothing: each pixel becomes the mean of the valid pixels in its
    (2r+1)² window whose depth is within ``max_diff`` m of its own (a cheap bilateral filter that
    averages sensor noise without blurring the hand into the background)."""
    d = np.asarray(depth, float)
    H, W = d.shape
    pad = np.pad(d, radius, constant_values=np.nan)
    acc = np.zeros_like(d)
    cnt = np.zeros_like(d)
    with np.errstate(invalid="ignore"):
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                nb = pad[radius + dy:radius + dy + H, radius + dx:radius + dx + W]
                ok = np.isfinite(nb) & (np.abs(nb - d) <= max_diff)
                acc += np.where(ok, nb, 0.0)
                cnt += ok
    out = np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan)
    out[~np.isfinite(d)] = np.nan
    return out


def dropout_band(mask, depth, width=1):
    """``(band, fill)``: the pixels without depth within ``width`` 4-connected steps of the hand
    ``mask`` (``(H, W)`` bool), and the depth (m) each is given, the nearest (smallest) depth of its
    neighbours one step nearer the hand (NaN elsewhere and where none has depth). ``depth``: the
    frame's depth, NaN where the sensor gave none.

    Depth sensors lose pixels along the hand's outline (Kinect v1: edge drop-outs two pixels deep,
    projector shadows one or two pixels wide beside each finger, silhouettes frayed by the lateral
    noise; :mod:`tracker.sim.noise`). A pixel without depth there is no evidence that the camera saw
    past the hand, but a silhouette term that counts it as background pulls the fingers' edges
    inwards every frame: under the Kinect v1 noise model (scenarios count and open-close), frames
    tracked from the previous frame's truth ended 2.3° and 2.7° off on average (up to 30° on a
    finger) with the band's pixels as background, 1.0° with a band of two pixels as hand, as with
    the silhouette term off. Pixels with depth that the segmentation left out (background, the
    forearm cut at the wrist) are never added.

    >>> m = np.zeros((1, 5), bool); m[0, 2] = True
    >>> d = np.array([[np.nan, np.nan, 0.5, np.nan, 0.9]])
    >>> band, fill = dropout_band(m, d, 2)
    >>> band.astype(int).tolist(), fill[0, :2].tolist()
    ([[1, 1, 0, 1, 0]], [0.5, 0.5])
    """
    m = np.ascontiguousarray(mask, dtype=np.bool_)
    d = np.ascontiguousarray(depth, dtype=np.float64)
    # one 4-connected ring per step, so a band pixel takes the depth of the ring inside it (compiled:
    # every tracked frame runs it; tests/tracker/test_observe.py checks it against the definition)
    band, fill = np.empty(m.shape, np.bool_), np.empty(m.shape)
    dropout_band_kernel(m, d, int(width), band, fill)
    return band, fill


@dataclass
class Observation:
    points: np.ndarray        # (N, 3) metres
    normals: np.ndarray       # (N, 3), NaN where unknown
    mask: np.ndarray          # (H, W) hand silhouette as segmented
    depth: np.ndarray         # (H, W) metres, the hand's pixels and the dropout band (NaN elsewhere)
    density: float            # share of silhouette pixels kept (≈ 1/stride²)
    stride: int = 1
    frame_depth: np.ndarray | None = None   # the whole frame it came from (the wrist cue looks past the mask)
    silhouette: np.ndarray | None = None    # (H, W) mask and its dropout band (:func:`dropout_band`): what
    #                                         the silhouette terms fit; None = the mask
    window: tuple | None = None             # the (rows, cols) slices segmented; None = the whole frame


def hand_window(points, camera, margin_m=0.08):
    """``(window, predicted)``: slice pairs ``(rows, cols)`` of the image box of the hand's points
    ``(N, 3)`` (camera frame; the hand predicted for the next frame), grown by ``margin_m`` metres at
    the points' nearest depth on every side (``window``, clipped to ``camera.height × camera.width``),
    and the box itself (``predicted``); None when no point lies in front of the camera.

    The margin is for two things: motion the prediction (constant velocity) misses, and the wrist
    cut, which reads the arm's width up to 2.6 palm radii from the palm's centre — about 5 cm past
    the wrist for a hand of the model's size, 7–8 cm for one 1.5 times as big — and the arm's
    direction from its far end, so the window must show that much of the arm (8 cm by measurement:
    with 6 cm the mask differed from the whole frame's on 4 of the 19 real frames, 2 of them farther
    from the labelled hand, by up to 476 px; with 8 cm on 3, each closer to it; the segmentation
    costs about the same).

    >>> from types import SimpleNamespace
    >>> cam = SimpleNamespace(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480)
    >>> hand_window(np.array([[0.0, 0.0, 0.5], [0.05, 0.1, 0.5]]), cam, 0.02)[0]
    (slice(220, 361, None), slice(300, 391, None))
    """
    P = np.asarray(points, float).reshape(-1, 3)
    P = P[np.isfinite(P).all(axis=1) & (P[:, 2] > 0)]
    if not len(P):
        return None
    u = P[:, 0] / P[:, 2] * camera.fx + camera.cx
    v = P[:, 1] / P[:, 2] * camera.fy + camera.cy
    z = float(P[:, 2].min())
    my, mx = int(np.ceil(margin_m * camera.fy / z)), int(np.ceil(margin_m * camera.fx / z))
    H, W = int(camera.height), int(camera.width)
    ya, yb = int(np.floor(v.min())), int(np.ceil(v.max())) + 1
    xa, xb = int(np.floor(u.min())), int(np.ceil(u.max())) + 1
    if yb + my <= 0 or xb + mx <= 0 or ya - my >= H or xa - mx >= W:
        return None
    window = (slice(max(ya - my, 0), min(yb + my, H)), slice(max(xa - mx, 0), min(xb + mx, W)))
    return window, (slice(ya, yb), slice(xa, xb))


def observe(depth, camera, settings: ObserveSettings | None = None, *, segmenter=None, color=None,
            window=None, **changes) -> Observation:
    """Segment the hand and sample its points.

    ``settings`` (:class:`ObserveSettings`) with any of its fields replaced by ``changes`` (e.g.
    ``observe(depth, camera, stride=1)``); ``segmenter``: a :class:`tracker.segment.Segmenter` (its
    defaults when None); ``color``: the registered colour frame, for skin segmentation. ``window``:
    ``(window, predicted)`` from :func:`hand_window` while tracking
    (:meth:`tracker.track.FrameTracker.segment_window`): the hand is segmented in ``window`` alone
    (:meth:`tracker.segment.Segmenter.in_window`), and in the whole frame when that result looks
    wrong (the hand runs out of the window, or is not where it was predicted);
    ``Observation.window`` says which was used."""
    st = settings or ObserveSettings()
    if changes:
        st = dataclasses.replace(st, **changes)
    seg = segmenter or Segmenter()
    # the frame, the mask, the depth and the silhouette are written to the segmenter's buffers
    # (reused when the caller holds no earlier observation's: Segmenter.buffers)
    bufs = getattr(seg, "buffers", None)
    if bufs is None:  # a segmenter of the caller's own (any callable with box_min/box_max): fresh arrays
        bufs = FrameBuffers()
    d = _float64(depth, bufs)
    H, W = d.shape
    # the segmenter needs the points only for a box; otherwise the back-projection, smoothing and
    # normals are computed in the hand's window alone (a tenth of the frame or less)
    boxed = seg.box_min is not None or seg.box_max is not None
    P = backproject(d, camera) if boxed else None
    focal = 0.5 * (camera.fx + camera.fy)
    mask, used, found = None, None, {}
    if window is not None:
        # the whole frame's plane once: a window refused falls back to the whole frame
        found["plane"] = seg.frame_plane(d, color, focal=focal)
        mask = seg.in_window(d, window[0], color, P, focal=focal, expected=window[1], **found)
        used = None if mask is None else window[0]
    if mask is None:
        # while tracking, the whole frame is told where the hand was predicted (Segmenter's prefer)
        mask = seg(d, color, P, focal=focal, prefer=None if window is None else window[1], **found)
    if not mask.any():
        return Observation(np.zeros((0, 3)), np.zeros((0, 3)), mask, np.full((H, W), np.nan), 0.0, int(st.stride), d)
    (ya, yb), (xa, xb) = bounds(mask)
    edge = max(int(st.edge_px), 0)
    pad = int(st.smooth) + 2 + edge
    y0, y1 = max(ya - pad, 0), min(yb + pad + 1, H)
    x0, x1 = max(xa - pad, 0), min(xb + pad + 1, W)
    dw = np.ascontiguousarray(d[y0:y1, x0:x1])
    mw = np.ascontiguousarray(mask[y0:y1, x0:x1], dtype=np.bool_)
    stride = int(st.stride)
    n_mask = int(mw.sum())
    if st.target_points:
        # np.clip(np.floor(np.sqrt(·)), 1, stride) in plain floats (the same correctly rounded root)
        stride = int(min(max(math.floor(math.sqrt(n_mask / float(st.target_points))), 1), stride))
    # one compiled pass (smooth_depth, backproject and image_normals, the last two at the kept pixels
    # only); the stride grid is anchored at the image's pixel (0, 0), not at the window's corner
    h, w = dw.shape
    cap = ((h + stride - 1) // stride) * ((w + stride - 1) // stride)
    dsm, pts, nrm = np.empty((h, w)), np.empty((cap, 3)), np.empty((cap, 3))
    k = observe_window(dw, mw, float(camera.fx), float(camera.fy), float(camera.cx - x0), float(camera.cy - y0),
                       int(st.smooth), SMOOTH_MAX_DIFF_M, float(st.normal_max_jump), stride, (-y0) % stride, (-x0) % stride,
                       dsm, pts, nrm)
    out_d = bufs.full("depth", (H, W), np.nan)
    np.copyto(out_d[y0:y1, x0:x1], dsm, where=mw)  # NaN off the mask already
    sil = mask
    if edge:
        band, fill = dropout_band(mw, dsm, edge)
        if band.any():
            sil = bufs.copy_of("silhouette", mask)
            sil[y0:y1, x0:x1] |= band
            np.copyto(out_d[y0:y1, x0:x1], fill, where=band)
    return Observation(pts[:k], nrm[:k], mask, out_d, float(k) / max(n_mask, 1), stride, d, sil, used)


def _float64(depth, buffers):
    """``np.asarray(depth, np.float64)``: the array itself when it is float64 already, else its values
    converted into one of ``buffers`` (:class:`tracker.segment.buffers.FrameBuffers`)."""
    a = np.asarray(depth)
    if a.dtype == np.float64:
        return a
    return buffers.copy_of("frame", a, np.float64)


def gate(points, predicted, radius=0.03, *, normals=None, min_share=0.5, min_points=30) -> np.ndarray:
    """Boolean ``(N,)``: the data ``points`` ``(N, 3)`` within ``radius`` m of the predicted hand's
    surface (``predicted``: ``(M, 3)`` model surface samples at the predicted pose,
    :meth:`tracker.correspond.ModelSamples.pose`).

    A table, torso, forearm or second object that the segmentation left next to the hand is then
    out of reach of the correspondences, however many of its points there are. Guard against a
    fast motion that the prediction missed: the prediction is trusted only when at least
    ``min_share`` of its surface samples have a data point within ``radius`` (the hand is where
    it was predicted; clutter cannot fake this, it only adds points) and at least ``min_points``
    points would remain; otherwise every point is kept (:func:`predicted_near` says which). NaN
    points are never near. With the samples' ``normals``, only samples facing the camera (at the
    origin) count: the camera sees the hand's near side, and a body close behind the hand stays out
    of the gate.

    >>> model = np.array([[0.0, 0.0, 0.5], [0.02, 0.0, 0.5]])
    >>> data = np.array([[0.0, 0.01, 0.5], [0.02, 0.0, 0.52], [0.3, 0.0, 0.5]])
    >>> gate(data, model, 0.03, min_points=1).tolist()
    [True, True, False]
    >>> gate(data, model + 0.2, 0.03, min_points=1).tolist()   # prediction far off: keep everything
    [True, True, True]
    """
    near = predicted_near(points, predicted, radius, normals=normals, min_share=min_share, min_points=min_points)
    return np.ones(len(np.reshape(points, (-1, 3))), bool) if near is None else near


def predicted_near(points, predicted, radius=0.03, *, normals=None, min_share=0.5, min_points=30):
    """:func:`gate`'s points near the predicted hand, or None when the prediction is not trusted.

    >>> model = np.array([[0.0, 0.0, 0.5], [0.02, 0.0, 0.5]])
    >>> predicted_near(np.array([[0.0, 0.01, 0.5]]), model + 0.2, 0.03, min_points=1) is None
    True
    """
    P = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    M = np.ascontiguousarray(predicted, dtype=np.float64).reshape(-1, 3)
    Mn = _NO_ROWS if normals is None else np.ascontiguousarray(normals, dtype=np.float64).reshape(-1, 3)
    near = np.empty(len(P), bool)
    # compiled (a grid instead of two KD-trees): the gate runs on every tracked frame
    if gate_kernel(P, M, Mn, normals is not None, float(radius), float(min_share), int(min_points), near):
        return near
    return None


def past_wrist(points, end, axis, margin=0.002) -> np.ndarray:
    """Boolean ``(N,)``: the ``points`` ``(N, 3)`` more than ``margin`` m past the hand's end toward
    the forearm. ``end``: where the hand's surface ends at the wrist (:meth:`handmodel.HandModel.wrist_crease`),
    ``axis``: the hand's direction from the wrist toward the fingers (the y axis of the root joint's
    frame, :meth:`handmodel.HandModel.joint_frames` ``[0]``); nothing of the hand lies beyond the plane
    through ``end`` normal to ``axis``. NaN points are never past.

    >>> past_wrist(np.array([[0.0, 0.05, 0.5], [0.0, -0.001, 0.5], [0.01, -0.03, 0.5]]),
    ...            end=np.array([0.0, 0.0, 0.5]), axis=np.array([0.0, 1.0, 0.0])).tolist()
    [False, False, True]
    """
    with np.errstate(invalid="ignore"):
        return (np.asarray(points, float).reshape(-1, 3) - np.asarray(end, float)) @ np.asarray(axis, float) \
            < -float(margin)


_NO_ROWS = np.zeros((0, 3))
