"""The size calibration's work spread over tracked frames (``scale.budget``, :class:`tracker.sizing.SpreadWork`):
each frame's probes within the budget in ICP iterations, the same result as the work done at once, the
size and finger lengths still found on a rendered hand, and ``refine="checked"`` calibrating a frame on its
own only where the tracked fit explains it poorly."""
import math

import numpy as np
import pytest
from test_init_orientation import CAM, scene

from handmodel import HandModel
from tracker.errors import TrackerError
from tracker.resize import shaped_hand
from tracker.scale import COST_POINTS, parabola_scale, parabola_scale_steps, probe_cost, run_steps
from tracker.settings import ScaleSettings
from tracker.sim.motions import POSTURES
from tracker.sizing import SpreadWork
from tracker.track import FrameTracker, TrackerSettings

BASE = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def probes(costs, done):
    """Work whose probes cost ``costs`` (ICP iterations); ``done`` receives each probe's index as it runs."""
    for i, c in enumerate(costs):
        yield c
        done.append(i)
    return len(done)


@pytest.mark.parametrize("budget", [1, 10, 24, 40])
def test_each_frame_spends_at_most_its_budget_and_every_probe_runs_once(budget):
    """Frame by frame: the probes run in order, each once, a frame's iterations within the budget
    unless one probe alone costs more (it runs alone: the work must go on); the result comes with
    the last probe."""
    costs = [10, 10, 4, 4, 4, 10, 25, 4, 10]
    done = []
    work = SpreadWork(probes(costs, done))
    per_frame, nxt = [], []
    while not work.finished:
        before = len(done)
        spent = work.run(budget)
        per_frame.append(spent)
        ran = costs[before:len(done)]
        assert spent == sum(ran) and len(ran) >= 1
        assert spent <= budget or len(ran) == 1, (budget, ran)
        nxt.append(costs[len(done)] if len(done) < len(costs) else None)
    assert done == list(range(len(costs))) and work.result == len(costs)
    assert sum(per_frame) == sum(costs)
    # no frame stopped early: the next probe would not have fitted in its budget
    assert all(spent + c > budget for spent, c in zip(per_frame[:-1], nxt[:-1])), (per_frame, nxt)


def test_no_budget_runs_the_whole_work_on_one_frame():
    done = []
    work = SpreadWork(probes([10, 10, 30], done))
    assert work.run(0) == 50 and work.finished and done == [0, 1, 2]
    # a frame that already spent some of its budget elsewhere takes only what is left
    done = []
    work = SpreadWork(probes([10, 10, 30], done))
    assert work.run(25, spent=10) == 20 and done == [0]


