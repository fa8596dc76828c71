"""``tracker live``: the RealSense source through librealsense's own playback of ``.bag`` files (the
real D435 file and bags written here from synthetic recordings), the same tracking path as
``tracker track``, Ctrl-C, and the one-line errors of a missing camera or extra."""
from __future__ import annotations

import signal
import sys

import numpy as np
import pandas as pd
import pytest
from conftest import import_pyrealsense2, played_by_librealsense, shared
from typer.testing import CliRunner

from tracker.cli import app
from tracker.io.recording import Recording
from tracker.io.tracking_file import read_keypoints, read_tracking

import_pyrealsense2()  # the wheel may be there without the system libusb (.ci/run installs it where it can)
rosbag1 = pytest.importorskip("rosbags.rosbag1")
typesys = pytest.importorskip("rosbags.typesys")

# librealsense's threads are native code: each test runs in a process of its own (conftest: isolated)
pytestmark = pytest.mark.isolated

BAG = ("sensor_recordings", "librealsense_single_depth_color_640x480.bag")


def _run(args):
    return CliRunner().invoke(app, [str(a) for a in args], env={"SYNERGY_PATH": ""})


def write_bag(rec, out, template):
    """A RealSense bag (file format v3) of ``rec``'s depth frames: the static messages of
    ``template`` (a real RealSense Viewer file: device, sensor, stream and option topics), its depth
    camera info with ``rec``'s intrinsics, one ``mono16`` image (and the template's metadata) per frame
    at ``rec``'s rate; colour left out."""
    ts = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    cam = rec.camera
    with rosbag1.Reader(template) as r:
        conns = [c for c in r.connections if "Color_0/image" not in c.topic]
        msgs = list(r.messages(connections=conns))
    w = rosbag1.Writer(out)
    w.open()
    new = {c.id: w.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest,
                                  callerid=c.ext.callerid, latching=c.ext.latching) for c in conns}
    first = min(t for c, t, _ in msgs if c.topic.endswith("Depth_0/image/data"))
    per_frame = [(c, raw) for c, t, raw in msgs if t == first and "/Depth_0/image/" in c.topic]
    for c, t, raw in msgs:
        if "/image/" in c.topic:
            continue
        if c.topic.endswith("Depth_0/info/camera_info"):
            m = ts.deserialize_ros1(raw, c.msgtype)
            m.K = np.array([cam.fx, 0, cam.cx, 0, cam.fy, cam.cy, 0, 0, 1.0])
            m.P = np.array([cam.fx, 0, cam.cx, 0, 0, cam.fy, cam.cy, 0, 0, 0, 1, 0.0])
            raw = ts.serialize_ros1(m, c.msgtype)
        w.write(new[c.id], t, raw)
    for i in range(len(rec)):
        t = first + round(i * 1e9 / rec.fps)
        for c, raw in per_frame:
            if c.topic.endswith("image/data"):
                m = ts.deserialize_ros1(raw, c.msgtype)
                m.header.seq = i
                m.header.stamp.sec, m.header.stamp.nanosec = divmod(t, 10**9)
                m.data = rec.depth_units(i).astype("<u2").view(np.uint8).ravel()
                raw = ts.serialize_ros1(m, c.msgtype)
            w.write(new[c.id], t, raw)
    w.close()
    return out


@pytest.fixture(scope="module")
def synthetic_bag(tmp_path_factory):
    d = tmp_path_factory.mktemp("live")
    r = _run(["synth", "--frames", "5", "--noise", "none", "-o", d / "rec"])
    assert r.exit_code == 0, r.output
    return write_bag(Recording.open(d / "rec"), d / "rec.bag", shared(*BAG)), d / "rec"


