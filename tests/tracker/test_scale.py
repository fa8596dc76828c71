"""tracker.scale: resized fit contexts against rebuilt ones, the size score without the wrist cue,
the parabola search, the one-search calibration against the earlier one, the tracker's calibration
over several frames when a frame's fit is poor, and the size within 3 % on resized rendered hands in
clutter under Kinect v1 and RealSense noise."""
import copy
import functools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as hst
from test_init_orientation import CAM, scene

from handmodel import HandModel
from tracker.io.cameras import preset
from tracker.correspond import CapsuleModel
from tracker.init import score
from tracker.scale import (
    calibrate_scale,
    calibrate_scale_searched,
    parabola_scale,
    rescaled,
    size_score,
    without_wrist,
)
from tracker.sim.motions import POSTURES
from tracker.track import FrameTracker, TrackerSettings, fit_context
from tracker.wrist import WristCue

BASE = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def rebuilt(tracker):
    """``context_for`` as it was before contexts were resized: each size built anew."""
    cache = {}

    def context_for(s):
        key = round(float(s), 5)
        if key not in cache:
            cache[key] = fit_context(BASE if key == 1.0 else BASE.scaled(key), tracker.settings, tracker.synergies)[0]
        return cache[key]
    return context_for


@pytest.mark.parametrize("s", [0.8, 1.37])
def test_resized_context_is_the_rebuilt_hand(s):
    """The resized samples lie on the resized hand's capsules (the surface the fit matches against),
    as a rebuilt context's do; only the matcher and the samples change, the rest is shared."""
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)))
    ctx = tr.context_for(s)
    ref = fit_context(BASE.scaled(s), tr.settings)[0]
    th = np.zeros(BASE.n_dofs)
    th[6:] = np.linspace(-0.6, 0.3, BASE.n_dofs - 6)
    th[3:6] = [0.4, -0.3, 0.2]
    np.testing.assert_allclose(ctx.hand.keypoints(th), ref.hand.keypoints(th), atol=1e-12)
    for samples in (ctx.samples, ctx.score_samples):
        P, N = samples.pose(th)
        c = CapsuleModel(ref.hand)(th, P, reject=1.0, facing_only=False)
        assert c.distance.max() < 1e-6, c.distance.max()  # a micrometre: the base samples are on their surface to that
        assert np.einsum("ij,ij->i", N, c.normals).min() > 0.999  # the surface's normals there
    base = tr.context_for(1.0)
    assert ctx.full is base.full and ctx.reduced is base.reduced and ctx.limits is base.limits
    assert ctx.matcher.surface.hand is ctx.hand and ctx.samples.hand is ctx.hand
    # the model-sized context is left as it was
    assert base.samples.hand is BASE
    np.testing.assert_array_equal(base.samples.local, fit_context(BASE, tr.settings)[0].samples.local)


def test_resized_and_rebuilt_contexts_score_alike(bundle):
    """The size score of the same fits with resized and with rebuilt contexts: equal up to the
    samples' randomness (measured ≤ 0.1 mm), and both rank the true size first."""
    hand = BASE.scaled(1.2)
    th, ob, sil = scene(hand, "palm", POSTURES["open"])
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto")), synergies=bundle)
    fast, slow = tr.context_for, rebuilt(tr)
    got = {}
    for name, cf in (("fast", fast), ("slow", slow)):
        got[name] = []
        for s in (1.08, 1.2, 1.32):
            ctx = cf(s)
            t = rescaled(hand, ctx.hand, th)
            corr = ctx.matcher(t, ob.points, ob.normals)
            got[name].append(size_score(ctx, t, corr, sil))
    np.testing.assert_allclose(got["fast"], got["slow"], atol=0.15)
    assert np.argmin(got["fast"]) == 1 and np.argmin(got["slow"]) == 1