def test_a_parabola_spread_over_frames_finds_what_it_finds_at_once(bundle):
    """The same probes, the same size and θ to the bit, whether run at once or a few per frame."""
    hand = BASE.scaled(1.2)
    th, ob, sil = scene(hand, "palm", POSTURES["open"])
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)), synergies=bundle)
    start = th.copy()
    start[:3] += BASE.keypoints(th).mean(0) - hand.keypoints(th).mean(0)
    pts = ob.points[np.all(np.isfinite(ob.points), axis=1)][::3]
    once = parabola_scale(tr.context_for, start, BASE, pts, 1.1, silhouette=sil)
    work = SpreadWork(parabola_scale_steps(tr.context_for, start, BASE, pts, 1.1, silhouette=sil))
    frames = 0
    while not work.finished:
        assert work.run(20) <= 20
        frames += 1
    cost = probe_cost(10, len(pts))
    assert frames == math.ceil(7 / (20 // cost))  # 7 probes, as many a frame as fit in 20
    spread = work.result
    assert spread[0] == once[0] and spread[3] == once[3]
    np.testing.assert_array_equal(spread[1], once[1])
    assert run_steps(parabola_scale_steps(tr.context_for, start, BASE, pts, 1.1, silhouette=sil))[0] == once[0]


def test_a_probe_costs_its_iterations_on_the_reference_points_and_less_on_fewer():
    """:func:`tracker.scale.probe_cost`: 10 iterations on ``COST_POINTS`` points cost 10; fewer points
    cost less, but not in proportion (an iteration's fixed part), more points more."""
    assert probe_cost(10, COST_POINTS) == pytest.approx(10.0)
    small, large = probe_cost(10, COST_POINTS // 3), probe_cost(10, 2 * COST_POINTS)
    assert 10.0 / 3 < small < 10.0 < large < 20.0
    assert probe_cost(4, 500) == pytest.approx(0.4 * probe_cost(10, 500))


def track_still(bundle, scale, n, **changes):
    """A hand ``scale`` × the model, open palm, the same frame tracked ``n`` times from the
    model with the size automatic and ``changes`` to the scale settings."""
    hand = BASE.scaled(scale)
    _, ob, _ = scene(hand, "palm", POSTURES["open"])
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto", **changes)), synergies=bundle)
    results = [tr.track(ob, CAM) for _ in range(n)]
    return tr, results


def test_size_and_fingers_settle_within_the_budget(bundle):
    """Default settings (``refine="checked"``, ``budget`` 40): every refining frame's size work within
    the budget (a probe costs at most 10, on at most 1,500 points: less than it), spread over more frames than the
    estimates need, and still the size within 3 % of the rendered 1.25× hand, the finger lengths found,
    no frame calibrated on its own (the tracked fit is good), and the size work over once it is done."""
    st = ScaleSettings()
    assert st.refine == "checked" and st.budget == 40
    tr, results = track_still(bundle, 1.25, 40)
    assert all(r.status != "lost" for r in results)
    work = tr.sizing.work_
    assert len(work) > st.frames - 1 and max(work) <= st.budget, work
    assert len(tr.scale_estimates_) == st.frames and abs(tr.scale_ / 1.25 - 1.0) <= 0.03, tr.scale_estimates_
    assert tr.finger_scales_ is not None and tr.sizing.searches_ == 0
    assert not tr.sizing.refining()
    # all the work at once instead: the same probes fall on the frames that refine
    tr0, _ = track_still(bundle, 1.25, st.frames, budget=0)
    assert len(tr0.sizing.work_) == st.frames - 1 and max(tr0.sizing.work_) > st.budget
    assert tr0.finger_scales_ is not None and abs(tr0.scale_ / 1.25 - 1.0) <= 0.03


def test_spread_estimates_come_from_the_first_tracked_frames(bundle):
    """A hand 1.2× opening and closing (Kinect v1, no noise): with a small budget each estimate takes
    several frames, yet the estimates are those of the first ``frames`` − 1 tracked frames, kept until
    their turn — each within 0.05 % of the estimates made at once (measured ≤ 0.02 %; frames later in the
    motion give other sizes)."""
    from tracker.io.cameras import preset
    from tracker.sim.experiments import run_scene
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion

    shown = HandShape(1.2).apply(BASE)
    truth = make_motion("open-close", hand=shown, frames=30).theta[:20]
    found = {}
    for budget in (0, 12):
        st = TrackerSettings().replace(scale=dict(hand_scale="auto", budget=budget, finger_lengths=False))
        tr = FrameTracker(BASE, st, synergies=bundle)
        run_scene(BASE, shown, truth, preset("kinect1"), tr)
        found[budget] = (np.array(tr.scale_estimates_), tr.sizing.work_)
    (at_once, work0), (spread, work12) = found[0], found[12]
    assert len(at_once) == len(spread) == 5 and len(work12) >= 3 * len(work0) and max(work12) <= 12
    np.testing.assert_allclose(spread, at_once, rtol=5e-4)


def test_finish_does_the_rest_at_once(bundle):
    """A recording that ends while the work is under way (the first calibration and four refining frames
    kept, their estimates and the finger lengths to come): :meth:`SizeCalibration.finish` does it all,
    and then there is nothing left to do."""
    tr, _ = track_still(bundle, 1.25, 5)
    sz = tr.sizing
    assert sz.refining() and tr.finger_scales_ is None and len(tr.scale_estimates_) < 5
    assert sz.finish(tr)
    assert len(tr.scale_estimates_) == 5 and abs(tr.scale_ / 1.25 - 1.0) <= 0.03 and tr.finger_scales_ is not None
    assert not sz.refining() and not sz.finish(tr)
    # the tracked hand has the lengths found
    th = np.zeros(BASE.n_dofs)
    np.testing.assert_allclose(tr.hand.keypoints(th), shaped_hand(BASE, tr.scale_, tr.finger_scales_).keypoints(th))


def test_checked_calibrates_a_frame_alone_where_the_tracked_fit_is_poor(bundle):
    """``trust_mm`` below any fit's score: every local estimate is distrusted, so each refining frame is
    calibrated on its own (``searches_``), and the size is still the rendered one's within 3 %."""
    tr, _ = track_still(bundle, 0.9, 8, trust_mm=0.01, finger_lengths=False, frames=3)
    assert tr.sizing.searches_ == 2 and len(tr.scale_estimates_) == 3, tr.sizing.searches_
    assert abs(tr.scale_ / 0.9 - 1.0) <= 0.03, tr.scale_estimates_


@pytest.mark.parametrize("bad", [-1, 2.5, float("nan"), "40", True])
def test_bad_budget_refused(bad):
    with pytest.raises(TrackerError, match="scale.budget: must be a whole number"):
        FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale="auto", budget=bad)))


def test_refine_choices_and_the_papers_size_unchanged():
    with pytest.raises(TrackerError, match="scale.refine: must be 'search', 'local' or 'checked'"):
        FrameTracker(BASE, TrackerSettings().replace(scale=dict(refine="probe")))
    paper = TrackerSettings.paper().scale
    assert paper.hand_scale == 1.0 and not paper.finger_lengths  # no calibration at all: no size work
