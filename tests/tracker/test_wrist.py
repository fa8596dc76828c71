"""The wrist cue (tracker.wrist): on the 19 labelled real SR305 frames against the labelled wrist and
the labelled fingertips, and on rendered scenes against the rendered hand's wrist."""
from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from PIL import Image
from scipy import ndimage

from tests.conftest import shared
from tracker._silhouette_kernels import feature_transform
from tracker._wrist_kernels import (
    arm_entry,
    count_near,
    longest_line,
    near_line,
    outline_and_ring,
    seeded_surfaces,
    surface_depth,
    surface_past_outline,
)
from tracker.io.cameras import preset
from tracker.observe import observe
from tracker.segment import surfaces
from tracker.sim.motions import make_motion
from tracker.sim.render import render
from tracker.wrist import OUTLINE_SURFACE_PX, WristCue, wrist_cue

TIPS = ("thumb", "index", "middle", "ring", "pinky")


def _real_frames():
    labels = json.loads(shared("realsense_sr305_lada", "labels", "labels.json").read_text())
    return {k: v for k, v in labels.items() if isinstance(v, dict) and "wrist" in v}


def test_real_frames_cue_at_the_labelled_wrist_pointing_up_the_arm():
    """Defaults only: every labelled frame has a cue; its pixel is within 36 px of the labelled wrist
    on every frame and within 16 px on all but one (measured median 4.7 px; the one farther is a frame
    whose mask keeps ~35 px of forearm, so the cue sits where the mask ends), and the arm direction
    points from the fingertips to the wrist within 50° in the image (measured ≤ 49°, median 7°)."""
    cam = preset("sr305")
    errs, angles = [], []
    for name, lab in sorted(_real_frames().items()):
        units = np.asarray(Image.open(shared("realsense_sr305_lada", f"{name}.png")))
        depth = np.where(units > 0, units * cam.depth_scale_m, np.nan)
        cue = wrist_cue(observe(depth, cam).mask, depth, cam)
        assert cue is not None, name
        errs.append(float(np.hypot(*(cue.pixel - lab["wrist"]))))
        arm = np.asarray(lab["wrist"], float) - np.mean([lab[t] for t in TIPS], axis=0)
        d2 = cue.direction[:2]
        angles.append(np.degrees(np.arccos(d2 @ arm / np.linalg.norm(d2) / np.linalg.norm(arm))))
        assert 0.015 <= cue.width_m <= 0.12
    errs = np.array(errs)
    assert len(errs) == 19
    assert errs.max() <= 36 and np.sum(errs > 16) <= 1 and np.median(errs) <= 8, errs.round(1)
    assert max(angles) <= 50 and np.median(angles) <= 15, np.round(angles, 1)


@pytest.mark.parametrize("clutter", ["forearm", "forearm,torso=0.1"])
def test_rendered_forearm_cue_at_the_wrist(hand, clutter):
    """A rendered bare forearm: the cue lies within 25 mm of the model's wrist keypoint (the cut is at
    the wrist crease, the keypoint is the joint centre; measured 13–20 mm) and points along the arm,
    away from the middle finger's base, within 20° (measured ≤ 10°)."""
    cam = preset("kinect1")
    for th in make_motion("rotate", hand=hand, frames=30).theta[::6]:
        r = render(hand, th, cam, clutter=clutter)
        cue = wrist_cue(observe(r.depth, cam).mask, r.depth, cam)
        assert cue is not None
        kp = hand.keypoints(th)
        assert np.linalg.norm(cue.point - kp[0]) <= 0.025
        axis = (kp[0] - kp[9]) / np.linalg.norm(kp[0] - kp[9])
        assert axis @ cue.direction >= np.cos(np.radians(20))


