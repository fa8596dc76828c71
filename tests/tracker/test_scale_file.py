"""The calibrated hand as a file: what ``tracker calibrate`` / ``track --save-hand`` write, tracking on
it without estimating again (``--hand-model FILE``), the guard against scaling it twice, the header,
and the command line's errors on bad hand files and existing outputs."""
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from handmodel import HandModel
from tracker import TRACKING_HAND
from tracker.cli import app
from tracker.errors import TrackerError
from tracker.io.tracking_file import read_tracking, tracking_metadata
from tracker.run import settings_for_hand
from tracker.scale import calibrated_hand
from tracker.track import FrameTracker, TrackerSettings

BASE = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


def _cli(*args):
    # wide enough that the summary's cells keep long temporary paths whole (pytest-xdist's are longer)
    return CliRunner().invoke(app, [str(a) for a in args], env={"SYNERGY_PATH": "", "COLUMNS": "200"})


def _one_error_line(r, path):
    assert r.exit_code == 2, r.output
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}"), r.stderr
    assert "Traceback" not in r.output


class _Calibrated:
    """What calibrated_hand reads of a tracker, without tracking: a right hand 1.25× with a long index."""

    base_hand = HandModel.load(right=True)
    scale_ = 1.25
    scale_estimates_ = [1.22, 1.25, 1.27]
    finger_scales_ = {"thumb": 1.0, "index": 1.08, "middle": 1.0, "ring": 0.97, "pinky": 1.0}
    settings = TrackerSettings()


def test_calibrated_hand_file_holds_the_hand_and_its_record(tmp_path):
    hand = calibrated_hand(_Calibrated, recording=tmp_path / "rec", frames=range(5))
    path = hand.save(tmp_path / "me.yaml")
    back = HandModel.load(path)
    th = np.random.default_rng(1).uniform(-0.5, 0.2, 26)
    want = _Calibrated.base_hand.scaled(1.25, {"index2": 1.08, "index3": 1.08, "index_tip": 1.08,
                                               "ring2": 0.97, "ring3": 0.97, "ring_tip": 0.97})
    np.testing.assert_array_equal(back.keypoints(th), want.keypoints(th))
    assert back.handedness == "right" and back.name == "default-calibrated"
    cal = back.calibration
    assert cal["hand_scale"] == 1.25 and cal["scale_estimates"] == [1.22, 1.25, 1.27]
    assert cal["scale_spread"] == pytest.approx(0.02) and cal["frames"] == [0, 1, 2, 3, 4]
    assert cal["finger_lengths"]["index"] == 1.08 and cal["recording"] == str(tmp_path / "rec")
    assert cal["tool"].startswith("synergistic-hand-tracking ")
    base = back.provenance["base_model"]
    assert (base["name"], base["sha256"]) == ("default", BASE.sha256)
    # the shipped model is no calibrated hand
    assert BASE.calibration is None


def test_a_calibrated_file_is_tracked_as_it_is_unless_auto_is_asked(tmp_path):
    path = calibrated_hand(_Calibrated).save(tmp_path / "me.yaml")
    hand = HandModel.load(path, right=False)
    auto = TrackerSettings()
    assert settings_for_hand(hand, auto).scale.hand_scale == 1.0  # the default "auto" is not asked for
    assert settings_for_hand(hand, auto, hand_scale_asked=True).scale.hand_scale == "auto"
    assert settings_for_hand(hand, auto.replace(scale=dict(hand_scale=1.0)), hand_scale_asked=True).scale.hand_scale == 1.0
    with pytest.raises(TrackerError, match=r"me.yaml: is a calibrated hand .* --hand-scale 1.25 would scale it again"):
        settings_for_hand(hand, auto.replace(scale=dict(hand_scale=1.25)), hand_scale_asked=True)
    # the model file's hand: the settings as they are
    assert settings_for_hand(BASE, auto).scale.hand_scale == "auto"
    tr = FrameTracker(hand, settings_for_hand(hand, auto))
    meta = tracking_metadata("rec", tr)
    assert meta["hand_model"] == f"default-calibrated {hand.sha256}" and meta["hand_model_file"] == str(path)
    assert meta["hand_calibration"].startswith(f"this file's hand: size 1.25 × default {BASE.sha256}")
    assert meta["hand_scale"] == "1.0000 (the hand file's calibrated hand as it is)"


