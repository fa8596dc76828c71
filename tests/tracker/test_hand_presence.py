"""The hand-presence CNN (issue 38: "whether a hand is there is decided with the detector's hand score"):
the shipped network is sealed; on freshly rendered frames it tells hands from the surfaces a
segmentation takes instead; on the real frames it says hand for every labelled still and no hand for the
real hand-less recordings; in the tracker, a start whose region it calls no hand runs no search."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

pytest.importorskip("onnxruntime", reason="the hand-presence CNN runs on onnxruntime")

from tests.conftest import shared  # noqa: E402
from tracker.errors import TrackerError  # noqa: E402
from tracker.hand_presence import PRESENCE_FORMAT, hand_probability, load_presence, read_presence  # noqa: E402
from tracker.keypoint_cnn import cnn_path  # noqa: E402
from tracker.settings import TrackerSettings  # noqa: E402
from tracker.sim.train_detector import HELDOUT_SEED_OFFSET  # noqa: E402

#: The tests' own scenes: neither the training seed (0) nor the manifest's held-out one.
SEED = 515_151


@pytest.fixture(scope="module")
def model():
    return load_presence()


@pytest.fixture(scope="module")
def scenes():
    from tracker.sim.dataset import DataRecipe
    from tracker.sim.train_presence import PresenceSettings, draw_presence

    return draw_presence(DataRecipe(), PresenceSettings(), SEED, 16)


def test_shipped_network_is_sealed_and_a_flipped_byte_is_refused(tmp_path, model):
    m = model.manifest
    assert m["format"] == PRESENCE_FORMAT and m["family"] == "presence"
    assert m["command"].startswith("tracker train-detector") and "--family presence" in m["command"]
    assert m["heldout_seed"] == m["seed"] + HELDOUT_SEED_OFFSET
    src = cnn_path("hand-presence-cnn")
    for suffix in (".json", ".onnx"):
        shutil.copy(src.with_suffix(suffix), tmp_path / f"p{suffix}")
    assert read_presence(tmp_path / "p.json").manifest == m
    onnx = tmp_path / "p.onnx"
    data = bytearray(onnx.read_bytes())
    data[len(data) // 2] ^= 0x01
    onnx.write_bytes(bytes(data))
    with pytest.raises(TrackerError) as e:
        read_presence(tmp_path / "p.json")
    assert str(onnx) in str(e.value) and "onnx_sha256" in str(e.value) and "\n" not in str(e.value)
    # the keypoint CNN's reader refuses it (another format), and this reader the keypoint CNN
    with pytest.raises(TrackerError, match="manifest"):
        from tracker.keypoint_cnn import read_cnn

        read_cnn(src)
    with pytest.raises(TrackerError, match=PRESENCE_FORMAT):
        read_presence(cnn_path())


def test_unseen_rendered_frames_tell_hands_from_what_a_segmentation_takes_instead(model, scenes):
    """Crops of 16 whole frames the network never saw: hands (true and segmented boxes) against the
    segmentation's misses and hand-sized boxes on arms, torsos, tables and objects."""
    from tracker.sim.train_presence import roc_auc

    X, y, kind = scenes
    assert y.sum() >= 12 and (y == 0).sum() >= 12  # both classes, from every kind of box
    p = model.run(X)
    assert roc_auc(p, y) >= 0.95
    # at the tracker's threshold the hands pass
    assert np.mean(p[y == 1] >= TrackerSettings().start.presence_below) >= 0.95


