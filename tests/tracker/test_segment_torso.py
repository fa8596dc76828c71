"""Segmentation of a hand held a few centimetres in front of the body, depth only: the arm joins the
hand's surface to the torso's, so the region grew into the torso within the hand's reach; the hand is
the layer in front of it (tracker.segment._in_front)."""
from __future__ import annotations

import numpy as np
import pytest

from handmodel.rigid import euler_to_matrix
from tests.conftest import mask_scores, realistic_frame
from tracker.io.cameras import preset
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.segment.layers import _in_front
from tracker.sim import experiments as E
from tracker.sim.hands import HandShape
from tracker.sim.motions import make_motion
from tracker.sim.noise import NoiseModel
from tracker.sim.render import Clutter, DepthRenderer


def _torso_frame(hand, sensor, scale, gap, frame, motion="open-close"):
    """``(camera, depth, labels)``: frame ``frame`` of ``motion`` (30 frames, seed 0) with a forearm and
    a torso ``gap`` metres behind the hand centre, placed from the motion's mean hand centre."""
    cam_name, noise_name = E.REALISTIC_SENSORS[sensor]
    cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
    shown = HandShape(scale).apply(hand)
    truth = make_motion(motion, hand=shown, frames=30, seed=0).theta
    R = euler_to_matrix(truth[:, 3:6])
    clutter = Clutter.parse(f"forearm,torso={gap}").sized(scale).fixed(
        (truth[:, :3] + R @ E.hand_centre(shown)).mean(axis=0))
    r = DepthRenderer(shown, cam).render(truth[frame], labels=True, clutter=clutter,
                                         incidence=nm.needs_incidence, reflectance=nm.needs_reflectance)
    depth = nm.apply(r.depth, cam, np.random.default_rng([0, frame]), r.cos_incidence, r.reflectance)
    return cam, depth, r.labels


def _mask_scores(cam, depth, labels):
    """``(recall, precision)`` of the default segmenter's mask against the rendered hand's seen pixels."""
    mask = observe(depth, cam).mask
    seen = (labels >= 0) & np.isfinite(depth)
    both = (mask & seen).sum()
    return both / seen.sum(), both / max(mask.sum(), 1)


@pytest.mark.parametrize("sensor, scale, gap, frame", [
    ("realsense", 1.0, 0.03, 10), ("realsense", 1.5, 0.05, 15), ("realsense", 1.5, 0.03, 0),
    ("kinect1", 1.0, 0.03, 15), ("kinect1", 1.5, 0.03, 10)])
def test_torso_a_few_cm_behind_the_hand_is_left_out(hand, sensor, scale, gap, frame):
    """Without colour, a torso 3–5 cm behind the hand filled most of the mask (old precision
    0.06–0.26: the palm circle landed on the torso). The layer in front is the hand and its arm, whose
    forearm the wrist cut then removes: precision ≥ 0.8 (measured 0.88–0.97), recall ≥ 0.9 (0.94–0.98)."""
    recall, precision = _mask_scores(*_torso_frame(hand, sensor, scale, gap, frame))
    assert recall >= 0.9 and precision >= 0.8, (recall, precision)


@pytest.mark.parametrize("sensor, scale, frame", [
    ("realsense", 1.0, 16), ("realsense", 1.0, 21), ("kinect1", 1.5, 17), ("kinect1", 1.5, 22)])
def test_a_turning_hand_a_few_cm_in_front_of_the_body_is_found(hand, sensor, scale, frame):
    """Rotation with the torso 3 cm behind, depth only. The body beside the layer counted as the arm going
    on: realsense x1 (the layer is the hand with its whole free-ended forearm) the wrist cut kept the
    forearm's end (recall 0.00 on both frames); kinect1 x1.5 a thumb touching it was cut as the arm, with
    fingertips (0.75, 0.71). Now the body is behind the layer except where its wide part meets it without a
    step, and the fingers' end of a whole arm is the seed: recall ≥ 0.9 (measured 0.93-0.95), precision
    ≥ 0.8 (0.84-0.96)."""
    recall, precision = _mask_scores(*_torso_frame(hand, sensor, scale, 0.03, frame, motion="rotate"))
    assert recall >= 0.9 and precision >= 0.8, (recall, precision)


