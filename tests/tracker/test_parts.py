"""The tracker's settings groups and named parts alone (tracker.settings, tracker.parts): each group
small, frozen, checked and with the paper's values; the parts built from their settings and tested
through their public methods, without a tracker."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from handmodel import HandModel
from tracker.correspond import ModelSamples
from tracker.errors import TrackerError
from tracker.icp import posed_samples
from tracker.parts import Gate, LossCheck, Prediction, Recentring, TrackerStats
from tracker.settings import (
    LossSettings,
    ObserveSettings,
    PredictSettings,
    SafetyNetSettings,
    SettingsGroup,
    TrackerSettings,
)
from tracker.sim.motions import make_motion
from tracker.track import FrameTracker, build_parts

HAND = HandModel.load()


def _groups(s):
    yield s
    for f in dataclasses.fields(s):
        v = getattr(s, f.name)
        if isinstance(v, SettingsGroup):
            yield from _groups(v)


def test_every_settings_group_is_small_frozen_checked_and_has_the_papers_values():
    groups = list(_groups(TrackerSettings()))
    # the top level, 11 groups, the net's wrist test, icp's two, refine's keypoint term, init's halving and seeded
    assert len(groups) == 18
    for g in groups:
        assert len(dataclasses.fields(g)) <= 12, type(g).__name__
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(g, dataclasses.fields(g)[0].name, None)
        g.check()
        type(g).paper().check()
    p = TrackerSettings.paper()
    # the paper's method is every group's paper() (one definition per group)
    for f in dataclasses.fields(p):
        if isinstance(getattr(p, f.name), SettingsGroup):
            assert getattr(p, f.name) == type(getattr(p, f.name)).paper(), f.name


def test_replace_nests_and_leaves_the_original():
    s = TrackerSettings()
    t = s.replace(net=dict(far_share=0.0, wrist=dict(every=2)), loss=LossSettings(min_points=5))
    assert (t.net.far_share, t.net.wrist.every, t.net.score_mm, t.loss.min_points) == (0.0, 2, 0.7, 5)
    assert (s.net.far_share, s.net.wrist.every, s.loss.min_points) == (0.1, 6, 30)
    with pytest.raises(TrackerError, match="WristTestSettings has no field 'evry'"):
        s.replace(net=dict(wrist=dict(evry=2)))


@pytest.mark.parametrize("change, where", [
    ({"mode": "fast"}, "mode"), ({"subspace": {"variance": 1.5}}, "subspace.variance"),
    ({"refine": {"unseen_prior": 2.0}}, "refine.unseen_prior"), ({"loss": {"no_hand_rejected": 1.0}}, "loss.no_hand_rejected"),
    ({"scale": {"hand_scale": 0.1}}, "scale.hand_scale"), ({"observe": {"stride": 0}}, "observe.stride"),
    ({"net": {"wrist": {"fit_mm": -1.0}}}, "net.wrist.fit_mm")])
def test_check_names_the_field(change, where):
    with pytest.raises(TrackerError) as e:
        TrackerSettings().replace(**change).check()
    assert e.value.where == where


def test_the_command_line_names_the_option_of_a_bad_field():
    from tracker.cli_common import settings_from_options

    args = [False, "full", None, None] + [None] * 12 + [None, False]
    with pytest.raises(TrackerError, match=r"^--unseen-prior: must be within 0..1, got 2.0$"):
        settings_from_options(*args, unseen_prior=2.0)
    with pytest.raises(TrackerError, match=r"^--no-hand-rejected: must be a share in \[0, 1\)"):
        settings_from_options(*args, no_hand=1.0)
    assert settings_from_options(*args, unseen_prior=0.25, safety_net=False).refine.unseen_prior == 0.25
    with pytest.raises(TrackerError, match=r"^--size-refine: must be 'search', 'local' or 'checked', got 'fast'$"):
        settings_from_options(*args, size_refine="fast")
    assert settings_from_options(*args, size_refine="search").scale.refine == "search"
    assert settings_from_options(*args).scale.refine == TrackerSettings().scale.refine == "checked"


def test_loss_check_alone():
    stats = TrackerStats()
    loss = LossCheck(LossSettings(), (0.6, 2.0), stats)

    class Pairs:  # what the check reads of a fit's correspondences
        def __init__(self, share):
            self.valid = np.ones(10, bool)
            self.rejected_share = share

    assert loss.found_nothing(Pairs(0.25)) and not loss.found_nothing(Pairs(0.15))
    assert not loss.size_out(1.3) and loss.size_out(0.6) and loss.size_out(1.99) and not loss.size_out(1.97)
    assert loss.no_hand_sized(2.0, Pairs(0.0)) and stats.size_out == 1
    assert loss.no_hand_sized(1.2, Pairs(0.3)) and stats.size_out == 1
    assert loss.too_small(149, None) and not loss.too_small(150, None)
    assert loss.kept(11.9, 0.6) and not loss.kept(12.1, 0.0) and not loss.kept(float("nan"), 0.0)
    off = LossCheck(LossSettings.paper())
    assert not off.found_nothing(Pairs(0.9)) and not off.size_out(2.0) and not off.too_small(1, None)


def test_recentring_alone_moves_a_prediction_that_missed_the_cloud():
    theta = make_motion("open-close", hand=HAND, frames=5).theta[2]
    samples = ModelSamples(HAND, spacing=0.006)
    P, N = posed_samples(HAND, samples, theta)
    cloud = P[N[:, 2] < 0]  # the camera-facing side, as a depth camera sees it
    stats = TrackerStats()
    part = Recentring(50.0, stats)
    missed = theta.copy()
    missed[:3] += [0.08, -0.03, 0.0]
    moved = part(HAND, samples, missed, cloud)
    assert np.abs(moved[:3] - theta[:3]).max() < 0.005 and np.array_equal(moved[3:], theta[3:])
    assert stats.recentred == 1
    near = theta.copy()
    near[0] += 0.01
    assert part(HAND, samples, near, cloud) is near and stats.recentred == 1


def test_prediction_alone_adds_the_last_change_but_not_the_rotation_without_turn():
    gate = Gate(ObserveSettings(), 30, False)
    pred = Prediction(PredictSettings(share=0.5, turn=False), gate, Recentring(50.0))
    lim = np.array(HAND.limits, float)
    prev = np.zeros(HAND.n_dofs)
    now = prev.copy()
    now[:6] = [0.02, 0.0, 0.0, 0.1, 0.0, 0.0]
    now[8] = 0.2
    out = pred.theta(now, prev, HAND, lim)
    want = now.copy()
    want[0] += 0.01
    want[8] = 0.3
    post = ~HAND.pose_mask
    want[post] = np.clip(want[post], lim[post, 0], lim[post, 1])
    np.testing.assert_allclose(out, want)
    np.testing.assert_array_equal(pred.theta(now, None, HAND, lim), now)


def test_the_parts_share_one_count_the_cue_and_the_gate():
    stats = TrackerStats()
    parts = build_parts(HAND, TrackerSettings().replace(start=dict(rgb_seed=True)), None, stats,
                        keypoint_detector=lambda color: None, depth_detector=lambda depth, camera, mask, hand: None)
    assert all(p.stats is stats for p in parts if hasattr(p, "stats"))
    assert sum(hasattr(p, "stats") for p in parts) == 12  # all but the hand sizes (the hand presence included)
    assert parts.presence is not None and parts.presence.stats is stats
    assert parts.net.cue is parts.cue and parts.search.cue is parts.cue and parts.search.colour is parts.colour
    assert parts.prediction.gate is parts.gate and parts.prediction.recentring is parts.recentring
    assert parts.search.keypoints is not None and parts.search.keypoints.stats is stats
    plain = build_parts(HAND, TrackerSettings().replace(start=dict(detector="", presence="")), None, TrackerStats())
    assert plain.colour is None and plain.search.keypoints is None and plain.presence is None
    with pytest.raises(TrackerError, match="needs a synergy bundle"):
        build_parts(HAND, TrackerSettings(mode="reduced"), None, stats)


def test_each_frame_result_carries_the_counts_so_far():
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0), net=SafetyNetSettings(enabled=False)))
    few = tr.step(np.zeros((5, 3)))
    assert few.status == "lost" and few.stats == TrackerStats()
    plane = np.stack(np.meshgrid(np.linspace(-0.01, 0.01, 10), np.linspace(-0.01, 0.01, 10)), -1).reshape(-1, 2)
    r = tr.step(np.column_stack([plane, np.full(len(plane), 0.7)]))
    # 100 points, no mask: a region of 100 < 150 pixels is too small to start from
    assert r.stats.no_hand == r.stats.too_few == 1 and r.stats == tr.stats and r.stats is not tr.stats