def test_real_bag_plays_back_as_pyrealsense2_reports(tmp_path):
    """The D435 file: both depth frames, the intrinsics and depth scale librealsense reports, the
    depth units as stored in the file (read independently with rosbags)."""
    import pyrealsense2 as rs

    bag = shared(*BAG)
    r = _run(["live", "--playback", bag, "-o", tmp_path / "t.csv", "--save", tmp_path / "saved",
              "--rerun", tmp_path / "t.rrd", "--no-check-hand", "--hand-scale", "1"])
    assert r.exit_code == 0, r.output
    df, meta = read_tracking(tmp_path / "t.csv")
    assert df["frame"].tolist() == [0, 1] and meta["recording"] == str(bag)
    saved = Recording.open(tmp_path / "saved")
    pipe, cfg = rs.pipeline(), rs.config()
    cfg.enable_device_from_file(str(bag), repeat_playback=False)
    prof = pipe.start(cfg)
    try:
        k = prof.get_stream(rs.stream.depth).as_video_stream_profile().get_intrinsics()
        scale = prof.get_device().first_depth_sensor().get_depth_scale()
    finally:
        pipe.stop()
    c = saved.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (k.width, k.height, k.fx, k.fy, k.ppx, k.ppy)
    assert c.depth_scale_m == scale and abs(scale - 0.001) < 1e-9
    ts = typesys.get_typestore(typesys.Stores.ROS1_NOETIC)
    with rosbag1.Reader(bag) as rd:
        conns = [x for x in rd.connections if x.topic.endswith("Depth_0/image/data")]
        raw = [ts.deserialize_ros1(m, x.msgtype) for x, _, m in rd.messages(connections=conns)]
    for i, m in enumerate(raw):
        assert np.array_equal(saved.depth_units(i), np.frombuffer(m.data.tobytes(), "<u2").reshape(m.height, m.width))
    from tracker.viewer import read_frames

    assert read_frames(tmp_path / "t.rrd")["world/camera/depth"] == [0, 1]


def test_live_is_the_track_pipeline(synthetic_bag, tmp_path):
    """A bag written here from a synthetic recording: its frames come back unit for unit, and
    tracking them live gives exactly what ``tracker track`` gives on the saved frames."""
    bag, rec = synthetic_bag
    r = _run(["live", "--playback", bag, "-o", tmp_path / "live.csv", "--save", tmp_path / "saved",
              "--keypoints", tmp_path / "kp.csv", "--no-check-hand", "--hand-scale", "1"])
    assert r.exit_code == 0, r.output
    src, saved = Recording.open(rec), Recording.open(tmp_path / "saved")
    assert len(saved) == len(src) == 5
    for i in range(len(src)):
        assert np.array_equal(saved.depth_units(i), src.depth_units(i))
    assert np.allclose([saved.camera.fx, saved.camera.cy], [src.camera.fx, src.camera.cy], rtol=1e-6)
    r = _run(["track", tmp_path / "saved", "-o", tmp_path / "track.csv", "--no-check-hand", "--hand-scale", "1"])
    assert r.exit_code == 0, r.output
    live, lmeta = read_tracking(tmp_path / "live.csv")
    track, tmeta = read_tracking(tmp_path / "track.csv")
    pd.testing.assert_frame_equal(live.drop(columns=["ms", "time_s"]), track.drop(columns=["ms", "time_s"]))
    # the same learned parts as tracker track's defaults; --no-presence takes the network away as it does there
    assert lmeta["presence"] == tmeta["presence"] != "" and lmeta["detector"] == tmeta["detector"] != ""
    r = _run(["live", "--playback", bag, "-o", tmp_path / "np.csv", "--no-check-hand", "--hand-scale", "1",
              "--no-presence"])
    assert r.exit_code == 0, r.output
    _, nmeta = read_tracking(tmp_path / "np.csv")
    assert nmeta["presence"] == "" and nmeta["detector"] == tmeta["detector"]
    assert (live["status"] != "lost").all() and live["fit_mm"].max() < 2.0
    kp, kmeta = read_keypoints(tmp_path / "kp.csv", [])
    assert len(kp) == 5 and kmeta["recording"]


