"""The start search's orientation: the both-direction score ranks the right fit above upside-down and
palm↔back flipped ones on rendered frames, the model→data cost sees free space and the silhouette,
and the search finds back-facing and resized hands the right way up."""
import numpy as np
import pytest

from handmodel import HandModel
from handmodel.rigid import euler_to_matrix, matrix_to_euler
from tracker.io.cameras import preset
from handmodel.geometry import surface_samples
from tracker.correspond import DATA_CAP_MM, Matcher, ModelSamples, Silhouette, data_to_model_mm, model_to_data_mm
from tracker.init import REJECTED_PAIR_MM, data_cost_mm, placements, score
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim.motions import FACING, POSTURES, hand_centre
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

BASE = HandModel.load()
CAM = preset("kinect1")
# a small hand in a grasp covers less than the default segmenter's minimum area
SEG = Segmenter(min_area=0.001)


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def scene(hand, facing, posture, tilt_deg=(10.0, -15.0, 5.0), distance=0.7):
    """θ truth with the hand centre ``distance`` in front of the camera, and what the tracker sees."""
    th = np.zeros(hand.n_dofs)
    th[~hand.pose_mask] = posture
    R = euler_to_matrix(np.radians(tilt_deg)) @ FACING[facing]
    th[3:6] = matrix_to_euler(R)
    th[:3] = np.array([0.0, 0.0, distance]) - R @ hand_centre(hand)
    depth = DepthRenderer(hand, CAM).render(th, labels=False).depth
    ob = observe(depth, CAM, segmenter=SEG)
    return th, ob, Silhouette(ob.mask, ob.depth, CAM)


def turned(hand, theta, axis_hand, deg=180.0):
    """θ rotated by ``deg`` about an axis of the hand frame through the hand's keypoint centroid."""
    th = np.array(theta, float)
    R = euler_to_matrix(th[3:6])
    c = hand.keypoints(th).mean(0)
    Q = R @ euler_to_matrix(np.radians(deg) * np.asarray(axis_hand, float))
    th[3:6] = matrix_to_euler(Q)
    th[:3] = c - Q @ R.T @ (c - th[:3])
    return th


def kp_mm(h1, t1, h2, t2):
    return float(np.mean(np.linalg.norm(h1.keypoints(t1) - h2.keypoints(t2), axis=1)) * 1000.0)


def test_data_cost_measures_every_point_against_the_whole_model(bundle):
    """Each data point costs its distance to the nearest model surface on either side (a point 3 mm
    off the back of the hand, which faces away from the camera, costs 3 mm, not a far miss), capped
    at ``DATA_CAP_MM`` (a point a metre away costs the cap, not a metre); a pair ICP rejected adds
    ``REJECTED_PAIR_MM``; and the score of a fit is that mean, taken from the fit's own points."""
    th, ob, sil = scene(BASE, "palm", POSTURES["open"])
    matcher = Matcher(BASE)
    P, _, N = surface_samples(BASE, th, spacing=0.006)
    away = N[:, 2] > 0.5  # the back of the hand, seen from the camera
    assert away.sum() > 50
    near = P[away] + 0.003 * N[away]
    far = np.array([[0.0, 0.0, 1.7]])
    d = data_to_model_mm(matcher, th, np.vstack([near, far]))
    # (samples where two parts overlap lie closer to the other one)
    assert np.all(d[:-1] <= 3.05) and np.mean(np.abs(d[:-1] - 3.0) < 0.05) >= 0.8, np.round(d[:-1], 2)
    assert d[-1] == DATA_CAP_MM
    tr = FrameTracker(BASE, TrackerSettings(), synergies=bundle)
    corr = matcher(th, ob.points, ob.normals)
    assert corr.points is ob.points or np.array_equal(corr.points, ob.points)
    want = np.minimum(data_to_model_mm(matcher, th, ob.points) + REJECTED_PAIR_MM * ~corr.valid, DATA_CAP_MM)
    assert data_cost_mm(tr.context, th, corr) == pytest.approx(float(want.mean()))
    # the fit's correspondences carry their points, so the score measures the points it was fitted to
    th2, c2 = tr.context.fit(th, ob.points, "full", 0, 2, silhouette=sil, normals=ob.normals)
    assert c2.points is not None and len(c2.points) == len(ob.points)


