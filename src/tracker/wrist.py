"""Where the arm enters the hand: the wrist cue of a segmented depth frame.

A segmenter that cuts the forearm off leaves one stretch of the hand's outline where the surface goes
on at nearly the same depth outside the mask: the wrist line. Fingers end in a depth step or in no
data, so that stretch tells where the wrist is and which way the arm goes; the start search uses it to
rule out hands whose fingers point up the arm (:func:`tracker.init.score`).

>>> import numpy as np
>>> from types import SimpleNamespace
>>> cam = SimpleNamespace(fx=250.0, fy=250.0, cx=50.0, cy=50.0)
>>> depth = np.full((100, 100), np.nan)
>>> depth[20:60, 30:70] = 0.5            # a "palm"
>>> depth[60:100, 40:60] = 0.5           # the arm going on downwards
>>> mask = np.zeros((100, 100), bool); mask[20:60, 30:70] = True
>>> w = wrist_cue(mask, depth, cam)
>>> [round(float(v)) for v in w.pixel], [round(float(v), 2) for v in w.direction]
([50, 59], [0.0, 1.0, 0.0])
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._silhouette_kernels import feature_transform
from ._wrist_kernels import (
    BEHIND_CAMERA_TURNS,
    MIN_ARM_DIRECTION,
    MIN_DEPTH_M,
    MIN_FINGER_SPAN_M,
    MM,
    count_near,
    longest_line,
    near_line,
    outline_and_ring,
    seeded_surfaces,
    surface_depth,
)
from .segment import surfaces
from .segment.ops import _nearest

WRIST_REACH_MM = 50.0
WRIST_TURN_MM = 30.0
#: Half-width (px) of the window whose masked depths give an outline pixel's surface depth
#: (:func:`tracker._wrist_kernels.surface_depth`): wider than a 1–2 px fringe of the body.
OUTLINE_SURFACE_PX = 3


@dataclass(frozen=True)
class WristCue:
    """The wrist line's centre (``point``, camera frame, m; ``pixel`` (u, v)), the unit direction from
    the hand into the arm (``direction``, camera frame) and the line's length (``width_m``)."""

    point: np.ndarray
    pixel: np.ndarray
    direction: np.ndarray
    width_m: float