@pytest.mark.parametrize("motion", ["fist-side", "pinch"])
def test_a_forearm_piece_beside_the_wrist_is_no_hand(model, motion):
    """What a segmentation cut short by its window keeps when it misses the hand: the forearm's piece next to
    the wrist (the rendered forearm's pixels within half a hand's extent of the hand, and a band farther
    down). Each is no hand at the tracker's threshold (1.2.0, trained with boxes beside the hand: at most
    0.028 on these 12 regions; 1.1.0 called a fist-side one 0.31, and in the tracker a forearm piece of the
    SR305 1.5× side fist 0.93)."""
    from scipy.ndimage import distance_transform_edt

    from tests.conftest import harder_frame
    from tracker.sim.clutter import CLUTTER_LABELS

    below = TrackerSettings().start.presence_below
    p = []
    for sensor, scale, frame in (("kinect1", 1.0, 0), ("realsense", 1.5, 22), ("realsense", 0.8, 44)):
        hand, cam, depth, _, labels, _ = harder_frame(motion, sensor, scale, frame)
        seen = labels >= 0
        arm = (labels == CLUTTER_LABELS["forearm"]) & np.isfinite(depth)
        extent = 0.19 * scale * cam.fx / float(np.median(depth[seen & np.isfinite(depth)]))
        away = distance_transform_edt(~seen)
        for lo, hi in ((0.0, 0.5), (0.2, 0.8)):
            piece = arm & (away > lo * extent) & (away <= hi * extent)
            assert piece.sum() >= 50
            p.append(hand_probability(depth, cam, piece, hand.handedness, model=model))
        # the same frame's hand is a hand
        assert hand_probability(depth, cam, seen & np.isfinite(depth), hand.handedness, model=model) >= 0.5
    assert max(p) < below, np.round(p, 3)


def test_hand_less_frames_give_only_not_hands():
    """The recipe's frames without a hand: something is in view (the object, at least), no pixel is hand,
    and every crop of them is labelled no hand."""
    from tracker.sim.dataset import DataRecipe
    from tracker.sim.train_presence import PresenceSettings, hand_less_scene, scene_crops

    seen = 0
    for i in range(6):
        rng = np.random.default_rng([SEED, i])
        c = hand_less_scene(DataRecipe(), rng)
        assert not ((c.parts >= 0) & (c.parts < 21)).any() and c.meta["hand_less"]
        seen += int(np.isfinite(c.depth).sum() > 500)
        X, y, kind = scene_crops(c, rng, PresenceSettings())
        assert len(X) == len(y) and not np.any(y) and "true" not in kind
    assert seen >= 4


def test_auc_is_the_mann_whitney_statistic():
    from tracker.sim.train_presence import roc_auc

    rng = np.random.default_rng(0)
    p, y = rng.random(200), rng.random(200) < 0.4
    brute = np.mean([(a > b) + 0.5 * (a == b) for a in p[y] for b in p[~y]])
    assert roc_auc(p, y) == pytest.approx(brute)
    assert roc_auc(y.astype(float), y) == 1.0 and roc_auc(1.0 - y, y) == 0.0


def test_real_stills_are_hands_and_rank_above_real_hand_less_regions(model):
    """Evaluation only (never trained on): the 19 labelled SR305 stills through the tracker's segmentation
    are hands (1.2.0: 0.9971-1.0; 1.1.0: 0.9941-1.0), and every one ranks above the regions segmented in the
    hand-less D435 and Azure Kinect recordings (a wall's edge 0.016 and 0.022, turned away; a mug on its
    saucer 0.977, not — 1.1.0: 0.73 —: a limit of this network, docs/experiments/detector.md, "Is it a
    hand?")."""
    root = shared("realsense_sr305_lada")
    from tracker.sim.train_presence import evaluate_real

    r = evaluate_real(model, root)
    below = TrackerSettings().start.presence_below
    assert len(r["stills"]) == 19 and min(r["stills"]) >= 0.95
    if r["hand_less_frames"]:
        assert max(r["hand_less_frames"]) < min(r["stills"])
        assert sum(p < below for p in r["hand_less_frames"]) >= 2


def test_bad_input_is_one_line_or_no_answer(model):
    depth = np.full((480, 640), 0.5, np.float32)
    assert np.isnan(hand_probability(depth, "sr305", np.zeros(depth.shape, bool), "left", model=model))
    with pytest.raises(TrackerError, match="mask"):
        hand_probability(depth, "sr305", np.zeros((5, 5), bool), "left", model=model)
    with pytest.raises(TrackerError):
        hand_probability(depth, "sr305", np.ones(depth.shape, bool), "both", model=model)


def test_settings_check_the_threshold():
    for bad in (-0.1, 1.0, float("nan"), True):
        with pytest.raises(TrackerError, match="presence_below"):
            TrackerSettings().replace(start=dict(presence_below=bad)).check()
    assert TrackerSettings.paper().start.presence == "" and TrackerSettings().start.presence == "hand-presence-cnn"