def test_realtime_playback_is_paced_and_says_what_it_published(synthetic_bag, tmp_path):
    """--realtime on a playback: frames at the bag's rate, fits under a budget, the summary counts the
    predicted and dropped frames; every row is a valid status and the fitted ones are the hand."""
    bag, rec = synthetic_bag
    r = _run(["live", "--playback", bag, "-o", tmp_path / "rt.csv", "--no-check-hand", "--hand-scale", "1", "--realtime",
              "--budget-ms", "5000"])
    assert r.exit_code == 0, r.output
    assert "predicted (fit pending)" in r.output and "dropped (late)" in r.output, r.output
    live, _ = read_tracking(tmp_path / "rt.csv")
    assert set(live["status"]) <= {"tracked", "reinit", "predicted", "lost"}
    fitted = live[live["status"].isin(["tracked", "reinit"])]
    assert len(fitted) >= 1 and fitted["fit_mm"].max() < 2.0
    r = _run(["live", "--playback", bag, "-o", tmp_path / "bad.csv", "--budget-ms", "0"])
    assert r.exit_code == 2 and "--budget-ms" in r.output


def test_playback_delivers_every_frame_in_order_however_slow_the_reader(tmp_path_factory, monkeypatch):
    """A 30-frame bag read after a 1 s stall and then slowly: all 30 frames, in order, unit for unit;
    also when the process stalls right after librealsense starts streaming (through a pipeline,
    whose playback starts in real time and keeps one frameset, that lost frames: CI saw 4 of 5)."""
    import time

    import pyrealsense2 as rs

    from tracker.live import RealSenseSource

    class StallingPipeline(rs.pipeline):
        def start(self, *args):
            profile = super().start(*args)
            time.sleep(0.3)  # as a loaded machine can, before the caller's next line
            return profile

    monkeypatch.setattr(rs, "pipeline", StallingPipeline)

    d = tmp_path_factory.mktemp("slow")
    r = _run(["synth", "--frames", "30", "--noise", "none", "-o", d / "rec"])
    assert r.exit_code == 0, r.output
    rec = Recording.open(d / "rec")
    bag = write_bag(rec, d / "rec.bag", shared(*BAG))
    with RealSenseSource(bag) as source:
        scale = source.camera.depth_scale_m
        time.sleep(1.0)
        got = []
        for frame in source:
            got.append(frame)
            time.sleep(0.02)
    assert [f.index for f in got] == list(range(30))
    np.testing.assert_allclose([f.time_s for f in got], np.arange(30) / rec.fps, atol=2e-3)
    for f in got:
        units = np.where(np.isfinite(f.depth), np.rint(f.depth / scale), 0)
        assert np.array_equal(units, rec.depth_units(f.index))


def _aligned_by_librealsense(rs, bag):
    """``(depth units, colour)`` for every depth frame of ``bag``, its colour put on the depth grid by
    ``rs.align``, each depth frame with the colour frame nearest in time (composed into a frameset by a
    processing block; the file is played without a pipeline: ``played_by_librealsense``)."""
    with played_by_librealsense(rs, bag) as (frames, _):
        pending = []
        block = rs.processing_block(lambda f, source: source.frame_ready(source.allocate_composite_frame(pending)))
        queue = rs.frame_queue(4)
        block.start(queue)
        align = rs.align(rs.stream.depth)
        theirs = []
        for d in frames[rs.stream.depth]:
            c = min(frames[rs.stream.color], key=lambda c: abs(c.get_timestamp() - d.get_timestamp()))
            pending[:] = [d, c]
            block.invoke(d)
            fs = align.process(queue.wait_for_frame().as_frameset())
            theirs.append((np.asanyarray(fs.get_depth_frame().get_data()).copy(),
                           np.asanyarray(fs.get_color_frame().get_data()).copy()))
    return theirs