def wrist_cue(mask, depth, camera, *, step_m=0.015, arm_reach_m=0.06, width_range_m=(0.015, 0.12),
              min_arm_share=0.5) -> WristCue | None:
    """The wrist of a hand ``mask`` in a ``depth`` image (metres, NaN = none), or None.

    Outline pixels of the mask whose outside neighbours continue the surface (depth within
    ``step_m`` of the hand's surface there, the masked median within :data:`OUTLINE_SURFACE_PX`) form
    candidate lines; the longest is the wrist when it is wrist-wide
    (``width_range_m``) and holds at least ``min_arm_share`` of all such outline — a hand lying on a
    table or touching the body continues everywhere and gives no cue. The arm's direction is the
    mean of the continuing surface within ``arm_reach_m`` beyond the line, from the line's centre.
    """
    full_m = np.asarray(mask, bool)
    full_d = np.asarray(depth, float)
    if not full_m.any():
        return None
    # the outline work happens in the mask's window (a tenth of the frame or less)
    rows, cols = np.flatnonzero(full_m.any(1)), np.flatnonzero(full_m.any(0))
    y0, y1 = max(rows[0] - 4, 0), min(rows[-1] + 5, full_m.shape[0])
    x0, x1 = max(cols[0] - 4, 0), min(cols[-1] + 5, full_m.shape[1])
    m, d = full_m[y0:y1, x0:x1], full_d[y0:y1, x0:x1]
    cam = _Shifted(camera.fx, camera.fy, camera.cx - x0, camera.cy - y0)
    # the window's morphology compiled (scipy's calls cost mostly their overhead here)
    inner, ring = outline_and_ring(m, d)
    if not ring.any():
        return None
    # each outside ring pixel's nearest mask depth: the surface goes on when they agree
    _, near_y, near_x = _nearest(inner)
    iy, ix = near_y[ring], near_x[ring]
    ry, rx = np.nonzero(ring)
    # against the hand's surface behind the outline, the masked median around it: an outline pixel's
    # own depth can be the background's — flying pixels at a depth step bridge the segmentation's
    # band, and a fringe of a body close behind the hand joins the mask, whose outline then "goes
    # on" into the body (a cue at a notch of the hand; compiled, OUTLINE_SURFACE_PX)
    surface = np.full(m.shape, np.nan)
    oy, ox = np.nonzero(inner)
    surface[oy, ox] = surface_depth(m, d, oy, ox, OUTLINE_SURFACE_PX)
    dz = np.abs(d[ry, rx] - surface[iy, ix])
    goes_on = np.zeros_like(m)
    ok = dz < step_m
    goes_on[ry[ok], rx[ok]] = True
    if not goes_on.any():
        return None
    # pieces of one line a few pixels apart (no-data specks along the wrist) are one line
    line, most = longest_line(goes_on, min_arm_share)
    if not most:
        return None
    # the inside outline pixels that face the line: the wrist line on the hand
    face = near_line(inner, line)
    fy, fx = np.nonzero(face)
    if len(fy) < 3:
        return None
    P = _points(cam, fx, fy, d[fy, fx])
    P = P[np.isfinite(P).all(1)]
    if len(P) < 3:
        return None
    width = float(np.linalg.norm(P.max(0) - P.min(0)))
    if not width_range_m[0] <= width <= width_range_m[1]:
        return None
    centre = np.median(P, axis=0)
    # the arm: surface outside the mask reachable from the line without a depth step
    # the arm beyond the line, in the whole frame: it leaves the mask's window
    reach = int(np.ceil(arm_reach_m * camera.fx / centre[2]))
    ly, lx = np.nonzero(line)
    ly, lx = ly + y0, lx + x0
    a0, a1 = max(ly.min() - reach, 0), min(ly.max() + reach + 1, full_m.shape[0])
    b0, b1 = max(lx.min() - reach, 0), min(lx.max() + reach + 1, full_m.shape[1])
    seed = np.zeros((a1 - a0, b1 - b0), bool)
    seed[ly - a0, lx - b0] = True
    # the surfaces outside the hand (the hand itself blanked, so the arm cannot reach round through it)
    # that hold the line, within reach of it (compiled: tracker.segment.surfaces' surfaces, the exact
    # distance to the line)
    dw = np.where(full_m[a0:a1, b0:b1], np.nan, full_d[a0:a1, b0:b1])
    dist = np.empty(seed.shape)
    feature_transform(seed, dist, np.empty(seed.shape, np.int32), np.empty(seed.shape, np.int32))
    arm = seeded_surfaces(dw, seed, step_m, float(reach), dist)
    ay, ax = np.nonzero(arm)
    A = _points(camera, ax + b0, ay + a0, dw[ay, ax])
    A = A[np.linalg.norm(A - centre, axis=1) <= arm_reach_m]
    if len(A) < 3:
        return None
    v = A.mean(0) - centre
    if np.linalg.norm(v) < 1e-3:
        return None
    uv = np.array([camera.fx * centre[0] / centre[2] + camera.cx, camera.fy * centre[1] / centre[2] + camera.cy])
    return WristCue(centre, uv, v / np.linalg.norm(v), width)


