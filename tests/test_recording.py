"""Recording folders: lossless round trip, errors, the real SR305 frames, the CLI."""
import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st
from typer.testing import CliRunner

from conftest import shared
from tracker.cameras import Camera, preset
from tracker.errors import RecordingError, TrackerError
from tracker.recording import Recording, RecordingWriter, import_pngs

SMALL = Camera(32, 24, 30.0, 30.0, 15.5, 11.5, 0.001, "uint16", "small")


@given(st.integers(0, 10_000), st.sampled_from(["uint16", "nyu_rgb"]), st.sampled_from([0.001, 0.000125]),
       st.booleans(), st.booleans())
@settings(max_examples=25, deadline=None)
def test_round_trip_is_lossless(seed, enc, scale, with_color, with_truth):
    import tempfile
    from pathlib import Path

    rng = np.random.default_rng(seed)
    cam = Camera(32, 24, 30.0, 30.0, 15.5, 11.5, scale, enc, "t")
    frames = []
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp) / "rec"
        with RecordingWriter(d, cam, fps=25, handedness="right") as w:
            for _ in range(3):
                depth = rng.uniform(0.2, 4.0, (24, 32)).astype(np.float32)
                depth[rng.random((24, 32)) < 0.2] = np.nan
                color = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) if with_color else None
                truth = rng.normal(size=26) if with_truth else None
                w.write(depth, color, truth)
                frames.append((depth, color, truth))
        rec = Recording.open(d)
        assert len(rec) == 3 and rec.fps == 25 and rec.handedness == "right" and rec.camera == cam
        for f, (depth, color, truth) in zip(rec, frames):
            assert f.depth.dtype == np.float32
            np.testing.assert_array_equal(np.isnan(f.depth), np.isnan(depth))
            ok = np.isfinite(depth)
            assert np.abs(f.depth[ok] - depth[ok]).max() <= scale / 2 + 1e-6
            if with_color:
                np.testing.assert_array_equal(f.color, color)
            if with_truth:
                np.testing.assert_allclose(f.truth, truth, rtol=1e-9)


def _write(tmp_path, n=3):
    d = tmp_path / "rec"
    with RecordingWriter(d, SMALL, fps=30) as w:
        for _ in range(n):
            w.write(np.full((24, 32), 0.5), truth=np.zeros(26))
    return d


def test_errors_name_file_and_problem(tmp_path):
    d = _write(tmp_path)
    meta = yaml.safe_load((d / "recording.yaml").read_text())
    (d / "recording.yaml").write_text(yaml.safe_dump({**meta, "fps": -1}))
    with pytest.raises(RecordingError, match=r"recording\.yaml: field fps"):
        Recording.open(d)
    (d / "recording.yaml").write_text(yaml.safe_dump(meta))
    (d / "depth" / "000001.png").unlink()
    with pytest.raises(RecordingError, match=r"depth: missing frame file\(s\) 000001\.png of 3"):
        Recording.open(d)
    import imageio.v3 as iio

    iio.imwrite(d / "depth" / "000001.png", np.zeros((24, 32), np.uint8))
    with pytest.raises(RecordingError, match=r"000001\.png: wrong bit depth: uint8"):
        Recording.open(d)[1]
    iio.imwrite(d / "depth" / "000001.png", np.zeros((20, 32), np.uint16))
    with pytest.raises(RecordingError, match=r"000001\.png: image is 32×20, the camera says 32×24"):
        Recording.open(d)[1]
    (d / "depth" / "000001.png").write_bytes(b"not a png")
    with pytest.raises(RecordingError, match="unreadable PNG"):
        Recording.open(d)[1]
    with pytest.raises(RecordingError, match="missing"):
        Recording.open(tmp_path)
    with pytest.raises(RecordingError, match="exists and is not empty"):
        RecordingWriter(d, SMALL)
    with pytest.raises(TrackerError, match="unknown preset"):
        preset("kinect9")


def test_sr305_frames_load_with_their_intrinsics(tmp_path):
    src = shared("realsense_sr305_lada")
    rec = import_pngs(src, tmp_path / "sr", preset("sr305"))
    assert len(rec) == 4 and rec.camera.fx == pytest.approx(476.007)
    from tracker.segment import nearest_blob

    meds = []
    for f in rec:
        blob = nearest_blob(f.depth, band=0.15, min_pixels=500)
        meds.append(float(np.nanmedian(f.depth[blob])))
        # the nearest surface (the hand held out) is in front of the rest of the scene (the body)
        assert np.nanmedian(f.depth[~blob]) > meds[-1]
    # SOURCES.md states about 600–800 mm (measured: 0.70, 0.50, 0.62, 0.60 m — frame 230536_110 holds
    # the hand nearer); a wrong depth unit (1 mm instead of 0.125 mm) would put it at 4–6 m
    assert all(0.45 <= m <= 0.85 for m in meds) and np.median(meds) >= 0.55, meds


def test_backprojection_of_a_plane():
    cam = preset("kinect1")
    d = np.full((cam.height, cam.width), 1.25)
    X = cam.backproject(d)
    assert np.allclose(X[..., 2], 1.25)
    uv = cam.project(X.reshape(-1, 3)).reshape(cam.height, cam.width, 2)
    np.testing.assert_allclose(uv[..., 0], np.arange(cam.width)[None, :].repeat(cam.height, 0), atol=1e-9)
    # field of view: the image's x extent at 1.25 m
    assert X[0, -1, 0] - X[0, 0, 0] == pytest.approx(1.25 * (cam.width - 1) / cam.fx)


def test_stride_sampling_density():
    from tracker.observe import observe

    cam = preset("kinect1")
    d = np.full((cam.height, cam.width), np.nan)
    d[100:200, 300:400] = 0.7
    ob = observe(d, cam, stride=3)
    assert len(ob.points) == len(range(102, 200, 3)) * len(range(300, 400, 3))
    assert ob.density == pytest.approx(len(ob.points) / 10_000)


def test_cli_synth_track_eval(tmp_path):
    from tracker.cli import app

    runner = CliRunner()
    rec = tmp_path / "rec"
    r = runner.invoke(app, ["synth", "--motion", "still", "--noise", "none", "--frames", "8", "-o", str(rec)])
    assert r.exit_code == 0, r.output
    out = tmp_path / "out.csv"
    r = runner.invoke(app, ["track", str(rec), "--mode", "reduced", "--synergies", "fingerfist", "-o", str(out),
                            "--keypoints", str(tmp_path / "kp.csv")])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["eval", str(rec), str(out), "--plot", str(tmp_path / "e.png")])
    assert r.exit_code == 0 and "posture_error_mean_deg" in r.output
    r = runner.invoke(app, ["track", str(rec), "-o", str(out)])
    assert r.exit_code == 2 and "never overwritten" in r.output
    r = runner.invoke(app, ["show", str(rec), "-o", str(tmp_path / "sheet.png")])
    assert r.exit_code == 0 and (tmp_path / "sheet.png").stat().st_size > 1000
    r = runner.invoke(app, ["info", str(tmp_path)])
    assert r.exit_code == 2 and "recording.yaml: missing" in r.output
