"""Tracking under the Kinect v1 noise model (tracker.sim.noise): the sensor's drop-outs along the
hand's outline must not pull the fit (tracker.observe.dropout_band)."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as hst

from tracker.io.cameras import preset
from tracker.observe import observe
from tracker.coupling import (BENT_BACK_DEG, COUPLING, bent_back, last_bones_points, recoupled, restart_uncoupled,
                              unbent, uncoupled)
from tracker.sim import experiments as E
from tracker.sim.motions import make_motion
from tracker.sim.noise import NoiseModel
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

CAM = preset("kinect1")
KINECT = NoiseModel.preset("kinect1")


def _open_close(hand, seed, **kw):
    """The first 36 frames of open-close (the hand opens and closes into a fist) under Kinect v1
    noise, tracked from the first frame in full DoF by the default tracker at the model's size."""
    truth = make_motion("open-close", hand=hand).theta[:36]
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(**kw))
    return E.run_sequence(hand, truth, CAM, tr, noise=KINECT, seed=seed)


@pytest.mark.parametrize("seed", [0, 1])
def test_closing_into_a_fist_under_kinect_noise_keeps_the_fingers(hand, seed):
    """The first 36 frames of open-close tracked from the first frame: every frame within 5°, the
    mean within 2.8° (measured 2.1° and 1.9°, seeds 0 and 1). Before the band, and before the
    silhouette pull kept the samples' depth (8093537), fingers folded into a wrong shape while
    closing and stayed there: 6.0° (56 % of frames ≤ 5°) and 3.1° (89 %)."""
    r = _open_close(hand, seed)
    e = np.nan_to_num(r.error_deg, nan=np.inf)
    assert e.max() <= 5.0 and e.mean() <= 2.8, (e.mean(), e.max())


def _from_truth(hand, name, frames, **kw):
    """Per frame and finger, the posture error (°, mean over the finger's 4 angles) of frames each
    tracked from the previous frame's truth (the prediction from the two before), Kinect v1 noise,
    safety net off: what one frame's data do to a right start."""
    truth = make_motion(name, hand=hand).theta[:frames]
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0), net=dict(enabled=False)).replace(**kw))
    ren = DepthRenderer(hand, CAM)
    post = ~hand.pose_mask
    out = []
    for f in range(len(truth)):
        depth = KINECT.apply(ren.render(truth[f], labels=False).depth, CAM, rng=np.random.default_rng([0, f]))
        ob = observe(depth, CAM, tr.settings.observe)
        if f >= 2:
            tr.theta, tr.prev, tr.lost = truth[f - 1].copy(), truth[f - 2].copy(), False
        r = tr.track(ob, CAM)
        out.append(np.degrees(np.abs(r.theta[post] - truth[f][post])).reshape(5, 4).mean(1))
    return np.array(out[2:])


def test_one_frame_from_the_truth_keeps_every_finger_with_the_band(hand):
    """Open-close frames 2–39, each from the previous frame's truth: with the dropout band no finger
    ends more than 6° off (measured 5.2°); with the sensor's missing edge pixels as background
    (edge_px=0) the silhouette term pulled the fingers' edges inwards and a finger ended 8.3° off
    (frames 18 and 34)."""
    on = _from_truth(hand, "open-close", 40)
    off = _from_truth(hand, "open-close", 40, observe=dict(edge_px=0))
    assert on.max() <= 6.0, on.max()
    assert off.max() > 7.0, off.max()


# ------------------------------------------------------------------ the fingers' coupling (tracker.coupling)
def test_uncoupled_and_recoupled_follow_the_coupling_line(hand):
    """A finger is flagged exactly when its last joint is beyond the tolerance from a × the joint
    before it + b (COUPLING, per finger); recoupled puts only the flagged fingers on the line, within
    the limits, and leaves every other DoF alone."""
    rng = np.random.default_rng(0)
    post = np.flatnonzero(~hand.pose_mask).reshape(5, 4)
    lim = np.asarray(hand.limits, float)
    for _ in range(50):
        th = np.zeros(hand.n_dofs)
        th[post] = rng.uniform(lim[post, 0], lim[post, 1])
        line = COUPLING[:, 0] * th[post[:, 2]] + np.radians(COUPLING[:, 1])
        off = np.degrees(np.abs(th[post[:, 3]] - line))
        flags = uncoupled(hand, th, 25.0)
        np.testing.assert_array_equal(flags, off > 25.0)
        out = recoupled(hand, th, flags, lim)
        k = post[flags, 3]
        np.testing.assert_allclose(out[k], np.clip(line[flags], lim[k, 0], lim[k, 1]))
        rest = np.setdiff1d(np.arange(hand.n_dofs), k)
        np.testing.assert_array_equal(out[rest], th[rest])


def test_restart_keeps_only_a_clearly_better_fit(hand):
    """The restart starts the refit from the recoupled θ and keeps its result only when it scores
    lower by more than gain_mm; a coupled fit is not refitted at all."""
    th = np.zeros(hand.n_dofs)
    idx = np.flatnonzero(~hand.pose_mask).reshape(5, 4)[1]
    th[idx[2]], th[idx[3]] = np.radians(-80.0), np.radians(30.0)
    starts = []

    def refit(t0):
        starts.append(t0)
        return t0 + 0.01, "refit"

    for score_refit, kept in ((1.0 - 0.06, True), (1.0 - 0.04, False), (1.5, False)):
        out, corr, restarted = restart_uncoupled(hand, th, "fit", refit, lambda t, c: 1.0 if c == "fit" else score_refit,
                                                 hand.limits, tolerance_deg=30.0, gain_mm=0.05)
        assert restarted is kept and corr == ("refit" if kept else "fit")
        np.testing.assert_allclose(starts[-1], recoupled(hand, th, uncoupled(hand, th, 30.0), hand.limits))
    n = len(starts)
    assert restart_uncoupled(hand, np.zeros(hand.n_dofs), "fit", refit, lambda t, c: 0.0, hand.limits)[2] is False
    assert len(starts) == n