@pytest.mark.slow
def test_tracking_on_the_calibrated_file_matches_the_automatic_run(bundle, tmp_path):
    """A hand rendered 1.2× (the model's proportions) in front of its forearm and torso under Kinect v1
    noise: the hand the automatic run calibrated, written and read back, tracks the same frames as
    well (mean keypoint error within 0.5 mm; measured 1.89 vs 1.93 mm, the model size 9.6) without estimating its size
    again — while the model's own hand, unscaled, is far off."""
    from tracker.io.cameras import preset
    from tracker.sim.experiments import run_scene
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion
    from tracker.sim.noise import NoiseModel

    shown = HandShape(1.2).apply(BASE)
    truth = make_motion("open-close", hand=shown, frames=16).theta
    cam, noise = preset("kinect1"), NoiseModel.preset("kinect1")

    def run(hand, settings):
        tr = FrameTracker(hand, settings, synergies=bundle)
        return tr, run_scene(BASE, shown, truth, cam, tr, clutter="forearm,torso", noise=noise, seed=3)

    auto, r_auto = run(BASE, TrackerSettings())
    assert len(auto.scale_estimates_) == auto.settings.scale.frames and abs(auto.scale_ / 1.2 - 1) <= 0.03
    path = calibrated_hand(auto, recording="scene", frames=range(5)).save(tmp_path / "me.yaml")
    hand = HandModel.load(path, right=False)
    filed, r_file = run(hand, settings_for_hand(hand, TrackerSettings()))
    assert filed.scale_ == 1.0 and filed.scale_estimates_ == []
    e_auto, e_file = np.nanmean(r_auto["keypoint_mm"]), np.nanmean(r_file["keypoint_mm"])
    _, r_model = run(BASE, TrackerSettings().replace(scale=dict(hand_scale=1.0)))
    print(f"\nkeypoint error: auto {e_auto:.2f}, hand file {e_file:.2f}, "
          f"model size {np.nanmean(r_model['keypoint_mm']):.2f} mm")
    assert e_file <= e_auto + 0.5 and e_file <= 5.0
    assert np.nanmean(r_model["keypoint_mm"]) > e_file + 3.0


@pytest.fixture(scope="module")
def rec(tmp_path_factory):
    d = tmp_path_factory.mktemp("handfile")
    r = _cli("synth", "--frames", "6", "--hand-scale", "1.2", "--noise", "none", "-o", d / "rec")
    assert r.exit_code == 0, r.output
    return d


@pytest.mark.slow
def test_the_summary_says_what_a_size_number_brings_back(rec, tmp_path):
    """The automatic size is printed with how to reuse it: ``--hand-scale X`` is the size alone, so
    with finger lengths estimated the summary says the hand file brings them back (a new user took the
    number for the whole hand); without them the number is the whole of it."""
    r = _cli("track", rec / "rec", "-o", tmp_path / "a.csv", "--no-check-hand")
    assert r.exit_code == 0, r.output
    _, meta = read_tracking(tmp_path / "a.csv")
    size = meta["hand_scale"].split()[0]
    assert "finger lengths" in meta["hand_scale"], meta["hand_scale"]
    text = " ".join(r.output.split())
    assert f"reuse it with --hand-scale {size} (the size only) or --save-hand FILE (with the finger lengths)" in text
    r = _cli("track", rec / "rec", "-o", tmp_path / "b.csv", "--no-check-hand", "--no-finger-lengths")
    assert r.exit_code == 0, r.output
    size = read_tracking(tmp_path / "b.csv")[1]["hand_scale"].split()[0]
    text = " ".join(r.output.split())
    assert f"reuse it with --hand-scale {size} or --save-hand FILE" in text and "size only" not in text


@pytest.mark.slow
def test_calibrate_then_track_on_the_file(rec, tmp_path):
    """``tracker calibrate`` writes the hand of the first frames (every frame tracked until the size and
    finger lengths are settled: their work spread over the frames, ``scale.budget``, here the whole
    six-frame recording); ``track --hand-model`` uses it as it is and says so; neither overwrites an
    existing file."""
    hand = tmp_path / "me.yaml"
    r = _cli("calibrate", rec / "rec", "-o", hand)
    assert r.exit_code == 0, r.output
    assert f"size (× {TRACKING_HAND})" in r.output and f"wrote {hand}" in r.output
    cal = yaml.safe_load(hand.read_text())["provenance"]["calibration"]
    assert abs(cal["hand_scale"] / 1.2 - 1) <= 0.03 and cal["frames"] == list(range(6))
    assert len(cal["scale_estimates"]) == 5 and cal["finger_lengths"] is not None
    before = hand.read_bytes()
    _one_error_line(_cli("calibrate", rec / "rec", "-o", hand), hand)
    assert hand.read_bytes() == before
    out = tmp_path / "t.csv"
    r = _cli("track", rec / "rec", "--hand-model", hand, "-o", out, "--no-check-hand")
    assert r.exit_code == 0, r.output
    _, meta = read_tracking(out)
    assert meta["hand_model_file"] == str(hand) and meta["hand_scale"].startswith("1.0000 (the hand file's")
    assert HandModel.load(hand).sha256 in meta["hand_model"]
    # --save-hand beside a calibrated file: nothing is calibrated in that run
    _one_error_line(_cli("track", rec / "rec", "--hand-model", hand, "-o", tmp_path / "u.csv",
                         "--save-hand", tmp_path / "again.yaml"), tmp_path / "again.yaml")


