"""Azure Kinect .mkv recordings: the real pyk4a file against its own calibration and PyAV's decoding,
the per-mode intrinsics conversion, damaged files as one-line errors."""
import json

from conftest import SHARED_DATA

import numpy as np
import pytest
from typer.testing import CliRunner

av = pytest.importorskip("av", reason="the [recordings] extra (av) is not installed")
from tracker.errors import RecordingError  # noqa: E402
from tracker.io.mkv import DEPTH_MODES, MkvRecording, depth_intrinsics  # noqa: E402
from tracker.io.recording import Recording, import_recording_file  # noqa: E402

MKV = SHARED_DATA / "sensor_recordings" / "azure_kinect_recording.mkv"


def _mkv():
    if not MKV.is_file():
        pytest.skip(f"real Azure Kinect recording not available: {MKV} (../shared/data is absent)")
    return MKV


def _calibration_and_frames(path):
    """The calibration JSON and every depth frame, read with PyAV directly (the reference)."""
    c = av.open(str(path))
    try:
        cal = json.loads(next(s for s in c.streams if s.type == "attachment").data)
        depth = next(s for s in c.streams.video if s.metadata.get("title") == "DEPTH")
        frames = [f.to_ndarray() for p in c.demux(depth) if p.size for f in p.decode()]
        return cal, depth.metadata["K4A_DEPTH_MODE"], frames
    finally:
        c.close()


def test_real_mkv_matches_its_calibration_and_pyav():
    path = _mkv()
    cal, mode, frames = _calibration_and_frames(path)
    rec = Recording.open(path)
    assert isinstance(rec, MkvRecording) and mode == "NFOV_UNBINNED"
    assert len(rec) == len(frames) == 1 and rec.camera.shape == (576, 640) and not rec.has_color
    assert rec.camera.depth_scale_m == 0.001  # b16g is millimetres
    cam = next(c for c in cal["CalibrationInformation"]["Cameras"] if c["Purpose"].endswith("Depth"))
    cx_n, cy_n, fx_n, fy_n = cam["Intrinsics"]["ModelParameters"][:4]
    # the SDK: normalised to 1024², NFOV unbinned crops (192, 180), the origin moves to the pixel centre
    c = rec.camera
    np.testing.assert_allclose([c.fx, c.fy, c.cx, c.cy],
                               [fx_n * 1024, fy_n * 1024, cx_n * 1024 - 192 - 0.5, cy_n * 1024 - 180 - 0.5], rtol=1e-12)
    assert 500 < c.fx < 510 and 300 < c.cx < 340  # an NFOV depth camera, principal point near the centre
    assert np.array_equal(rec.depth_units(0), frames[0])
    f = rec[0]
    assert f.time_s == 0.0 and np.array_equal(np.isnan(f.depth), frames[0] == 0)
    assert np.nanmedian(f.depth) == pytest.approx(np.median(frames[0][frames[0] > 0]) / 1000)


def test_real_mkv_imports_to_a_folder(tmp_path):
    out = import_recording_file(_mkv(), tmp_path / "rec", handedness="right")
    _, _, frames = _calibration_and_frames(MKV)
    assert len(out) == 1 and out.handedness == "right" and out.camera.name == "azure_kinect_nfov_unbinned"
    assert np.array_equal(out.depth_units(0), frames[0])


CAL = {"CalibrationInformation": {"Cameras": [
    {"Purpose": "CALIBRATION_CameraPurposePhotoVideo", "SensorWidth": 4096, "SensorHeight": 3072,
     "Intrinsics": {"ModelParameters": [0.5] * 14}},
    {"Purpose": "CALIBRATION_CameraPurposeDepth", "SensorWidth": 1024, "SensorHeight": 1024,
     "Intrinsics": {"ModelParameters": [0.51, 0.49, 0.48, 0.47] + [0] * 10}}]}}