def test_a_fringe_of_the_body_in_the_mask_is_no_wrist(hand, monkeypatch):
    """A 1.5x hand 4 cm in front of the body, SR305 noise, depth only (the realistic scene's seed 2,
    frames 3-12): flying pixels at the hand's edge bridge the segmentation's depth band, so a 1-2 px
    fringe of the body joins the mask. Its outline "went on" into the body: on frame 3 the cue lay at
    the notch between thumb and index, 65 px from the wrist crease, and the safety net replaced a
    6 mm track with a 72 mm fit (the run: 58 mm). Measured against the hand's surface behind the
    outline (the masked median, ``OUTLINE_SURFACE_PX``) every cue lies at the wrist (measured
    10-15 px from the rendered crease), and the fringe no longer hides the wrist line on frames
    4, 7 and 12."""
    import tracker.wrist as W
    from tests.conftest import realistic_frame
    from tracker.sim import experiments as E
    from tracker.sim.hands import HandShape

    shown = HandShape(1.5, E.realistic_fingers(1.5, 2)).apply(hand)
    truth = make_motion("open-close", hand=shown, frames=30, seed=2).theta
    noise_seed = 2 + list(E.REALISTIC_SCENES).index("+torso 4 cm")
    found, old = 0, {}
    for f in (3, 4, 7, 12):
        cam, depth, _, _ = realistic_frame(hand, "realsense", 1.5, "forearm,torso=0.04", f, noise_seed, seed=2)
        ob = observe(depth, cam)
        crease = cam.project(shown.wrist_crease(truth[f]))
        cue = wrist_cue(ob.silhouette, ob.frame_depth, cam)
        if cue is not None:
            found += 1
            assert np.hypot(*(cue.pixel - crease)) <= 20, (f, cue.pixel, crease)
        with monkeypatch.context() as mp:
            mp.setattr(W, "OUTLINE_SURFACE_PX", 0)  # the outline pixel's own depth, as before
            c0 = wrist_cue(ob.silhouette, ob.frame_depth, cam)
        old[f] = None if c0 is None else float(np.hypot(*(c0.pixel - crease)))
    assert found >= 3, found
    assert old[3] is not None and old[3] > 40, old  # the scene still shows what the rule is for


def test_no_arm_no_cue(hand):
    """A hand alone in space (our plain renderer) and an empty mask give no cue, never a guess."""
    cam = preset("kinect1")
    th = make_motion("open-close", hand=hand, frames=10).theta[5]
    r = render(hand, th, cam)
    assert wrist_cue(observe(r.depth, cam).mask, r.depth, cam) is None
    assert wrist_cue(np.zeros(cam.shape, bool), r.depth, cam) is None


# The wrist test's compiled pieces (tracker._wrist_kernels) against the scipy / numpy expressions they
# replace, on small random windows: depths from a few levels 5-100 mm apart (steps over and under the
# 15 mm jump, equal depths for the reattachment's ties) and holes.
_LEVELS = np.array([0.5, 0.505, 0.51, 0.53, 0.6, np.nan])


@st.composite
def _window(draw, max_side=14):
    h, w = draw(st.integers(1, max_side)), draw(st.integers(1, max_side))
    m = draw(arrays(bool, (h, w)))
    d = _LEVELS[draw(arrays(np.int8, (h, w), elements=st.integers(0, len(_LEVELS) - 1)))]
    return m, d


@given(_window())
@settings(max_examples=300, deadline=None)
def test_outline_and_ring_are_scipys_morphology(win):
    m, d = win
    inner, ring = outline_and_ring(m, d)
    np.testing.assert_array_equal(inner, m & ~ndimage.binary_erosion(m))
    np.testing.assert_array_equal(ring, ndimage.binary_dilation(m, iterations=2) & ~m & np.isfinite(d))


@given(_window(), st.sampled_from([0.0, 0.3, 0.5, 0.9]))
@settings(max_examples=300, deadline=None)
def test_longest_line_is_scipys_largest_label(win, share):
    goes_on = win[0]
    line, most = longest_line(goes_on, share)
    labels, n = ndimage.label(ndimage.binary_dilation(goes_on, iterations=3), structure=np.ones((3, 3)))
    if n == 0:
        assert not line.any() and not most
        return
    labels = np.where(goes_on, labels, 0)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    k = int(np.argmax(sizes)) + 1
    np.testing.assert_array_equal(line, labels == k)
    assert most == (not sizes[k - 1] < share * sizes.sum())


@given(_window(), _window())
@settings(max_examples=200, deadline=None)
def test_near_line_is_scipys_dilation(a, b):
    h, w = min(a[0].shape[0], b[0].shape[0]), min(a[0].shape[1], b[0].shape[1])
    inner, line = a[0][:h, :w], b[0][:h, :w]
    np.testing.assert_array_equal(near_line(inner, line), inner & ndimage.binary_dilation(line, iterations=2))


@given(_window(), st.integers(0, 6))
@settings(max_examples=400, deadline=None)
def test_seeded_surfaces_are_segment_surfaces_within_reach(win, reach):
    seed, d = win
    assume(seed.any())
    dist = np.empty(seed.shape)
    feature_transform(seed, dist, np.empty(seed.shape, np.int32), np.empty(seed.shape, np.int32))
    lab, _ = surfaces(d, jump=0.015)
    ids = np.unique(lab[seed])
    want = np.isin(lab, ids[ids > 0]) & (ndimage.distance_transform_edt(~seed) <= reach)
    np.testing.assert_array_equal(seeded_surfaces(d, seed, 0.015, float(reach), dist), want)


