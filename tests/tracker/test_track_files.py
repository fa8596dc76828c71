"""``tracker track`` on a recording file read in place: the real D435 bag with the hand named on the
command line, a time range and frame step; those options refused for a recording folder."""
from __future__ import annotations

from typer.testing import CliRunner

from tests.conftest import shared
from tracker.cli import app
from tracker.io.tracking_file import read_tracking

BAG = ("sensor_recordings", "librealsense_single_depth_color_640x480.bag")


def _cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_track_a_bag_in_place_with_the_hand_and_frames_chosen(tmp_path):
    bag = shared(*BAG)
    r = _cli("track", bag, "--hand", "right", "--no-check-hand", "-o", tmp_path / "t.csv")
    assert r.exit_code == 0, r.output
    df, meta = read_tracking(tmp_path / "t.csv")
    assert len(df) == 2 and meta["handedness"] == "right"  # a file does not say: the option does
    r = _cli("track", bag, "--every", "2", "--no-check-hand", "-o", tmp_path / "e.csv")
    assert r.exit_code == 0, r.output
    df, meta = read_tracking(tmp_path / "e.csv")
    assert len(df) == 1 and meta["handedness"] == "left"


def test_file_options_refused_for_a_folder_and_a_bad_hand(tmp_path):
    from tracker.sim.synthesize import synthesize

    synthesize("open-close", "kinect1", None, tmp_path / "rec", frames=2)
    r = _cli("track", tmp_path / "rec", "--every", "2", "-o", tmp_path / "t.csv")
    assert r.exit_code == 2 and "--every are for recording files" in r.stderr, r.output
    r = _cli("track", tmp_path / "rec", "--hand", "both", "-o", tmp_path / "t.csv")
    assert r.exit_code == 2 and "--hand: must be left or right" in r.stderr, r.output
    assert not (tmp_path / "t.csv").exists()