@pytest.mark.parametrize("mode", list(DEPTH_MODES))
def test_depth_intrinsics_per_mode(mode):
    (bw, bh), (ox, oy), (w, h) = DEPTH_MODES[mode]
    got = depth_intrinsics(CAL, mode, "cal")
    assert got[:2] == (w, h)
    np.testing.assert_allclose(got[2:], [0.48 * bw, 0.47 * bh, 0.51 * bw - ox - 0.5, 0.49 * bh - oy - 0.5])
    # binning halves the focal length; the principal point stays at the same place of the field of view
    full = depth_intrinsics(CAL, mode.replace("2X2BINNED", "UNBINNED"), "cal")
    if "BINNED" in mode and "UN" not in mode:
        assert got[2] == pytest.approx(full[2] / 2)
        assert got[4] + 0.5 == pytest.approx((full[4] + 0.5) / 2)


@pytest.mark.parametrize("cal,match", [
    ({}, "no depth camera intrinsics"),
    ({"CalibrationInformation": {"Cameras": []}}, "0 depth cameras"),
    ({"CalibrationInformation": {"Cameras": [{"Purpose": "CALIBRATION_CameraPurposeDepth",
                                              "Intrinsics": {"ModelParameters": ["x"]}}]}}, "no depth camera intrinsics"),
    ({"CalibrationInformation": {"Cameras": [{"Purpose": "CALIBRATION_CameraPurposeDepth", "SensorWidth": 512,
                                              "Intrinsics": {"ModelParameters": [0.5] * 4}}]}}, "calibrated at 512×1024"),
])
def test_bad_calibration_is_an_error(cal, match):
    with pytest.raises(RecordingError, match=f"cal: .*{match}"):
        depth_intrinsics(cal, "NFOV_UNBINNED", "cal")
    with pytest.raises(RecordingError, match="depth mode 'OFF' is not one of"):
        depth_intrinsics(CAL, "OFF", "cal")


def _cli(*args):
    from tracker.cli import app

    return CliRunner().invoke(app, [str(a) for a in args])


def test_damaged_mkv_is_a_one_line_error_or_reads(tmp_path):
    data = _mkv().read_bytes()
    _, _, frames = _calibration_and_frames(MKV)
    bad = tmp_path / "bad.mkv"
    outcomes = set()
    for n in list(np.linspace(0, len(data) - 1, 12).astype(int)):
        bad.write_bytes(data[:n])
        try:
            rec = Recording.open(bad)
            assert np.array_equal(rec.depth_units(0), frames[0])  # what reads is the real frame
            outcomes.add("read")
        except RecordingError as exc:
            assert str(bad) in str(exc)
            outcomes.add("error")
    assert "error" in outcomes
    bad.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, dtype=np.uint8).tobytes())
    r = _cli("info", bad)
    assert r.exit_code == 2 and r.stderr.count("\n") == 1 and r.stderr.startswith(
        f"error: {bad}: not a Matroska file: it does not start with an EBML header (unknown binary data)")
    r = _cli("info", bad, "--topic", "/x")
    assert r.exit_code == 2 and "apply to ROS bags, not to .mkv files" in r.stderr


def test_a_cut_mkv_says_it_is_cut(tmp_path):
    """A recording copied only in part: the error (or, when its frames survive, the source line)
    says the file is cut short, not only that the depth track holds no frames."""
    from tracker.io.mkv import cut_short

    data = _mkv().read_bytes()
    assert cut_short(MKV) is None
    bad = tmp_path / "cut.mkv"
    bad.write_bytes(data[:800_000])  # before the depth packet
    assert cut_short(bad) == (len(data), 800_000)
    r = _cli("info", bad)
    assert r.exit_code == 2 and r.stderr.count("\n") == 1, r.output
    assert f"cut short: the file has 800000 of its {len(data)} bytes" in r.stderr
    bad.write_bytes(data[:1_500_000])  # after it: the frame reads, and the recording says what is lost
    rec = Recording.open(bad)
    assert len(rec) == 1 and "cut short" in rec.source


def test_info_says_a_file_does_not_name_its_hand():
    """A recording file read in place counts as a left hand: info says so, and how to change it (a
    right hand tracked as left is fitted mirrored, and the handedness check misses it on many frames)."""
    r = _cli("info", _mkv(), "--quick")
    assert r.exit_code == 0, r.output
    assert "left (a recording file does not say: --hand right to import or track a right hand)" in \
        " ".join(r.stdout.replace("│", " ").split())


