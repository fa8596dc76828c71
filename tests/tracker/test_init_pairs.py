"""The start search's pair restarts and its finger-overlap term: two model fingers in one place are
charged (real fingers cannot pass through each other), the overlap is measured between the phalanges'
axes as it should be, and two neighbouring fingers that swapped places (a curled finger's blob taken
by its neighbour) come back only when both move at once."""
from dataclasses import replace

import numpy as np
import pytest

from handmodel import HandModel
from tracker.io.cameras import preset
from tracker.correspond import Silhouette
from tracker.evaluate import posture_error_deg
from tracker.init import (
    PAIR_SHAPES,
    InitSettings,
    finger_overlap_mm,
    finger_pair_variants,
    finger_search_batched,
    posture_grid,
    score,
    segment_distances,
)
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim import experiments as E
from tracker.sim.motions import make_motion
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
CAM = preset("kinect1")
NAMES = list(HAND.dof_names)


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def test_segment_distances_match_dense_sampling():
    """The closed-form closest distance between two segments equals the minimum over densely sampled
    point pairs (within the sampling's resolution) and never exceeds it; the parameters returned give
    that distance — for crossing, parallel, end-to-end and degenerate (point) segments."""
    rng = np.random.default_rng(0)
    P0, P1, Q0, Q1 = (rng.normal(size=(200, 3)) for _ in range(4))
    P1[:20] = P0[:20] + (Q1[:20] - Q0[:20])          # parallel
    Q1[20:30] = Q0[20:30]                             # a point
    Q0[30:40] = P1[30:40] + rng.normal(0, 0.05, (10, 3))   # end near end
    d, s, t = segment_distances(P0, P1, Q0, Q1)
    u = np.linspace(0, 1, 201)
    for k in range(len(P0)):
        A = P0[k] + u[:, None] * (P1[k] - P0[k])
        B = Q0[k] + u[:, None] * (Q1[k] - Q0[k])
        dense = np.min(np.linalg.norm(A[:, None] - B[None], axis=-1))
        assert d[k] <= dense + 1e-9
        assert dense - d[k] <= 0.02 * max(np.linalg.norm(P1[k] - P0[k]), np.linalg.norm(Q1[k] - Q0[k]), 1e-9)
        got = np.linalg.norm(P0[k] + s[k] * (P1[k] - P0[k]) - Q0[k] - t[k] * (Q1[k] - Q0[k]))
        assert got == pytest.approx(d[k], abs=1e-9)


def test_finger_overlap_is_zero_for_real_postures_and_charges_fingers_in_one_place(bundle):
    """Every posture of the synergy grid (open hand to fist) at the model size and 1.4×, and every
    frame of the rendered open-close motion (its fist's thumb pressed over the index and middle
    fingers), has no overlap (the term must not tilt the search among real hands or the hand size),
    while a middle finger swung onto the index finger, or ring and pinky crossed, costs at least 10 mm."""
    for size in (1.0, 1.4):
        hand = HAND.scaled(size)
        for p in posture_grid(bundle.model):
            th = np.zeros(hand.n_dofs)
            th[~hand.pose_mask] = p
            assert finger_overlap_mm(hand, th) == 0.0
    for th in make_motion("open-close", hand=HAND, frames=30, seed=0).theta:
        assert finger_overlap_mm(HAND, th) == 0.0
    th = np.zeros(HAND.n_dofs)
    th[~HAND.pose_mask] = bundle.model.mean_
    swung = [finger_overlap_mm(HAND, np.where(np.arange(HAND.n_dofs) == NAMES.index("middle1_abd"), a, th))
             for a in np.radians([-40.0, 40.0])]
    crossed = th.copy()
    crossed[NAMES.index("ring1_abd")], crossed[NAMES.index("pinky1_abd")] = np.radians([35.0, -35.0])
    crossed2 = th.copy()
    crossed2[NAMES.index("ring1_abd")], crossed2[NAMES.index("pinky1_abd")] = np.radians([-35.0, 35.0])
    assert max(swung) >= 10.0, swung
    assert max(finger_overlap_mm(HAND, crossed), finger_overlap_mm(HAND, crossed2)) >= 10.0