def arm_behind(cue, mask, frame_depth, camera, *, reach_m=0.06, step_m=0.05, min_share=0.15) -> bool:
    """Whether an arm's worth of surface lies beyond the wrist ``cue``: the frame's pixels outside the
    hand ``mask`` within ``reach_m`` of the cue's centre and within ``step_m`` of its depth cover at
    least ``min_share`` of the area a forearm as wide as the wrist line would there (``width_m`` ×
    ``reach_m``). A few stray hand pixels the segmentation left outside the mask make a line of
    :func:`tracker.wrist.wrist_cue` too (measured on rendered hands without an arm: 15 pixels gave a
    2.5 cm "wrist" that cost the true pose 20–40 mm of score and sent the safety net's search to
    turned-over hands); an arm fills its area."""
    z = float(cue.point[2])
    r = reach_m * camera.fx / z
    h, w = mask.shape
    u, v = cue.pixel
    y0, y1 = max(int(v - r), 0), min(int(np.ceil(v + r)) + 1, h)
    x0, x1 = max(int(u - r), 0), min(int(np.ceil(u + r)) + 1, w)
    if y0 >= y1 or x0 >= x1:
        return False
    # counted in compiled code: the disc's pixels, off the hand, near the cue's depth
    near = count_near(np.asarray(mask, bool), np.asarray(frame_depth, float), y0, y1, x0, x1, float(u), float(v),
                      float(r), z, float(step_m))
    expected = (cue.width_m * camera.fx / z) * r
    return bool(near >= min_share * expected)


def arm_length_m(cue, mask, frame_depth, camera, *, reach_m=0.15, step_m=0.015, near_px=5) -> float:
    """How far (m, at most ``reach_m``) the surface beyond the wrist ``cue`` goes on: the largest
    distance from the cue's centre of the frame's surfaces outside the hand ``mask`` (split at depth
    steps over ``step_m``, :func:`tracker.segment.surfaces`) that touch the cue, within ``near_px``
    pixels of its pixel and ``2 × step_m`` of its depth.

    A forearm goes on for 20–25 cm; a piece of the hand the segmentation left outside its mask (a
    hand seen edge-on, cut as if it were an arm) ends within a finger's length. Measured: the rotate
    scenario's false cues (no arm rendered, cues that :func:`arm_behind` passes) 4–6 cm; the 19
    labelled SR305 frames' arms 17–60 cm.

    >>> from types import SimpleNamespace
    >>> cam = SimpleNamespace(fx=250.0, fy=250.0, cx=50.0, cy=50.0)
    >>> depth = np.full((100, 100), np.nan)
    >>> depth[20:60, 30:70] = 0.5
    >>> mask = np.zeros((100, 100), bool); mask[20:60, 30:70] = True
    >>> depth[60:100, 40:60] = 0.5          # an arm to the frame's edge: 8 cm at this depth
    >>> round(arm_length_m(wrist_cue(mask, depth, cam), mask, depth, cam), 2)
    0.08
    >>> depth[64:100] = np.nan              # a 4 cm wide stub, 8 mm long: its corners
    >>> round(arm_length_m(wrist_cue(mask, depth, cam), mask, depth, cam), 2)
    0.02
    """
    z = float(cue.point[2])
    if not z > 1e-3:
        return 0.0
    r = int(np.ceil(reach_m * camera.fx / z))
    h, w = mask.shape
    u, v = (int(round(float(c))) for c in cue.pixel)
    y0, y1, x0, x1 = max(v - r, 0), min(v + r + 1, h), max(u - r, 0), min(u + r + 1, w)
    if y0 >= y1 or x0 >= x1:
        return 0.0
    dw = np.where(mask[y0:y1, x0:x1], np.nan, frame_depth[y0:y1, x0:x1])
    lab, _ = surfaces(dw, jump=step_m)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    with np.errstate(invalid="ignore"):
        touch = (((yy - v) ** 2 + (xx - u) ** 2 <= near_px ** 2) & (np.abs(dw - z) <= 2 * step_m) & (lab > 0))
    ids = np.unique(lab[touch])
    if ids.size == 0:
        return 0.0
    ay, ax = np.nonzero(np.isin(lab, ids))
    A = _points(camera, ax + x0, ay + y0, dw[ay, ax])
    return float(min(np.linalg.norm(A - cue.point, axis=1).max(), reach_m))