@settings(max_examples=60, deadline=None)
@given(hst.lists(hst.floats(-2.3, 0.8), min_size=20, max_size=20))
def test_bent_back_flags_fingers_past_the_real_hyperextension(hand, post_angles):
    """bent_back flags exactly the fingers (never the thumb) whose last two joints' hyperextension
    (their positive flexion) sums to more than BENT_BACK_DEG; unbent gives those fingers' knuckle and
    last two joints their negative magnitude within the limits and leaves every other DoF alone."""
    post = np.flatnonzero(~hand.pose_mask).reshape(5, 4)
    th = np.zeros(hand.n_dofs)
    th[post.ravel()] = post_angles
    back = np.degrees(np.maximum(th[post[:, 2]], 0) + np.maximum(th[post[:, 3]], 0))
    want = back > BENT_BACK_DEG
    want[0] = False
    flags = bent_back(hand, th)
    np.testing.assert_array_equal(flags, want)
    lim = np.array([[-3.0, 1.0]] * hand.n_dofs)
    out = unbent(hand, th, flags, lim)
    k = post[flags][:, 1:].ravel()
    np.testing.assert_allclose(out[k], -np.abs(th[k]))
    rest = np.setdiff1d(np.arange(hand.n_dofs), k)
    np.testing.assert_array_equal(out[rest], th[rest])
    assert not bent_back(hand, th, None).any()


def test_restart_keeps_a_bent_back_finger_bent_forward_only_where_it_finds_data(hand):
    """A coupled finger bent back at every joint (MCP 44°, PIP 23°, DIP 34°, as the Kinect v1 0.8×
    fit of a curling index) is refitted only with bent_back_deg set, from its joints bent forward; the
    refit is kept when it scores better and at least BENT_BACK_MIN_POINTS of its pairs lie on the
    finger's last two bones (20, not 5: a finger hidden behind the hand fits any bend). With an
    uncoupled finger too, a refit rejected so is followed by the coupling's restart alone."""
    from types import SimpleNamespace

    th = np.zeros(hand.n_dofs)
    rows = np.flatnonzero(~hand.pose_mask).reshape(5, 4)
    idx = rows[1]
    th[idx[1:]] = np.radians([44.0, 23.0, 34.0])
    lim = np.array([[-3.0, 1.0]] * hand.n_dofs)
    last = np.flatnonzero(hand.dof_moves[idx[2]])          # the index's middle and distal phalanges' nodes
    palm = hand.node_index("middle1")

    def pairs(n_on_finger, tag):
        nodes = np.r_[np.full(n_on_finger, last[0]), np.full(200, palm)]
        return SimpleNamespace(nodes=nodes, valid=np.ones(nodes.size, bool), tag=tag)

    fit = pairs(0, "fit")
    for found, kept in ((20, True), (5, False)):
        assert last_bones_points(hand, pairs(found, ""))[1] == found
        starts = []

        def refit(t0):
            starts.append(t0)
            return t0, pairs(found, "refit")

        def scorer(t, c):
            return 1.0 if c.tag == "fit" else 0.5

        assert uncoupled(hand, th, 50.0).sum() == 0
        assert restart_uncoupled(hand, th, fit, refit, scorer, lim)[2] is False and not starts
        out, corr, restarted = restart_uncoupled(hand, th, fit, refit, scorer, lim, bent_back_deg=BENT_BACK_DEG)
        assert restarted is kept and corr.tag == ("refit" if kept else "fit") and len(starts) == 1
        np.testing.assert_allclose(np.degrees(starts[-1][idx[1:]]), [-44.0, -23.0, -34.0])
        # the ring finger's DIP folded off its coupling too: rejected, the coupling's restart follows alone
        both = th.copy()
        both[rows[3, 2:]] = np.radians([-80.0, 30.0])
        starts.clear()
        restart_uncoupled(hand, both, fit, refit, scorer, lim, bent_back_deg=BENT_BACK_DEG)
        assert len(starts) == (1 if kept else 2)
        if not kept:
            np.testing.assert_allclose(starts[-1], recoupled(hand, both, uncoupled(hand, both, 50.0), lim))


def test_paper_settings_have_neither_band_nor_restart():
    """TrackerSettings.paper() stays the paper's method: no silhouette band, no finger restarts."""
    st = TrackerSettings.paper()
    assert st.observe.edge_px == 0 and st.refine.finger_restart_deg == 0.0


def _count(hand, frames, **kw):
    truth = make_motion("count", hand=hand).theta[:frames]
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(**kw))
    return np.nan_to_num(E.run_sequence(hand, truth, CAM, tr, noise=KINECT, seed=0).error_deg, nan=np.inf)


def test_a_finger_opening_from_the_fist_is_restarted(hand):
    """Counting under Kinect v1 noise: as the ring finger opens from the fist (frames 95–110) its DIP
    stayed curled at the limit for a dozen frames without the restart (finger_restart_deg=0: up to
    13.8°, 8 frames beyond 7°); with it every one of those frames stays within 7° (measured 5.8° at
    most)."""
    on = _count(hand, 110)
    assert on[95:].max() <= 7.0, on[95:].round(1)