@pytest.fixture(scope="module")
def back_fists():
    """The grasp from the back (the tracker's hand alone, Kinect v1, no noise) open (frame 0) and closed to a
    fist (45, 59): ``(hand, camera, [(frame, depth, true keypoints)])``."""
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.io.cameras import preset
    from tracker.sim.motions import make_motion
    from tracker.sim.render import DepthRenderer

    hand, cam = HandModel.load(TRACKING_HAND), preset("kinect1")
    theta = make_motion("grasp-back", hand=hand).theta
    ren = DepthRenderer(hand, cam)
    return hand, cam, [(f, ren.render(theta[f], labels=False).depth, hand.keypoints(theta[f])) for f in (0, 45, 59)]


def test_a_fist_from_the_back_without_an_arm_is_a_hand(model, back_fists):
    """1.1.0's known miss, mended by 1.2.0's boxes beside the hand: the fists from the back score above the
    tracker's threshold (1.2.0: 0.31 and 0.42; 1.1.0: 0.02 and 0.038), the same hand open 1.0. Still far below
    the open hand: a fist without its arm is the network's least sure hand."""
    from tracker.observe import observe

    _, cam, frames = back_fists
    p = [hand_probability(depth, cam, observe(depth, cam).mask, "left", model=model) for _, depth, _ in frames]
    assert p[0] > 0.99 and min(p[1:]) >= TrackerSettings().start.presence_below, p


def test_the_detected_hand_overrules_the_network(back_fists):
    """Why the network can be on by default: where it calls a hand no hand — here those fists with the bar
    raised to 0.5, above what the network gives them — the keypoint CNN's hand fitted to the region scores
    within ``detector_accept_mm`` (measured 0.13-0.21 mm), so the start goes on and finds the fist (≤ 5 mm
    mean keypoint error; measured 2.7-2.8 mm). Without the detector nothing overrules the network and the
    frame is no hand: the overruling is what keeps it."""
    from synergy.bundle import load_bundle
    from tracker.observe import observe
    from tracker.track import FrameTracker

    hand, cam, frames = back_fists
    bundle = load_bundle("fingerfist")
    st = TrackerSettings().replace(init=dict(threads=1), scale=dict(hand_scale=1.0), start=dict(presence_below=0.5))
    for f, depth, truth in frames[1:]:
        ob = observe(depth, cam, st.observe)
        tr = FrameTracker(hand, st, synergies=bundle)
        r = tr.track(ob, cam)
        assert tr.presence.probability_ < st.start.presence_below, (f, tr.presence.probability_)
        assert r.status == "reinit" and tr.stats.hands_fitted == 1 and tr.stats.not_hands == 0, f
        assert np.linalg.norm(tr.hand.keypoints(r.theta) - truth, axis=1).mean() < 0.005, f
        alone = FrameTracker(hand, st.replace(start=dict(detector="")), synergies=bundle)
        r = alone.track(ob, cam)
        assert r.status == "lost" and alone.stats.not_hands == 1 and alone.stats.hands_fitted == 0, f


def test_a_start_on_no_hand_runs_no_search_and_a_hand_is_still_found():
    """A rendered scene with its hand moved out of view (the torso stays and is segmented): the start asks
    the network, calls it no hand and searches nothing; the same scene with its hand is found as before."""
    from handmodel import HandModel
    from synergy.bundle import load_bundle
    from tests.tracker.test_no_hand import _scene
    from tracker.observe import observe
    from tracker.segment import Segmenter
    from tracker.track import FrameTracker

    right, bundle = HandModel.load(right=True), load_bundle("fingerfist")
    st = TrackerSettings().replace(init=dict(threads=1), start=dict(presence="hand-presence-cnn"))
    empty, cam = _scene(right, "kinect1", "torso", False)
    ob = observe(empty, cam, st.observe, segmenter=Segmenter(plane="keep"))
    assert len(ob.points) >= st.loss.min_points
    tr = FrameTracker(right, st, synergies=bundle)
    r = tr.track(ob, cam)
    # no fit was made: nothing rejected a share of its points, every point counts as unexplained
    assert r.status == "lost" and tr.stats.not_hands == 1 and r.rejected_share == 1.0 and tr.stats.too_few == 0
    # the detected hand did not fit the torso either: nothing overruled the network
    assert tr.stats.hands_fitted == 0
    assert tr.presence.probability_ < st.start.presence_below and tr.scale_ is None
    # without the network the same frame is searched, and its fit's rejections call it no hand
    off = FrameTracker(right, st.replace(start=dict(presence="")), synergies=bundle)
    r = off.track(ob, cam)
    assert r.status == "lost" and off.stats.not_hands == 0 and off.presence is None and r.rejected_share < 1.0
    with_hand, cam = _scene(right, "kinect1", "forearm,torso", True)
    tr = FrameTracker(right, st, synergies=bundle)
    r = tr.track(observe(with_hand, cam, st.observe), cam)
    assert r.status == "reinit" and tr.stats.not_hands == 0 and tr.presence.probability_ >= 0.5