def test_size_score_leaves_the_wrist_cue_out():
    """The wrist cue's cost grows with the hand (its point lies up the arm, not at the wrist joint):
    the size score must not see it, the start search's score still does."""
    th, ob, sil = scene(BASE, "palm", POSTURES["open"])
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)))
    ctx = tr.context_for(1.0)
    corr = ctx.matcher(th, ob.points, ob.normals)
    plain = size_score(ctx, th, corr, sil)
    cued = copy.copy(sil)
    wrist = BASE.keypoints(th)[0]
    # the cue 6 cm past the wrist joint, as a mask that keeps some forearm puts it
    cued.wrist = WristCue(point=wrist + np.array([0.0, -0.06, 0.0]), pixel=np.zeros(2),
                          direction=np.array([0.0, -1.0, 0.0]), width_m=0.05)
    assert score(ctx, th, corr, cued) > score(ctx, th, corr, sil) + 5.0
    assert size_score(ctx, th, corr, cued) == pytest.approx(plain)
    assert cued.wrist is not None and without_wrist(cued).wrist is None and without_wrist(sil) is sil


def test_parabola_finds_the_size_of_a_smooth_score():
    """A score with its minimum between probes: the vertex, not the best probe."""
    calls = []

    class Ctx:
        def __init__(self, s):
            self.s, self.hand = s, BASE

        def fit(self, th, points, *a, **k):
            return th, None

    def context_for(s):
        calls.append(s)
        return Ctx(s)

    import tracker.scale as S

    orig = S.size_score
    S.size_score = lambda ctx, th, corr, sil: (np.log(ctx.s) - np.log(1.237)) ** 2 * 100.0
    try:
        s, _, _, _ = parabola_scale(context_for, np.zeros(BASE.n_dofs), BASE, np.zeros((5, 3)), 1.2, probes=5)
    finally:
        S.size_score = orig
    assert len(calls) == 5 and min(calls) == pytest.approx(1.2 * np.exp(-0.06))
    assert s == pytest.approx(1.237, rel=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("scale,facing,posture", [(0.8, "palm", "open"), (1.4, "back", "mean")])
def test_one_search_calibration_agrees_with_the_earlier_one(bundle, scale, facing, posture):
    """On rendered hands without noise, the calibration with one search and resized contexts finds
    the size within 3 % as the earlier one (a search per guess, contexts rebuilt) does, and within
    3 % of it."""
    hand = BASE.scaled(scale)
    p = bundle.model.mean_ if posture == "mean" else POSTURES[posture]
    _, ob, sil = scene(hand, facing, p)
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto")), synergies=bundle)
    s_fast, _, _ = calibrate_scale(tr.context_for, ob.points, tr.settings.init, silhouette=sil, normals=ob.normals)
    s_old, _, _ = calibrate_scale_searched(rebuilt(tr), ob.points, tr.settings.init, silhouette=sil,
                                           normals=ob.normals)
    print(f"\nscale {scale}: one search {s_fast / scale:.4f}, earlier {s_old / scale:.4f}")
    assert abs(s_fast / scale - 1.0) <= 0.03 and abs(s_old / scale - 1.0) <= 0.03
    assert abs(s_fast / s_old - 1.0) <= 0.03


@pytest.mark.slow
def test_poor_first_fits_are_calibrated_again_and_the_best_kept(bundle):
    """While no calibrated frame scores within ``scale_trust_mm``, the next frame is calibrated
    again (a start search, status reinit), at most ``scale_frames`` frames, and the size of the
    best-scoring one is used; then the tracker tracks and refines the size."""
    hand = BASE.scaled(1.2)
    _, ob, _ = scene(hand, "palm", POSTURES["open"])
    # budget 0: the tracked frame's estimate at once (spread over frames: test_scale_budget.py)
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto", trust_mm=0.0, frames=3, budget=0)),
                      synergies=bundle)
    status = [tr.track(ob, CAM).status for _ in range(4)]
    assert status[:3] == ["reinit"] * 3 and status[3] == "tracked", status
    assert len(tr.sizing.calibrations_) == 3
    best = min(tr.sizing.calibrations_)[1]
    assert tr.scale_estimates_[0] == best and len(tr.scale_estimates_) == 2
    assert abs(tr.scale_ / 1.2 - 1.0) <= 0.03
    # trusted at once: one calibration
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto")), synergies=bundle)
    assert [tr.track(ob, CAM).status for _ in range(2)] == ["reinit", "tracked"] and len(tr.sizing.calibrations_) == 1