def test_bad_hand_files_are_one_line_naming_the_file(rec, tmp_path):
    corrupt = tmp_path / "corrupt.yaml"
    corrupt.write_text("joints: [\n")
    wrong = rec / "rec" / "recording.yaml"
    for path in (tmp_path / "missing.yaml", corrupt, wrong):
        _one_error_line(_cli("track", rec / "rec", "--hand-model", path, "-o", tmp_path / "o.csv"), path)
    assert not (tmp_path / "o.csv").exists()


def test_existing_hand_output_is_never_overwritten(rec, tmp_path):
    taken = tmp_path / "taken.yaml"
    taken.write_text("mine\n")
    _one_error_line(_cli("track", rec / "rec", "-o", tmp_path / "o.csv", "--save-hand", taken), taken)
    _one_error_line(_cli("calibrate", rec / "rec", "-o", taken), taken)
    assert taken.read_text() == "mine\n"
    _one_error_line(_cli("calibrate", rec / "rec", "-o", tmp_path / "hand.txt"), tmp_path / "hand.txt")


@pytest.mark.slow
def test_calibrate_each_on_real_stills(tmp_path):
    """``tracker calibrate REC --each`` on five real SR305 stills of one hand (230536_30 … _110,
    imported as one recording): every frame fitted from its own start, the file records it, and
    the finger lengths go the ways this hand's labelled tips lie against the model's at the model's
    proportions (default tracking, along each finger's last bone: thumb tips beyond the model's on 17
    of the 18 frames where the thumb's last bone is seen, index short of them on 15 of 19, little finger
    on 14 of 18): thumb > 1, index and little finger < 1 (measured 1.08,
    0.97, 0.95; size 1.27, estimates 1.26–1.36; on an AMD EPYC 1.075, 0.932, 0.987, size 1.268 — the little
    finger 1.013 before the finger lengths' probes also started from the coupled last joint; with the
    fingerfist synergies, as tracking uses them, 1.059, 0.904, 0.885). Tracking from frame to frame would follow none of
    these jumps (0.7 s apart): the recording's own calibration runs on its first frame alone."""
    from tests.conftest import shared

    root = shared("realsense_sr305_lada")
    stills = tmp_path / "stills"
    stills.mkdir()
    for k, f in enumerate((30, 50, 70, 90, 110)):
        (stills / f"{k}.png").symlink_to(root / f"20210326-230536_{f}.png")
    assert _cli("import", stills, "--camera", "sr305", "-o", tmp_path / "rec").exit_code == 0
    hand = tmp_path / "me.yaml"
    r = _cli("calibrate", tmp_path / "rec", "--each", "--hand", "right", "-o", hand)
    assert r.exit_code == 0, r.output
    assert "5 frames each from its own start" in " ".join(r.output.split())
    cal = yaml.safe_load(hand.read_text())["provenance"]["calibration"]
    assert cal["each_frame"] is True and cal["frames"] == [0, 1, 2, 3, 4] and len(cal["scale_estimates"]) == 5
    f = cal["finger_lengths"]
    assert f["thumb"] > 1.02 and f["index"] < 0.99 and f["pinky"] < 0.99, f
    assert 1.15 <= cal["hand_scale"] <= 1.4, cal["hand_scale"]


def test_calibrate_and_save_hand_give_the_same_hand(tmp_path):
    """``tracker calibrate REC`` and ``tracker track REC --save-hand`` observe the frames alike (the
    hand's window once it is tracked), so they write the same hand: size, every estimate, finger
    lengths. Before, calibrate observed every frame whole: its third estimate here was 1.2388 against
    track's 1.2450 and the middle finger 1.078 against 1.000 (found by a new user). All 19 frames imported as one recording, as that user did:
    the size's later estimates come from frames the hand is tracked into."""
    from tests.conftest import shared

    root = shared("realsense_sr305_lada")
    assert _cli("import", root, "--camera", "sr305", "--hand", "right", "-o", tmp_path / "rec").exit_code == 0
    r = _cli("calibrate", tmp_path / "rec", "-o", tmp_path / "c.yaml")
    assert r.exit_code == 0, r.output
    r = _cli("track", tmp_path / "rec", "-o", tmp_path / "t.csv", "--save-hand", tmp_path / "t.yaml",
             "--no-check-hand")
    assert r.exit_code == 0, r.output
    c, t = (yaml.safe_load((tmp_path / n).read_text())["provenance"]["calibration"] for n in ("c.yaml", "t.yaml"))
    for key in ("hand_scale", "scale_estimates", "finger_lengths"):
        assert c[key] == t[key], (key, c[key], t[key])