def test_train_detector_presence_bad_input_is_one_line(tmp_path):
    from typer.testing import CliRunner

    from tracker.cli import app

    (tmp_path / "hand-presence-cnn-1.0.0.json").write_text("{}")
    r = CliRunner().invoke(app, ["train-detector", "-o", str(tmp_path), "--family", "presence"])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "exists" in r.stderr, r.stderr


@pytest.mark.slow
def test_training_is_reproducible_from_its_seed(scenes):
    torch = pytest.importorskip("torch", reason="training needs pip install '.[train]'")
    from tracker.sim.train_presence import PresenceSettings, fit

    X, y, _ = scenes
    st = PresenceSettings(epochs=1, batch=8, threads=1)
    (a, la), (b, lb) = fit(X[:24], y[:24], st, 3), fit(X[:24], y[:24], st, 3)
    assert la == lb and all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    c, _ = fit(X[:24], y[:24], st, 4)
    assert not all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), c.state_dict().values()))


def test_cli_names_the_frames_the_network_called_no_hand(tmp_path):
    """``tracker track`` on a recording of the rendered torso without its hand (kept by ``--plane keep``):
    the summary says which test called the frame no hand."""
    from typer.testing import CliRunner

    from handmodel import HandModel
    from tests.tracker.test_no_hand import _scene
    from tracker.cli import app
    from tracker.io.writer import RecordingWriter

    empty, cam = _scene(HandModel.load(right=True), "kinect1", "torso", False)
    with RecordingWriter(tmp_path / "rec", cam, fps=30, handedness="right") as w:
        w.write(empty)
    r = CliRunner().invoke(app, ["track", str(tmp_path / "rec"), "--plane", "keep", "--no-check-hand", "--threads",
                                 "1", "-o", str(tmp_path / "t.csv")])
    assert r.exit_code == 0, r.output
    out = " ".join(r.output.split())
    assert "no hand: on 1 frame what was segmented is no hand (1 that the hand-presence network " \
           "(hand-presence-cnn) called no hand (p < 0.05))" in out
    # the output says which networks made it: name, version and the manifest's seal
    from tracker.io.tracking_file import read_tracking
    from tracker.keypoint_cnn import load_cnn

    _, meta = read_tracking(tmp_path / "t.csv")
    m, k = load_presence().manifest, load_cnn().manifest
    assert meta["presence"] == f"hand-presence-cnn {m['version']} (manifest_sha256 {m['manifest_sha256']})"
    assert meta["detector"] == f"hand-keypoints-cnn {k['version']} (manifest_sha256 {k['manifest_sha256']})"
    r = CliRunner().invoke(app, ["track", str(tmp_path / "rec"), "--plane", "keep", "--no-check-hand", "--threads",
                                 "1", "--no-presence", "-o", str(tmp_path / "u.csv")])
    # without it the torso is searched, sized and refused at the end of the sizes searched
    assert r.exit_code == 0 and "1 fitted at the end of the hand sizes searched" in " ".join(r.output.split())
    _, meta = read_tracking(tmp_path / "u.csv")
    assert meta["presence"] == "" and meta["detector"].startswith("hand-keypoints-cnn ")
    r = CliRunner().invoke(app, ["track", str(tmp_path / "rec"), "--presence", "hand-presence-cnn", "--no-detector",
                                 "-o", str(tmp_path / "v.csv")])
    assert r.exit_code == 2 and "--no-detector: give --presence or --no-detector, not both" in r.stderr, r.output
    r = CliRunner().invoke(app, ["track", str(tmp_path / "rec"), "--presence", "hand-presence-cnn", "--no-presence",
                                 "-o", str(tmp_path / "v.csv")])
    assert r.exit_code == 2 and "--no-presence: give --presence or --no-presence, not both" in r.stderr, r.output