@pytest.mark.slow
@pytest.mark.parametrize("sensor,scale,clutter", [
    # small hands with their forearm came out 4-9 % large with the earlier size score (size_score's
    # docstring); the first two and realsense 0.8 forearm failed with it (1.088, 1.053, 1.038)
    ("kinect1", 0.8, "forearm"), ("kinect1", 0.8, "forearm,table"),
    # the forearm cut lay ~1 cm into the palm here (the small hand's slow taper at the coarse search's
    # resolution was no narrowing; 1.3 palm radii were too few): size 0.952, now 0.989
    ("realsense", 0.8, "forearm,torso"),
    ("kinect1", 1.5, "forearm,box"), ("kinect1", 1.0, "forearm"),
    ("realsense", 0.8, "forearm"), ("realsense", 1.5, "forearm,torso"), ("realsense", 1.0, "forearm,table")])
def test_size_within_3_percent_in_clutter_and_noise(bundle, sensor, scale, clutter):
    """Resized rendered hands with their forearm and a table, box or torso, under the sensor's
    noise, tracked from the model with ``hand_scale="auto"`` over 6 frames: the size within 3 %."""
    from tracker.sim.experiments import REALISTIC_SENSORS, run_scene
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion
    from tracker.sim.noise import NoiseModel

    cam_name, noise_name = REALISTIC_SENSORS[sensor]
    shown = HandShape(scale).apply(BASE)
    truth = make_motion("open-close", hand=shown, frames=30).theta[:6]
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto")), synergies=bundle)
    r = run_scene(BASE, shown, truth, preset(cam_name), tr, clutter=clutter, noise=NoiseModel.preset(noise_name),
                  seed=3)
    print(f"\n{sensor} ×{scale} {clutter}: size {r['scale'][-1] / scale:.4f}, keypoints {np.round(r['keypoint_mm'], 1)}")
    assert abs(r["scale"][-1] / scale - 1.0) <= 0.03, r["scale"] / scale
    assert np.nanmean(r["keypoint_mm"]) <= 10.0



@functools.lru_cache(maxsize=1)
def _base_context():
    return fit_context(BASE, TrackerSettings())[0]


@hyp_settings(max_examples=25, deadline=None)
@given(s=hst.floats(0.7, 1.7), q=hst.lists(hst.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1),
       shift=hst.lists(hst.floats(-0.3, 0.3), min_size=3, max_size=3), closed=hst.booleans())
def test_first_sizes_of_the_models_own_surface_are_its_size(s, q, shift, closed):
    """``first_sizes`` on the model's own palm-side surface (open or closed), scaled by ``s``, turned and moved
    anywhere: the matching guess is ``guess`` × s (an extent is blind to rotation and translation), both
    within the range, the closed guess at least the open one, and a keypoint size larger than the open guess
    takes its place."""
    from handmodel.rigid import quat_to_matrix
    from tracker.init.candidates import _palm_side
    from tracker.scale import closed_posture, first_sizes

    ctx = _base_context()
    posture = closed_posture(ctx) if closed else np.zeros(int((~BASE.pose_mask).sum()))
    pts = _palm_side(BASE, posture)[3]
    R = quat_to_matrix(np.asarray(q) / np.linalg.norm(q))
    cloud = s * (pts - pts.mean(0)) @ R.T + np.asarray(shift) + [0, 0, 0.7]
    open_s, closed_s, _ = first_sizes(ctx, cloud, None, (0.6, 2.0), 1.1)
    assert (closed_s if closed else open_s) == pytest.approx(min(1.1 * s, 2.0), rel=1e-6)
    assert 0.6 <= open_s <= 2.0 and 0.6 <= closed_s <= 2.0
    # the closed model spreads less than the open one: the same cloud is a larger closed hand
    assert closed_s >= open_s
    assert first_sizes(ctx, cloud, open_s + 0.1, (0.6, 2.0), 1.1)[0] == pytest.approx(min(open_s + 0.1, 2.0))