@pytest.mark.xfail(strict=True, reason="known limit (docs/known-limits.md): a hand turning in front of the body loses "
                   "fingers that lean back to within 1 cm of it, and the wrist cut then takes the wrong end")
@pytest.mark.parametrize("sensor, scale, frame", [("realsense", 1.0, 20), ("kinect1", 1.5, 25)])
def test_a_turning_hand_a_few_cm_in_front_of_the_body_keeps_its_fingers(hand, sensor, scale, frame):
    """Rotation with the torso 3 cm behind, depth only, still short of a hand's mask: realsense x1 frame 20
    (recall 0.00 before the body beside the layer stopped counting as the arm going on, 0.81 now, precision
    0.90); kinect1 x1.5 frame 25: a finger leaning back is left behind with the body (layer recall 0.76;
    mask recall 0.63 before, 0.82 now).
    Without the layer rule the torso filled the mask (precision 0.05 and 0.23). A hand's mask is recall
    ≥ 0.85 and precision ≥ 0.8 (the open-close frames above: 0.94-0.98, 0.88-0.97)."""
    recall, precision = _mask_scores(*_torso_frame(hand, sensor, scale, 0.03, frame, motion="rotate"))
    assert recall >= 0.85 and precision >= 0.8, (recall, precision)


def _hand_and_arm(body):
    """A 40 × 40 px 'hand' at 0.57 m with a 36 px (4 cm) wide 'arm' below it receding to 0.60 m at the
    image's lower edge, at f = 500 px (1 px ≈ 1.2 mm); with ``body``, a plane at 0.60 m behind both
    (0.12 m², a torso's front within a hand's reach)."""
    d = np.full((300, 280), 0.60 if body else np.nan)
    d[100:140, 120:160] = 0.57
    d[140:300, 122:158] = np.linspace(0.57, 0.60, 160)[:, None]
    return d


def test_the_layer_in_front_of_a_body_is_taken_and_a_hand_alone_is_kept():
    """A plane 3 cm behind a hand whose arm reaches it without a step: the region is the layer in
    front (the hand and the arm where it is more than 1 cm in front of the plane), ``behind`` the plane
    (around the hand and away from it alike: the body beyond the hand's outline is no arm going on), the
    seed on the hand. The same hand and arm with nothing behind keep their region."""
    for body in (True, False):
        d = _hand_and_arm(body)
        region = np.isfinite(d)
        seed = np.zeros(d.shape, bool)
        seed[110:130, 130:150] = True
        out, behind, new_seed, _ = _in_front(region, d, seed, 500.0)
        if body:
            assert out[100:140, 120:160].all() and not out[:95].any() and not out[:, :115].any()
            assert out[140:240, 122:158].all() and not out[-40:].any()   # the arm until 1 cm off the plane
            assert behind[97, 140] and behind[120, 117] and behind[200, 60] and new_seed[120, 140]
        else:
            assert (out == region).all() and not behind.any() and (new_seed == seed).all()


def test_plane_behind_a_patch_is_left_out_of_the_mask():
    """The whole segmenter on the constructed body: the hand is found without the plane behind it."""
    m = Segmenter(coarse=1)(_hand_and_arm(True), focal=500.0)
    assert m[105:135, 125:155].all() and not m[:95].any() and not m[:, :115].any(), m.sum()


def _hand_window(cam, depth, labels):
    """The tracker's window (:func:`tracker.observe.hand_window`) around the rendered hand's seen pixels."""
    from tracker.observe import hand_window

    vv, uu = np.nonzero((labels >= 0) & np.isfinite(depth))
    z = depth[vv, uu]
    P = np.stack([(uu - cam.cx) * z / cam.fx, (vv - cam.cy) * z / cam.fy, z], axis=1)
    return hand_window(P, cam)


