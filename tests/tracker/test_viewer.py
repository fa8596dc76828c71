"""The 3-D viewer: ``tracker track --rerun`` writes an ``.rrd`` headless that holds, for every
frame, the depth image, the segmentation, the points used, the fitted hand and the scalars, each
equal to what the tracker saw and wrote (read back with Rerun's own reader)."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from typer.testing import CliRunner

pytest.importorskip("rerun")

from tracker.cli import app  # noqa: E402
from tracker.io.recording import Recording  # noqa: E402
from tracker.io.tracking_file import read_tracking, tracked_hand  # noqa: E402
from tracker.viewer import FRAME_ENTITIES, HAND_ENTITIES, RerunLog, read_frame, read_frames, snapshot_png  # noqa: E402


def _ok(args):
    r = CliRunner().invoke(app, [str(a) for a in args], env={"SYNERGY_PATH": ""})
    assert r.exit_code == 0, r.output
    return r


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    d = tmp_path_factory.mktemp("viewer")
    _ok(["synth", "--frames", "4", "--noise", "none", "-o", d / "rec"])
    # the rendered hand is the model's size: the logged mesh is then the model's own
    _ok(["track", d / "rec", "-o", d / "t.csv", "--rerun", d / "t.rrd", "--no-check-hand", "--hand-scale", "1"])
    return d


def test_every_frame_has_its_entities(tracked):
    frames = read_frames(tracked / "t.rrd")
    for ent in FRAME_ENTITIES + HAND_ENTITIES:
        assert frames.get(ent) == [0, 1, 2, 3], (ent, frames.get(ent))


def test_logged_data_is_what_was_tracked(tracked):
    """The depth image is the recording's (mm), the points as many as the tracker used, the mesh and
    the keypoints the hand at the θ written to the CSV, the fit error the CSV's."""
    rec = Recording.open(tracked / "rec")
    df, meta = read_tracking(tracked / "t.csv")
    hand = tracked_hand(meta)  # the model, handedness and size the header says were tracked
    mesh = hand.mesh()
    for k in (0, 3):
        got = read_frame(tracked / "t.rrd", k)
        fmt = got["world/camera/depth"]["DepthImage:format"][0]
        depth = np.frombuffer(np.asarray(got["world/camera/depth"]["DepthImage:buffer"][0], np.uint8).tobytes(),
                              np.uint16).reshape(fmt["height"], fmt["width"])
        want = rec[k].depth * 1000
        assert np.array_equal(depth == 0, ~np.isfinite(want))
        assert np.abs(depth[depth > 0] - want[np.isfinite(want)]).max() <= 0.5
        mask = np.asarray(got["world/camera/mask"]["SegmentationImage:buffer"][0]).reshape(depth.shape)
        pts = np.asarray(got["world/points"]["Points3D:positions"], float)
        assert len(pts) == df["points"].iloc[k] > 100 and mask.sum() >= len(pts)
        theta = df[hand.dof_names].to_numpy(float)[k]
        V = np.asarray(got["world/hand/mesh"]["Mesh3D:vertex_positions"], float)
        assert np.abs(V - mesh.pose(theta)).max() < 1e-5  # float32 in the file
        kp = np.asarray(got["world/hand/keypoints"]["Points3D:positions"], float)
        assert np.abs(kp - hand.keypoints(theta)).max() < 1e-5
        assert len(got["world/hand/skeleton"]["LineStrips3D:strips"]) == hand.n_nodes - 1
        assert got["tracking/fit_mm"]["Scalars:scalars"][0] == pytest.approx(df["fit_mm"].iloc[k], rel=1e-6)
        assert got["tracking/status"]["TextLog:text"] == [df["status"].iloc[k]]
    pin = read_frame(tracked / "t.rrd", 0)["world/camera"]
    K = np.asarray(pin["Pinhole:image_from_camera"][0], float).reshape(3, 3).T  # column-major in Rerun
    cam = rec.camera
    assert np.allclose(K, [[cam.fx, 0, cam.cx + 0.5], [0, cam.fy, cam.cy + 0.5], [0, 0, 1]], atol=1e-3)


def test_a_frame_without_fit_clears_the_hand(tmp_path, hand):
    """A frame whose θ is not finite (nothing fitted yet) clears the hand instead of showing the last one."""
    from types import SimpleNamespace

    from tracker.io.cameras import preset
    from tracker.io.recording import Frame
    from tracker.track import FrameResult

    cam = preset("kinect1")
    depth = np.full(cam.shape, 0.8, np.float32)
    ob = SimpleNamespace(points=np.zeros((5, 3)), mask=np.zeros(cam.shape, bool))
    with RerunLog(cam, tmp_path / "v.rrd") as log:
        log.log_frame(Frame(0, 0.0, depth), FrameResult(hand.zero(), "reinit", 1.0, 5, 5, 10.0), ob, hand)
        log.log_frame(Frame(1, 0.1, depth), FrameResult(np.full(26, np.nan), "lost", np.nan, 0, 5, 10.0), None, hand)
    frames = read_frames(tmp_path / "v.rrd")
    assert frames["world/hand/mesh"] == [0] and frames["world/hand"] == [1]
    assert frames["world/points"] == [0, 1]