def test_pair_variants_set_two_neighbours_and_nothing_else(bundle):
    """Three neighbouring pairs (index-middle, middle-ring, ring-pinky) × the pair shapes of both:
    each variant differs from θ only in the two fingers' flexions (set to a shape) and abductions (the
    synergy mean's); without the ring finger's shapes only the index-middle pair is left."""
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    rng = np.random.default_rng(1)
    theta = np.r_[0.0, 0.0, 0.7, rng.normal(0, 0.3, 3), rng.normal(-0.4, 0.2, HAND.n_dofs - 6)]
    mean = np.zeros(HAND.n_dofs)
    mean[~HAND.pose_mask] = bundle.model.mean_
    out = finger_pair_variants(ctx, theta)
    n = len(PAIR_SHAPES) ** 2
    assert len(out) == 3 * n
    for k, (f, g) in enumerate((("index", "middle"), ("middle", "ring"), ("ring", "pinky"))):
        rows = [th for kk, th in out if kk == k + 1]
        assert len(rows) == n
        own = [i for i, nm in enumerate(NAMES) if nm.startswith((f, g))]
        for th in rows:
            other = np.setdiff1d(np.arange(HAND.n_dofs), own)
            np.testing.assert_array_equal(th[other], theta[other])
            for x in (f, g):
                assert th[NAMES.index(x + "1_abd")] == mean[NAMES.index(x + "1_abd")]
        shapes = {tuple(np.round(np.degrees(th[[NAMES.index(g + "2_flex")]]), 3)) for th in rows}
        assert len(shapes) >= len(PAIR_SHAPES) - 1   # shapes clipped to a limit may coincide
    no_ring = replace(ctx, finger_shapes=[(fi, v) for fi, v in ctx.finger_shapes if not NAMES[fi[0]].startswith("ring")])
    assert {k for k, _ in finger_pair_variants(no_ring, theta)} == {1}


@pytest.mark.slow
def test_pair_restarts_separate_a_curled_finger_from_its_neighbour(bundle):
    """The ring finger straight and the pinky curled (SR305 frame 231615_200), fitted with the two in
    each other's place — the pinky spread onto the ring finger, the ring finger curled into the palm.
    One finger moved at a time leaves both on one place; the pair restarts bring both back."""
    truth = E.sequence(bundle.model.mean_[None], bundle.model.mean_, lead=0, distance=0.6)[0]
    for nm in NAMES:
        if "flex" in nm and not nm.startswith("thumb"):
            truth[NAMES.index(nm)] = np.radians(-5.0)
    for nm, deg in (("pinky1_flex", -80.0), ("pinky2_flex", -85.0), ("pinky3_flex", -40.0)):
        truth[NAMES.index(nm)] = np.radians(deg)
    ob = observe(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM, stride=1, target_points=None,
                 smooth=0, segmenter=Segmenter(forearm="keep"))
    sil = Silhouette(ob.mask, ob.depth, CAM)
    tr = FrameTracker(HAND, TrackerSettings(), synergies=bundle)
    ctx = tr.context
    wrong = truth.copy()
    for nm, deg in (("ring1_flex", -80.0), ("ring2_flex", -85.0), ("ring3_flex", -40.0), ("pinky1_flex", -5.0),
                    ("pinky2_flex", -5.0), ("pinky3_flex", -5.0)):
        wrong[NAMES.index(nm)] = np.radians(deg)
    # the pinky swung onto the ring finger's place, then fitted there (a local minimum)
    wrong[NAMES.index("pinky1_abd")] = np.radians(-25.0 if HAND.handedness == "left" else 25.0)
    wrong, c = ctx.fit(wrong, ob.points, "full", 0, 10, silhouette=sil, normals=ob.normals)
    st = InitSettings()
    th = finger_search_batched(ctx, wrong, ob.points, st, silhouette=sil, normals=ob.normals)
    th_1 = finger_search_batched(ctx, wrong, ob.points, replace(st, finger_pairs=False), silhouette=sil,
                                 normals=ob.normals)
    e = [float(posture_error_deg(x, truth, HAND.pose_mask)) for x in (wrong, th_1, th)]
    print(f"\nring/pinky swapped: {e[0]:.1f} deg, single-finger restarts {e[1]:.1f} deg, with pairs {e[2]:.1f} deg; "
          f"score {score(ctx, wrong, c, sil):.2f}")
    assert e[2] <= 3.0
    assert e[1] > 2.0 * e[2]
