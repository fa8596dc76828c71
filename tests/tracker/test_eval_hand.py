"""``tracker eval`` judges keypoints where the joints really are: the estimate on the hand that was
tracked (the header's model file, size and finger lengths), the truth on the hand that was rendered
(``truth_hand.yaml``). On the default model for both, a wrong size estimate did not show at all."""
from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from handmodel import HandModel
from handmodel.dofs import DOF_NAMES
from tracker import TRACKING_HAND
from tracker.cli import app
from tracker.errors import TrackerError
from tracker.io.recording import Recording
from tracker.io.tracking_file import tracked_hand, write_tracking


def _run(args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"SYNERGY_PATH": "", "COLUMNS": "120"})


@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """A 4-frame recording of a hand 1.3× the model (noise-free)."""
    d = tmp_path_factory.mktemp("evalhand") / "rec"
    r = _run(["synth", "--frames", "4", "--hand-scale", "1.3", "--noise", "none", "-o", d])
    assert r.exit_code == 0, r.output
    return d


def _output(rec, path, shape):
    """A tracking output whose θ are the truth's, as tracked on the tracker's hand (the one ``synth``
    renders, :data:`tracker.TRACKING_HAND`) resized by ``shape``."""
    hand = HandModel.load(TRACKING_HAND)
    truth = Recording.open(rec).truth
    df = truth[["frame", "time_s"]].assign(status="tracked", fit_mm=1.0, points_used=500, points=900, ms=5.0)
    meta = {"recording": str(rec), "hand_model": f"{hand.name} {hand.sha256}", "handedness": hand.handedness,
            "hand_model_file": str(hand.path), "hand_shape": json.dumps(shape) if shape else ""}
    write_tracking(path, df.join(truth[list(DOF_NAMES)]), meta)
    return path


def _keypoint_mm(output):
    m = re.search(r"keypoint_error_mean_mm\s*\W\s*([0-9.]+)", output)
    assert m, output
    return float(m.group(1))


def test_the_right_size_scores_zero_and_a_wrong_one_does_not(big, tmp_path):
    right = _run(["eval", big, _output(big, tmp_path / "right.csv", {"scale": 1.3, "fingers": {}})])
    wrong = _run(["eval", big, _output(big, tmp_path / "wrong.csv", {"scale": 1.0, "fingers": {}})])
    assert right.exit_code == 0 and wrong.exit_code == 0, right.output + wrong.output
    assert _keypoint_mm(right.output) < 0.01
    # every joint of a 1.3x hand read on a 1x one: tens of mm (the old evaluation said 0 for both)
    assert _keypoint_mm(wrong.output) > 10


def test_finger_lengths_in_the_header_are_the_tracked_hand():
    hand = HandModel.load()
    meta = {"hand_model": f"{hand.name} {hand.sha256}", "hand_model_file": str(hand.path), "handedness": "left",
            "hand_shape": json.dumps({"scale": 1.1, "fingers": {"index": 1.08}})}
    got = tracked_hand(meta)
    kp0, kp = hand.keypoints(hand.zero()), got.keypoints(got.zero())
    tip, base = hand.keypoint_names.index("index_tip"), hand.keypoint_names.index("middle_tip")
    assert np.linalg.norm(kp[base]) == pytest.approx(1.1 * np.linalg.norm(kp0[base]), rel=1e-9)
    assert np.linalg.norm(kp[tip]) > 1.1 * np.linalg.norm(kp0[tip]) * 1.01


def test_a_changed_or_unreadable_hand_is_refused(tmp_path):
    hand = HandModel.load()
    meta = {"hand_model": f"{hand.name} {'0' * 64}", "hand_model_file": str(hand.path), "handedness": "left"}
    with pytest.raises(TrackerError, match="changed since"):
        tracked_hand(meta, "out.csv")
    meta = {"hand_model": f"{hand.name} {hand.sha256}", "hand_model_file": str(hand.path), "hand_shape": "{scale"}
    with pytest.raises(TrackerError, match="hand_shape"):
        tracked_hand(meta, "out.csv")
    meta = {"hand_model": "mine 123", "hand_model_file": str(tmp_path / "gone.yaml")}
    with pytest.raises(TrackerError, match="cannot be loaded"):
        tracked_hand(meta, "out.csv")