def test_snapshot_png(tracked, tmp_path):
    """The picture of a logged frame shows the mask and where the fitted wrist is (its first panel):
    the mask's outline was white on a white no-depth background, and an upside-down fit looked right."""
    from PIL import Image

    from tracker.plots import OVERLAY_COLOURS

    png = snapshot_png(tracked / "t.rrd", tmp_path / "view.png", frame=2)
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    img = np.asarray(Image.open(png).convert("RGB"), float) / 255
    left = img[:, : img.shape[1] // 2]

    def share(colour, tol):
        return np.all(np.abs(left - np.asarray(colour)) < tol, axis=-1).sum()

    assert share(OVERLAY_COLOURS["mask"], 0.25) > 50 and share(OVERLAY_COLOURS["wrist"], 0.12) > 10


def test_show_draws_a_rerun_recording(tracked, tmp_path):
    """tracker show takes the .rrd too: a picture of a logged frame where no viewer can run."""
    r = _ok(["show", tracked / "t.rrd", "-o", tmp_path / "v.png", "--frame", "1"])
    assert f"wrote {tmp_path / 'v.png'}" in r.stdout and (tmp_path / "v.png").stat().st_size > 20_000
    for args, reason in [(["--frame", "7"], "t.rrd: holds no frame 7 (frames 0–3)"),
                         (["--every", "2"], "t.rrd: --every does not apply to a Rerun recording")]:
        r = CliRunner().invoke(app, ["show", str(tracked / "t.rrd"), "-o", str(tmp_path / "w.png"), *args])
        assert r.exit_code == 2 and reason in r.stderr and r.stderr.count("\n") == 1, r.output
    assert not (tmp_path / "w.png").exists()
    # a cut file: one line (rerun's own "no footer" warning was printed before it)
    import warnings

    from tracker.errors import TrackerError

    (tmp_path / "cut.rrd").write_bytes((tracked / "t.rrd").read_bytes()[:60_000])
    r = CliRunner().invoke(app, ["show", str(tmp_path / "cut.rrd"), "-o", str(tmp_path / "w.png")])
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and "cut.rrd: not a readable Rerun recording" in r.stderr, \
        r.output
    with warnings.catch_warnings(record=True) as caught:  # pytest hides warnings from the CLI run above
        warnings.simplefilter("always")
        with pytest.raises(TrackerError, match="not a readable Rerun recording"):
            read_frames(tmp_path / "cut.rrd")
    assert not caught, [str(w.message) for w in caught]


def test_rerun_output_refused_like_the_others(tracked):
    """An existing .rrd is not overwritten, a wrong suffix is refused, both before any frame is tracked."""
    for rrd, reason in [(tracked / "t.rrd", "exists and is never overwritten"),
                        (tracked / "t.txt", "must end in .rrd")]:
        r = CliRunner().invoke(app, ["track", str(tracked / "rec"), "-o", str(tracked / "x.csv"), "--rerun", str(rrd)])
        assert r.exit_code == 2 and reason in r.stderr and r.stderr.count("\n") == 1, r.output
        assert not (tracked / "x.csv").exists()


def test_missing_extra_names_the_install(tracked, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun now raises ImportError
    monkeypatch.delitem(sys.modules, "tracker.viewer", raising=False)
    r = CliRunner().invoke(app, ["track", str(tracked / "rec"), "-o", str(tracked / "y.csv"), "--rerun",
                                 str(tracked / "y.rrd")])
    assert r.exit_code == 2, r.output
    assert r.stderr == "error: --rerun: the 3-D viewer needs rerun-sdk (pip install 'synergistic-hand-tracking[viz]')\n"
    assert not (tracked / "y.csv").exists()


def test_a_viewer_gone_does_not_cost_the_file(tmp_path, hand, monkeypatch):
    """A spawned viewer that is unreachable at the end (closed, or no screen) makes the flush fail;
    the file is still checked and published, and the reason kept as a warning."""
    from tracker.io.cameras import preset
    from tracker.io.recording import Frame
    from tracker.track import FrameResult

    cam = preset("kinect1")
    log = RerunLog(cam, tmp_path / "v.rrd")
    log.log_frame(Frame(0, 0.0, np.full(cam.shape, 0.8, np.float32)),
                  FrameResult(hand.zero(), "reinit", 1.0, 5, 5, 10.0), None, hand)
    real = log.rec.flush

    def flush(timeout_sec=None):
        real()
        raise RuntimeError("gRPC has been unable to connect for 9s")

    monkeypatch.setattr(log.rec, "flush", flush)
    assert log.close() == tmp_path / "v.rrd"
    assert "not reachable (gRPC has been unable to connect for 9s)" in log.warning_
    assert read_frames(tmp_path / "v.rrd")["world/camera/depth"] == [0]