def test_model_to_data_cost_sees_free_space_and_the_silhouette():
    th, _, sil = scene(BASE, "palm", POSTURES["open"])
    ms = ModelSamples(BASE, spacing=0.006)
    at_truth = model_to_data_mm(ms, th, sil)
    # the true pose: nearly every sample where the camera allows it
    assert np.mean(at_truth) < 0.5 and np.mean(at_truth > 0) < 0.05
    # 20 mm towards the camera: the hand's seen side lies in free space (the camera saw past it),
    # each of its samples costing about 20 − 6 mm (the tolerance)
    near = th.copy()
    near[2] -= 0.020
    c = model_to_data_mm(ms, near, sil)
    _, normals = ms.pose(near)
    assert 11.0 < np.median(c[normals[:, 2] < -0.5]) < 16.0
    # 20 mm away from the camera: behind the seen surface is allowed, except at the silhouette edge
    far = th.copy()
    far[2] += 0.020
    assert np.mean(model_to_data_mm(ms, far, sil)) < 3.0
    # 40 mm sideways: parts leave the silhouette and cost their distance to it, capped
    side = th.copy()
    side[0] += 0.040
    c = model_to_data_mm(ms, side, sil, cap_mm=30.0)
    assert c.max() == 30.0 and np.mean(c) > 5.0


@pytest.mark.parametrize("facing,posture", [("palm", "open"), ("back", "grasp"), ("palm", "pinch")])
def test_upside_down_and_flipped_fits_lose(bundle, facing, posture):
    """The true pose and the two the cloud's principal axes cannot tell from it — turned 180° in the
    palm plane (wrist where the fingertips are) and about the hand's long axis (palm and back
    swapped, a mirror image in silhouette) — each refined by the same fit: the true one scores best,
    by a margin."""
    th, ob, sil = scene(BASE, facing, POSTURES[posture])
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)), synergies=bundle)
    ctx = tr.context
    scores = {}
    for name, start in (("true", th), ("upside down", turned(BASE, th, (0, 0, 1))),
                        ("palm/back flipped", turned(BASE, th, (0, 1, 0)))):
        fitted, corr = ctx.fit(start, ob.points, "full", 2, 10, silhouette=sil, normals=ob.normals)
        scores[name] = score(ctx, fitted, corr, sil)
    print(f"\n{facing} {posture}: " + ", ".join(f"{k} {v:.2f}" for k, v in scores.items()))
    assert scores["true"] < 1.5
    assert scores["upside down"] > scores["true"] + 2.0
    assert scores["palm/back flipped"] > scores["true"] + 2.0


def test_placements_are_centred_on_the_data_by_the_side_facing_the_camera():
    """A back-facing hand: the placement closest to the truth lies within 15 mm of it (placing the
    palm side's centroid on the data put the hand a hand's thickness off, and the flipped fits won)."""
    th, ob, _ = scene(BASE, "back", POSTURES["open"])
    cands = placements(BASE, ob.points, np.zeros(20))
    R = euler_to_matrix(th[3:6])

    def angle(c):
        return np.degrees(np.arccos(np.clip((np.trace(euler_to_matrix(c[3:6]) @ R.T) - 1) / 2, -1, 1)))

    best = min(cands, key=angle)
    offset = np.linalg.norm(BASE.keypoints(best).mean(0) - BASE.keypoints(th).mean(0)) * 1000.0
    print(f"\nclosest placement: {angle(best):.1f} deg, centroid {offset:.1f} mm off")
    assert angle(best) < 30.0
    assert offset < 15.0


@pytest.mark.slow
@pytest.mark.parametrize("scale", [1.3, 1.5])
def test_back_facing_resized_hand_found_the_right_way_up(bundle, scale):
    """A large hand seen from the back, its size known: the start search finds it, not the flipped fit
    (before the both-direction score and the facing-side placements: 56–68 mm, turned 180°)."""
    hand = BASE.scaled(scale)
    th, ob, _ = scene(hand, "back", bundle.model.mean_)
    tr = FrameTracker(BASE, TrackerSettings().replace(scale=dict(hand_scale=scale)), synergies=bundle)
    r = tr.track(ob, CAM)
    err = kp_mm(hand, th, tr.hand, r.theta)
    print(f"\nscale {scale} back-facing: {err:.1f} mm")
    assert err < 5.0


@pytest.mark.slow
def test_the_wrong_hand_is_reported(bundle):
    """A left hand tracked as a right one (the recording's handedness wrong): the check on the first
    frame says the left hand fits clearly better; tracked as the left one, it says nothing."""
    _, ob, _ = scene(BASE, "palm", bundle.model.mean_)
    checks = {}
    for side, hand in (("left", BASE), ("right", BASE.mirrored())):
        tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(start=dict(check_hand=True)), synergies=bundle)
        tr.track(ob, CAM)
        checks[side] = tr.hand_check_
        print(f"\ntracked as {side}: {tr.hand_check_}")
    assert checks["right"].other_side == "left" and checks["right"].other_fits_better
    assert "fits clearly better" in str(checks["right"])
    assert checks["left"].other_side == "right" and not checks["left"].other_fits_better
    assert str(checks["left"]).endswith(": ok")