def test_playback_colour_is_librealsense_aligned_colour():
    """``--color`` on the real D435 file: colour on the depth grid agrees with librealsense's own
    ``rs.align`` (an independent implementation: it maps pixel footprints, we take the nearest colour
    pixel) within 20 levels on 95 % of the depth pixels, and is black exactly where align's is, give
    or take the footprint's edge."""
    import pyrealsense2 as rs

    from tracker.io.images import units_to_metres
    from tracker.live import RealSenseSource

    bag = shared(*BAG)
    with RealSenseSource(bag, color=True) as source:
        ours = [(f.depth, f.color) for f in source]
        camera = source.camera
    assert len(ours) == 2 and all(c is not None and c.shape == (480, 640, 3) for _, c in ours)
    theirs = _aligned_by_librealsense(rs, bag)
    # the file holds two depth frames and one colour frame: both depth frames are compared
    assert len(theirs) == len(ours) == 2
    for units, color in theirs:  # matched to ours by the depth itself
        depth = units_to_metres(units, camera)
        (mine,) = [c for d, c in ours if np.array_equal(d, depth, equal_nan=True)]
        valid = np.isfinite(depth)
        diff = np.abs(mine.astype(int) - color.astype(int)).max(-1)[valid]
        assert (diff <= 20).mean() > 0.95
        black_mine, black_theirs = (mine[valid].sum(-1) == 0), (color[valid].sum(-1) == 0)
        assert 0.3 < black_theirs.mean() and (black_mine != black_theirs).mean() < 0.02


def test_frames_limit_and_ctrl_c(synthetic_bag, tmp_path, monkeypatch):
    """``--frames N`` stops after N; Ctrl-C during tracking stops after that frame and the outputs
    are still written (the real SIGINT handler of the command)."""
    bag, _ = synthetic_bag
    r = _run(["live", "--playback", bag, "-o", tmp_path / "two.csv", "--frames", "2", "--no-check-hand", "--hand-scale", "1"])
    assert r.exit_code == 0, r.output
    assert read_tracking(tmp_path / "two.csv")[0]["frame"].tolist() == [0, 1]

    from tracker import run

    real = run.track_recording

    def interrupting(rec, tracker, on_frame=None, **kw):
        def each(frame, res, ob):
            on_frame(frame, res, ob)
            if frame.index == 1:
                signal.raise_signal(signal.SIGINT)  # as the user's Ctrl-C, delivered to the command's handler

        return real(rec, tracker, each, **kw)

    monkeypatch.setattr(run, "track_recording", interrupting)
    before = signal.getsignal(signal.SIGINT)  # ignored when the suite runs as a background job
    r = _run(["live", "--playback", bag, "-o", tmp_path / "stopped.csv", "--rerun", tmp_path / "s.rrd",
              "--no-check-hand", "--hand-scale", "1"])
    assert r.exit_code == 0, r.output
    assert read_tracking(tmp_path / "stopped.csv")[0]["frame"].tolist() == [0, 1]
    assert signal.getsignal(signal.SIGINT) is before  # put back


def test_no_camera_and_missing_extra(tmp_path, monkeypatch):
    import pyrealsense2 as rs

    if len(rs.context().query_devices()):
        pytest.skip("a RealSense camera is connected")
    r = _run(["live", "-o", tmp_path / "t.csv"])
    assert r.exit_code == 2 and r.stderr == ("error: camera: no RealSense camera connected (connect one, or play a "
                                             "recording back with --playback FILE.bag)\n"), r.output
    r = _run(["live", "--playback", tmp_path / "none.bag", "-o", tmp_path / "t.csv"])
    assert r.exit_code == 2 and r.stderr == f"error: {tmp_path / 'none.bag'}: no such file to play back\n"
    (tmp_path / "bad.bag").write_bytes(b"#ROSBAG V2.0\n" + b"\0" * 64)
    r = _run(["live", "--playback", tmp_path / "bad.bag", "-o", tmp_path / "t.csv"])
    assert r.exit_code == 2 and r.stderr.startswith(f"error: {tmp_path / 'bad.bag'}: librealsense cannot"), r.output
    assert r.stderr.count("\n") == 1
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    monkeypatch.delitem(sys.modules, "tracker.live", raising=False)
    r = _run(["live", "-o", tmp_path / "t.csv"])
    assert r.exit_code == 2 and r.stderr == ("error: pyrealsense2: live cameras need pyrealsense2 "
                                             "(pip install 'synergistic-hand-tracking[realsense]')\n"), r.output
    assert not (tmp_path / "t.csv").exists()
