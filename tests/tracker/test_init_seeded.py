"""The search with a detected hand first (:func:`tracker.init.seeded_search`) and its settings
(:class:`tracker.init.SeededSettings`), and the finger-wise restarts' ranking settings
(``HalvingSettings.restart_icp``, ``restart_margin_mm``): a detected hand fitted once is accepted with its
restarts, one not accepted is searched as with the default, and the restarts' settings set what is ranked
and what goes on."""
from dataclasses import fields

import numpy as np
import pytest

from handmodel import HandModel
from tracker.correspond import Silhouette
from tracker.evaluate import posture_error_deg
from tracker.init import FitContext, InitSettings, finger_search_batched, seeded_search
from tracker.io.cameras import preset
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim import experiments as E
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
CAM = preset("kinect1")
NAMES = list(HAND.dof_names)


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


class Counting(FitContext):
    """A :class:`FitContext` that records each batch of fits: ``(starts, ICP iterations)``, and each lone fit
    as ``(1, iterations)`` unless ``lone`` is False (the batches alone)."""

    lone = True

    def __post_init__(self):
        super().__post_init__()
        self.calls = []

    def fit_many(self, thetas, points, mode, n_rigid, n_icp, **kw):
        self.calls.append((len(np.atleast_2d(thetas)), n_icp))
        return super().fit_many(thetas, points, mode, n_rigid, n_icp, **kw)

    def fit(self, theta, points, mode, n_rigid, n_icp, **kw):
        if self.lone:
            self.calls.append((1, n_icp))
        return super().fit(theta, points, mode, n_rigid, n_icp, **kw)


def counting(ctx, lone=True):
    """``ctx`` as a :class:`Counting` context (``lone``: lone fits recorded too)."""
    c = Counting(**{f.name: getattr(ctx, f.name) for f in fields(ctx) if f.init})
    c.lone = lone
    return c


@pytest.fixture(scope="module")
def ring_curled(bundle):
    """A hand at 0.7 m with the ring finger curled alone, the fingers otherwise nearly straight; the
    same θ with the ring finger straight (a fit holding it wrong); the frame, its silhouette and a context."""
    truth = E.sequence(bundle.model.mean_[None], bundle.model.mean_, lead=0, distance=0.7)[0]
    for n in NAMES:
        if "flex" in n and not n.startswith("thumb"):
            truth[NAMES.index(n)] = np.radians(-5.0)
    for n, deg in (("ring1_flex", -45.0), ("ring2_flex", -100.0), ("ring3_flex", -15.0)):
        truth[NAMES.index(n)] = np.radians(deg)
    wrong = truth.copy()
    for n in ("ring1_flex", "ring2_flex", "ring3_flex"):
        wrong[NAMES.index(n)] = np.radians(-5.0)
    ob = observe(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM, stride=1, target_points=None,
                 smooth=0, segmenter=Segmenter(forearm="keep"))
    ctx = FrameTracker(HAND, TrackerSettings(), synergies=bundle).context
    return truth, wrong, ob, Silhouette(ob.mask, ob.depth, CAM), ctx


def test_restart_settings_set_the_ranking_fits_and_the_finalists(ring_curled):
    """The restarts are ranked with ``restart_icp`` iterations; every finger's best goes on with a margin
    no ranking can miss, fewer with the default 2 mm, fewer still (or as many) with 0 mm: only the
    restarts that rank better than θ itself. The ring finger's curl ranks better than the straight
    finger, so every margin finds it."""
    truth, wrong, ob, sil, ctx = ring_curled
    st = InitSettings()
    finalists, errs = {}, {}
    for margin in (1e9, 2.0, 0.0):
        c = counting(ctx)
        restarts = st.replace(halving=dict(restart_margin_mm=margin, restart_icp=3))
        th = finger_search_batched(c, wrong, ob.points, restarts, silhouette=sil, normals=ob.normals)
        ranked = [n for n, it in c.calls if it == 3]
        refined = [n for n, it in c.calls if it == st.refine_icp]
        assert ranked and sum(ranked) >= 5 * 3  # every finger's shapes, ranked with restart_icp iterations
        finalists[margin] = refined[0]
        errs[margin] = float(posture_error_deg(th, truth, HAND.pose_mask))
    print(f"\nfinalists (θ included) by margin: {finalists}; posture error {errs} deg")
    assert finalists[1e9] >= finalists[2.0] >= finalists[0.0] >= 2
    assert finalists[1e9] > finalists[0.0]
    assert max(errs.values()) <= 1.5 < float(posture_error_deg(wrong, truth, HAND.pose_mask))


def test_a_detected_hand_fitted_once_is_accepted_with_its_restarts(ring_curled):
    """``seeded.first`` "fit": the detected hand (the ring finger held straight, the hand 8 mm off) fitted
    once, accepted, and the restarts curl the ring finger as they do after the default's fits; before
    the restarts one fit against the default's batches of synergy starts."""
    truth, wrong, ob, sil, ctx = ring_curled
    seed = wrong.copy()
    seed[:3] += [0.006, -0.005, 0.0]
    out = {}
    for first in ("fit", "search"):
        c = counting(ctx)
        st = InitSettings().replace(halving=dict(seeded=dict(first=first, restart_icp=3)))  # 3: no other fit's count
        th, _, searched = seeded_search(c, ob.points, st, seed, accept_mm=3.0, silhouette=sil, normals=ob.normals)
        assert not searched
        ranking = [i for i, (_, it) in enumerate(c.calls) if it == 3][0]
        out[first] = (float(posture_error_deg(th, truth, HAND.pose_mask)), sum(n for n, _ in c.calls[:ranking]))
    print(f"\n(posture error deg, fits before the restarts): {out}")
    assert out["fit"][1] == 1 < out["search"][1]
    assert out["fit"][0] <= 1.5 and out["search"][0] <= 1.5


def test_a_detected_hand_not_accepted_is_searched_as_by_default(ring_curled):
    """``seeded.first`` "fit" whose fit is not accepted goes on as the default does: the same θ to the bit
    (the cheap search, an acceptance no fit meets)."""
    truth, wrong, ob, sil, ctx = ring_curled
    res = {}
    for first in ("fit", "search"):
        st = InitSettings.cheap().replace(halving=dict(seeded=dict(first=first)))
        res[first] = seeded_search(ctx, ob.points, st, wrong, accept_mm=1e-9, silhouette=sil, normals=ob.normals)
    assert res["fit"][2] and res["search"][2]
    np.testing.assert_array_equal(res["fit"][0], res["search"][0])