@given(_window(), st.integers(0, 3), st.integers(0, 3))
@settings(max_examples=200, deadline=None)
def test_surface_past_outline_is_the_ring_test(win, v0, u0):
    m, frame = win
    h, w = max(m.shape[0] - v0, 1), max(m.shape[1] - u0, 1)
    dist = np.empty((h, w))
    sub = m[v0:v0 + h, u0:u0 + w]
    if not sub.any():
        return
    feature_transform(np.ascontiguousarray(sub), dist, np.empty((h, w), np.int32), np.empty((h, w), np.int32))
    ring = (dist > 0) & (dist <= 2.0)
    assert surface_past_outline(dist, frame, v0, u0, 2.0) == bool(np.isfinite(frame[v0:v0 + h, u0:u0 + w][ring]).any())


@given(_window(), st.integers(0, 3), st.integers(0, 3))
@settings(max_examples=200, deadline=None)
def test_arm_entry_is_the_continuing_ring_by_scipy(win, v0, u0):
    """The pixels past the outline whose depth goes on from their nearest mask pixel's, by scipy's
    distance transform and its indices: their count and mean pixel."""
    m, frame = win
    h, w = max(m.shape[0] - v0, 1), max(m.shape[1] - u0, 1)
    sub = m[v0:v0 + h, u0:u0 + w]
    if not sub.any():
        return
    dist, iv, iu = np.empty((h, w)), np.empty((h, w), np.int32), np.empty((h, w), np.int32)
    feature_transform(np.ascontiguousarray(sub), dist, iv, iu)
    d_ref, (jv, ju) = ndimage.distance_transform_edt(~sub, return_indices=True)
    np.testing.assert_allclose(dist, d_ref)
    yy, xx = np.mgrid[:h, :w]  # each pixel's named mask pixel is a mask pixel at that distance
    assert sub[iv, iu].all() and np.allclose(np.hypot(yy - iv, xx - iu), dist)
    f = frame[v0:v0 + h, u0:u0 + w]
    with np.errstate(invalid="ignore"):
        # the nearest mask pixel of a tie may differ between the two: compare at the kernel's own
        goes_on = (dist > 0) & (dist <= 2.0) & (np.abs(f - f[iv, iu]) < 0.015)
    n, v, u = arm_entry(dist, iv, iu, frame, v0, u0, 2.0, 0.015)
    assert n == goes_on.sum()
    if n:
        yy, xx = np.nonzero(goes_on)
        assert v == pytest.approx(yy.mean() + v0) and u == pytest.approx(xx.mean() + u0)
    else:
        assert np.isnan(v) and np.isnan(u)


@given(_window(), st.integers(0, 4))
@settings(max_examples=300, deadline=None)
def test_surface_depth_is_the_masked_median_filter(win, r):
    m, d = win
    y, x = np.nonzero(np.ones_like(m))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        want = ndimage.generic_filter(np.where(m, d, np.nan), np.nanmedian, size=2 * r + 1, mode="constant",
                                      cval=np.nan)
    np.testing.assert_array_equal(surface_depth(m, d, y, x, r), want[y, x])


@given(_window(), st.floats(-3, 16), st.floats(-3, 16), st.floats(0, 9), st.sampled_from([0.5, 0.52, 0.6]))
@settings(max_examples=300, deadline=None)
def test_count_near_is_arm_behinds_disc(win, u, v, r, z):
    m, d = win
    h, w = m.shape
    y0, y1 = max(int(v - r), 0), min(int(np.ceil(v + r)) + 1, h)
    x0, x1 = max(int(u - r), 0), min(int(np.ceil(u + r)) + 1, w)
    assume(y0 < y1 and x0 < x1)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    with np.errstate(invalid="ignore"):
        want = (((yy - v) ** 2 + (xx - u) ** 2 <= r * r) & ~m[y0:y1, x0:x1] & (np.abs(d[y0:y1, x0:x1] - z) <= 0.05)).sum()
    assert count_near(m, d, y0, y1, x0, x1, u, v, r, z, 0.05) == want


def test_rendered_arm_cue_is_the_scipy_formula(hand):
    """On rendered forearm-and-torso frames under Kinect v1 and SR305 noise, the wrist cue with the
    compiled pieces equals the earlier scipy formula's, bit for bit (the window work is where the
    safety net's wrist test spent its ~1.5 ms a frame)."""
    from tracker.sim.noise import NoiseModel
    from tracker.sim.render import Clutter, DepthRenderer

    found = 0
    for sensor in ("kinect1", "sr305"):
        cam, noise = preset(sensor), NoiseModel.preset(sensor)
        truth = make_motion("open-close", hand=hand, frames=30).theta
        ren = DepthRenderer(hand, cam)
        clutter = Clutter.parse("forearm,torso").fixed(truth[:, :3].mean(axis=0))
        for f in range(0, 30, 6):
            r = ren.render(truth[f], labels=False, clutter=clutter, incidence=noise.needs_incidence,
                           reflectance=noise.needs_reflectance)
            depth = noise.apply(r.depth, cam, np.random.default_rng([0, f]), r.cos_incidence, r.reflectance)
            ob = observe(depth, cam)
            got, want = wrist_cue(ob.mask, ob.frame_depth, cam), _scipy_wrist_cue(ob.mask, ob.frame_depth, cam)
            assert (got is None) == (want is None), (sensor, f)
            if got is not None:
                found += 1
                for a, b in zip((got.point, got.pixel, got.direction, got.width_m),
                                (want.point, want.pixel, want.direction, want.width_m)):
                    np.testing.assert_array_equal(a, b)
    assert found >= 8, found