@pytest.mark.parametrize("frame", [0, 5])
def test_a_big_hand_before_a_close_torso_is_segmented_whole_frame_not_in_its_window(hand, frame):
    """Kinect v1, a 1.5× hand with a torso 4 cm behind, depth only (the realistic scene's noise seed):
    in the tracker's window the layer rule saw too little of the torso to call it a body and kept the
    torso as the hand (precision 0.3); the window's result is refused and the whole frame segmented."""
    cam, depth, _, labels = realistic_frame(hand, "kinect1", 1.5, "forearm,torso=0.04", frame, noise_seed=5)
    window = _hand_window(cam, depth, labels)
    assert Segmenter().in_window(depth, window[0], focal=cam.fx, expected=window[1]) is None
    ob = observe(depth, cam, window=window)
    assert ob.window is None  # the whole frame was segmented
    recall, precision = mask_scores(ob.mask, depth, labels)
    assert recall >= 0.85 and precision >= 0.9, (recall, precision)



def _with_and_without(hand, monkeypatch, sensor, scale, rule, off):
    """``((recall, precision), (recall, precision))`` of the default segmenter's mask on the first frame
    of the realistic depth-only scene with a torso 4 cm behind (its noise seed): as it is, then with
    ``tracker.segment.forearm``'s ``rule`` replaced by ``off``."""
    import tracker.segment.forearm as S

    cam, depth, _, labels = realistic_frame(hand, sensor, scale, "forearm,torso=0.04", 0, noise_seed=5)
    now = mask_scores(observe(depth, cam).mask, depth, labels)
    monkeypatch.setattr(S, rule, off)
    return now, mask_scores(observe(depth, cam).mask, depth, labels)


def test_the_body_seen_through_a_gap_in_the_hand_does_not_make_its_side_go_on(hand, monkeypatch):
    """SR305, 1.0× hand: the torso seen between thumb and palm, joined to the hand's surface by the
    sensor's noise, was taken as the hand's surface going on past the region like an arm; the palm was
    then placed on the forearm and the whole forearm kept (precision 0.34, the run's first frame lost).
    A piece held in a notch of the outline no longer goes on (``_outside_pieces``): precision ≥ 0.85,
    recall ≥ 0.9; with every piece going on, as before, precision < 0.5."""
    (recall, precision), (_, before) = _with_and_without(hand, monkeypatch, "realsense", 1.0, "_outside_pieces",
                                                         lambda pieces, solid, rad: pieces)
    assert recall >= 0.9 and precision >= 0.85, (recall, precision)
    assert before < 0.5, before


def test_a_small_hands_finger_bases_are_no_palm(hand, monkeypatch):
    """Kinect v1, 0.8× hand: at the search's resolution the spread fingers lie a pixel or two apart, the
    closing that mends no-data cracks joined their bases into a blob as wide as the palm, and the palm
    circle placed there cut the hand mid-palm (recall 0.65; the run lost its first frame, 34.7 mm). Palm
    places are now those the mask before closing fills (``_filled_places``: the blob's 0.66–0.77, the
    palm's 0.99): recall ≥ 0.9; without that test, < 0.75."""
    (recall, precision), (before, _) = _with_and_without(hand, monkeypatch, "kinect1", 0.8, "_filled_places",
                                                         lambda cand, raw, rad: cand)
    assert recall >= 0.9 and precision >= 0.7, (recall, precision)
    assert before < 0.75, before


@pytest.mark.parametrize("frame", [10, 14])
def test_an_arm_stub_does_not_make_the_fingers_the_arm(frame):
    """The report's realistic scene Kinect v1, the tracker's hand at 1.0×, the torso 4 cm behind, depth only
    (seed 0): the region's reach cut the arm to a stub as wide as the palm, which counted among the fingers
    in the wrist cut's opposite-fingers test and outweighed them, so the index, middle and ring fingers held
    together were "a wide part opposite the fingers" and cut as the arm (that run 11.2 mm). A part as wide
    as an arm that reaches less far than one no longer weighs as a finger: ≥ 90 % of the fingers' seen
    pixels stay (measured 0.97 on both frames; before 0.46 and 0.76)."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND

    j = list(E.REALISTIC_SCENES).index("+torso 4 cm")
    cam, depth, _, labels = realistic_frame(HandModel.load(TRACKING_HAND), "kinect1", 1.0,
                                            E.REALISTIC_SCENES["+torso 4 cm"], frame, j, seed=0)
    fingers = (labels >= 4) & np.isfinite(depth)  # segments past the palm and the thumb's three
    kept = (observe(depth, cam).mask & fingers).sum() / fingers.sum()
    assert kept >= 0.9, kept