def arm_line_normal(cue: WristCue) -> np.ndarray:
    """The unit normal of the plane through the camera centre and the arm's centre line (the line
    through the cue's point along its direction): a point's distance from that plane is how far it lies
    across the arm in the image, at its own depth. The middle of the wrist line lies on the arm's centre
    line by its definition; where the line ends along the arm depends on the segmenter's cut.

    >>> cue = WristCue(np.array([0.0, 0.0, 0.5]), np.zeros(2), np.array([0.0, 1.0, 0.0]), 0.05)
    >>> arm_line_normal(cue).round(3).tolist()  # the arm runs down the image: across it is ±x
    [-1.0, 0.0, 0.0]
    """
    n = np.cross(np.asarray(cue.point, float), np.asarray(cue.direction, float))
    return n / max(float(np.linalg.norm(n)), 1e-12)


@dataclass(frozen=True)
class _Shifted:
    fx: float
    fy: float
    cx: float
    cy: float


def _points(camera, u, v, z):
    u = np.asarray(u, float)
    v = np.asarray(v, float)
    return np.stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z], axis=1)


def wrist_cost_mm(cue: WristCue, hand, theta, *, reach_mm=WRIST_REACH_MM, turn_mm=WRIST_TURN_MM,
                  keypoints=None) -> float:
    """How far (mm) a hand at ``theta`` is from agreeing with the wrist ``cue``: its wrist keypoint
    farther than ``reach_mm`` from the cue's point costs the excess, and its fingers pointing up the
    arm in the image cost up to ``turn_mm`` (× the cosine between the hand's axis, wrist → middle
    base, and the arm's direction, both as seen in the image; nothing while they are 90° or more
    apart).

    The wrist bends up to ~80°, and a forearm receding from the camera says little about the hand's
    axis in depth, so only the image directions count, and only a hand folded back along its arm
    pays the full cost — an upside-down fit does. The reach is generous: the cue sits where the mask
    ends, which a mask that keeps a little forearm puts a few centimetres past the wrist joint
    (measured 13–20 mm on rendered arms, up to ~45 mm on a real frame); a hand behind the camera
    costs the most. ``keypoints``: ``hand.keypoints(theta)`` when the caller has them."""
    kp = hand.keypoints(np.asarray(theta, float)) if keypoints is None else keypoints
    # across the image only (at the cue's depth): the mask's end can lie on forearm receding from the
    # camera, centimetres behind the wrist joint, while where it is in the image is sharp
    w, p = kp[0], np.asarray(cue.point, float)
    if w[2] <= MIN_DEPTH_M:
        return reach_mm + BEHIND_CAMERA_TURNS * turn_mm
    far = float(np.hypot(w[0] / w[2] - p[0] / p[2], w[1] / w[2] - p[1] / p[2]) * p[2]) * MM
    cost = max(far - reach_mm, 0.0)
    arm = np.asarray(cue.direction[:2], float)
    fingers = (kp[9] - kp[0])[:2]
    na, nf = float(np.linalg.norm(arm)), float(np.linalg.norm(fingers))
    if na > MIN_ARM_DIRECTION and nf > MIN_FINGER_SPAN_M:
        cost += turn_mm * max(float(arm @ fingers) / (na * nf), 0.0)
    return cost


def ahead_of_wrist(points, wrist, middle_base, margin_m=0.0) -> np.ndarray:
    """Which ``points`` ``(N, 3)`` lie on the fingers' side of the plane through ``wrist`` across the
    hand's axis (``wrist`` → ``middle_base``, the middle finger's base), or at most ``margin_m`` behind it.

    >>> ahead_of_wrist(np.array([[0.0, 0.05, 0.5], [0.0, -0.05, 0.5]]), np.array([0.0, 0.0, 0.5]),
    ...                np.array([0.0, 0.08, 0.5]), 0.02).tolist()
    [True, False]
    """
    axis = np.asarray(middle_base, float) - np.asarray(wrist, float)
    axis /= max(float(np.linalg.norm(axis)), 1e-9)
    return (np.asarray(points, float) - wrist) @ axis >= -margin_m