def test_a_time_range_past_the_end_says_which(tmp_path):
    """--start alone was reported as "between 5 s and 0 s"."""
    r = _cli("import", _mkv(), "-o", tmp_path / "r", "--start", "5")
    assert r.exit_code == 2 and r.stderr.count("\n") == 1, r.output
    assert "no frames from 5 s (the file's frames span 0–0 s)" in r.stderr
    assert not (tmp_path / "r").exists()


def test_mutated_mkv_never_crashes(tmp_path):
    data = _mkv().read_bytes()
    bad = tmp_path / "mut.mkv"
    rng = np.random.default_rng(3)
    for _ in range(15):
        b = bytearray(data)
        for pos in rng.integers(0, len(b), 16):
            b[pos] = int(rng.integers(0, 256))
        bad.write_bytes(bytes(b))
        try:
            rec = Recording.open(bad)
            for i in range(len(rec)):
                assert rec.depth_units(i).shape == rec.camera.shape
        except RecordingError as exc:
            assert str(bad) in str(exc)


def test_track_warns_of_a_cut_mkv_and_tracks_what_it_holds(tmp_path):
    """tracker info said the file was cut short, tracker track said nothing: now one warning line on
    stderr, and the frames before the cut are tracked."""
    from tracker.io.tracking_file import read_tracking

    data = _mkv().read_bytes()
    bad = tmp_path / "cut.mkv"
    bad.write_bytes(data[:1_600_000])
    r = _cli("track", bad, "--no-check-hand", "--no-safety-net", "-o", tmp_path / "t.csv")
    assert r.exit_code == 0, r.output
    assert r.stderr == (f"warning: {bad}: cut short: the file has 1600000 of its {len(data)} bytes; "
                        "tracking the 1 frame it holds\n")
    df, _ = read_tracking(tmp_path / "t.csv")
    assert len(df) == 1
    r = _cli("track", MKV, "--no-check-hand", "--no-safety-net", "-o", tmp_path / "whole.csv")
    assert r.exit_code == 0 and "cut short" not in r.stderr, r.output  # a sound file: no warning


def _damaged_copy(tmp_path, at, value, name="damaged.mkv"):
    data = bytearray(_mkv().read_bytes())
    data[at] = value
    out = tmp_path / name
    out.write_bytes(bytes(data))
    return out


def test_a_wrong_element_size_names_the_element(tmp_path):
    """A Cluster's size one unit too large (its last byte +1) read on silently under PyAV, which
    resynchronises; the walk over the elements stops at the first one that runs past its parent."""
    from tracker.io.mkv import _vint, check_structure

    data = _mkv().read_bytes()
    pos = data.rindex(bytes.fromhex("1F43B675"), 0, data.index(bytes.fromhex("1C53BB6B"), 7000))
    n = _vint(data, pos + 4)[1]
    bad = _damaged_copy(tmp_path, pos + 4 + n - 1, (data[pos + 4 + n - 1] + 1) % 256)
    check_structure(_mkv())  # the real file is sound
    with pytest.raises(RecordingError, match=r"damaged: .* element at byte \d+ declares \d+ bytes, past the end"
                                             r"|damaged: no (Cluster|Segment) element starts at byte"):
        Recording.open(bad)


def test_a_damaged_element_id_is_refused_not_read_on(tmp_path):
    data = _mkv().read_bytes()
    tracks = data.rindex(bytes.fromhex("1654AE6B"), 0, 7000)  # the element, after the SeekHead naming it
    bad = _damaged_copy(tmp_path, tracks, 0x55)  # Tracks' ID no longer a Segment element
    with pytest.raises(RecordingError, match=f"no Segment element starts at byte {tracks}"):
        Recording.open(bad)


def test_fuzz_mutant_without_codec_parameters_is_refused(tmp_path):
    """Mutant 117 of the fuzzer's seed 0 left the depth track without codec parameters: an
    AttributeError ('NoneType' has no attribute 'width') before the fix."""
    import importlib.util
    from pathlib import Path

    _mkv()
    tool = Path(__file__).resolve().parents[2] / "tools" / "fuzz_recordings.py"
    spec = importlib.util.spec_from_file_location("fuzz_recordings", tool)
    fz = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fz)
    path, _ = fz.make_mutant("mkv", [MKV], 0, 117, tmp_path)
    with pytest.raises(RecordingError):
        for _ in Recording.open(path):
            pass