def _scipy_wrist_cue(full_m, full_d, camera, step_m=0.015, arm_reach_m=0.06, width_range_m=(0.015, 0.12),
                     min_arm_share=0.5):
    """:func:`tracker.wrist.wrist_cue` as it was before its window work was compiled (scipy's
    morphology, labels and distance transforms, :func:`tracker.segment.surfaces`)."""
    rows, cols = np.flatnonzero(full_m.any(1)), np.flatnonzero(full_m.any(0))
    if rows.size == 0:
        return None
    y0, y1 = max(rows[0] - 4, 0), min(rows[-1] + 5, full_m.shape[0])
    x0, x1 = max(cols[0] - 4, 0), min(cols[-1] + 5, full_m.shape[1])
    m, d = full_m[y0:y1, x0:x1], full_d[y0:y1, x0:x1]
    inner = m & ~ndimage.binary_erosion(m)
    ring = ndimage.binary_dilation(m, iterations=2) & ~m & np.isfinite(d)
    if not ring.any():
        return None
    near_inside = ndimage.distance_transform_edt(~inner, return_distances=False, return_indices=True)
    ry, rx = np.nonzero(ring)
    # the hand's surface at each outline pixel: the median masked depth in its 7 x 7 window
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        surface = ndimage.generic_filter(np.where(m, d, np.nan), np.nanmedian, size=2 * OUTLINE_SURFACE_PX + 1,
                                         mode="constant", cval=np.nan)
    ok = np.abs(d[ry, rx] - surface[near_inside[0][ring], near_inside[1][ring]]) < step_m
    goes_on = np.zeros_like(m)
    goes_on[ry[ok], rx[ok]] = True
    if not goes_on.any():
        return None
    labels, n = ndimage.label(ndimage.binary_dilation(goes_on, iterations=3), structure=np.ones((3, 3)))
    labels = np.where(goes_on, labels, 0)
    sizes = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    k = int(np.argmax(sizes)) + 1
    if sizes[k - 1] < min_arm_share * sizes.sum():
        return None
    line = labels == k
    fy, fx = np.nonzero(inner & ndimage.binary_dilation(line, iterations=2))
    if len(fy) < 3:
        return None
    z = d[fy, fx]
    P = np.stack([(fx + x0 - camera.cx) / camera.fx * z, (fy + y0 - camera.cy) / camera.fy * z, z], axis=1)
    P = P[np.isfinite(P).all(1)]
    if len(P) < 3:
        return None
    width = float(np.linalg.norm(P.max(0) - P.min(0)))
    if not width_range_m[0] <= width <= width_range_m[1]:
        return None
    centre = np.median(P, axis=0)
    reach = int(np.ceil(arm_reach_m * camera.fx / centre[2]))
    ly, lx = np.nonzero(line)
    ly, lx = ly + y0, lx + x0
    a0, a1 = max(ly.min() - reach, 0), min(ly.max() + reach + 1, full_m.shape[0])
    b0, b1 = max(lx.min() - reach, 0), min(lx.max() + reach + 1, full_m.shape[1])
    seed = np.zeros((a1 - a0, b1 - b0), bool)
    seed[ly - a0, lx - b0] = True
    dw = np.where(full_m[a0:a1, b0:b1], np.nan, full_d[a0:a1, b0:b1])
    lab, _ = surfaces(dw, jump=step_m)
    ids = np.unique(lab[seed])
    ay, ax = np.nonzero(np.isin(lab, ids[ids > 0]) & (ndimage.distance_transform_edt(~seed) <= reach))
    z = dw[ay, ax]
    A = np.stack([(ax + b0 - camera.cx) / camera.fx * z, (ay + a0 - camera.cy) / camera.fy * z, z], axis=1)
    A = A[np.linalg.norm(A - centre, axis=1) <= arm_reach_m]
    if len(A) < 3:
        return None
    v = A.mean(0) - centre
    if np.linalg.norm(v) < 1e-3:
        return None
    uv = np.array([camera.fx * centre[0] / centre[2] + camera.cx, camera.fy * centre[1] / centre[2] + camera.cy])
    return WristCue(centre, uv, v / np.linalg.norm(v), width)
