"""The keypoint CNN (family (b)): the shipped network is sealed, beats the centroid baseline on freshly
rendered held-out crops, treats a right hand as the mirror of a left one, says plainly what it
cannot do; the training's targets and the run time's decoding are each other's inverse."""
from __future__ import annotations

import shutil
import sys

import numpy as np
import pytest

pytest.importorskip("onnxruntime", reason="the keypoint CNN runs on onnxruntime (pip install '.[detector]')")

from tracker.detector import N_PARTS, OTHER  # noqa: E402
from tracker.errors import TrackerError  # noqa: E402
from tracker.io.cameras import Camera  # noqa: E402
from tracker.keypoint_cnn import (KeypointCNN, box_keypoints, cnn_path, detect, load_cnn,  # noqa: E402
                                  read_cnn, save_cnn)
from tracker.sim.dataset import DataRecipe, draw_crops  # noqa: E402
from tracker.sim.train_detector import HELDOUT_SEED_OFFSET, crop_camera, crop_truth_xyz  # noqa: E402

#: The tests' own crops: neither the training seed (0) nor the manifest's held-out one.
SEED = 424_242
#: Median keypoint error allowed on them (mm). The shipped network (1.1.0) measures 14.4 mm on its 197
#: held-out crops with the true pixels' box (docs/experiments/detector.md), 13.0 mm on these 30 and
#: 11.6–15.1 mm on three other sets of 30 (seeds 11–13); the centroid 45–55 mm. The floor keeps 1.0.0's
#: margin (26 mm over its 16.5 / 17.3–19.4 mm) over the worst of these.
FLOOR_MM = 20.0


@pytest.fixture(scope="module")
def crops():
    return draw_crops(DataRecipe(), SEED, 30)


def _hand(c):
    return (c.parts >= 0) & (c.parts < OTHER)


# ----------------------------------------------------------------------------- the shipped file
def test_shipped_network_is_sealed_and_a_flipped_byte_is_refused(tmp_path):
    net = load_cnn()
    m = net.manifest
    for key in ("command", "recipe", "seed", "settings", "metrics", "onnx_sha256", "manifest_sha256", "training"):
        assert key in m, key
    assert m["command"].startswith("tracker train-detector") and "--family cnn" in m["command"]
    assert m["heldout_seed"] == m["seed"] + HELDOUT_SEED_OFFSET
    src = cnn_path()
    for suffix in (".json", ".onnx"):
        shutil.copy(src.with_suffix(suffix), tmp_path / f"n{suffix}")
    assert read_cnn(tmp_path / "n.json").manifest == m  # the copy reads as the original

    onnx = tmp_path / "n.onnx"
    data = bytearray(onnx.read_bytes())
    data[len(data) // 2] ^= 0x01
    onnx.write_bytes(bytes(data))
    with pytest.raises(TrackerError) as e:
        read_cnn(tmp_path / "n.json")
    assert str(onnx) in str(e.value) and "onnx_sha256" in str(e.value) and "\n" not in str(e.value)

    shutil.copy(src.with_suffix(".onnx"), onnx)
    js = tmp_path / "n.json"
    text = js.read_text()
    js.write_text(text.replace('"seed": 0', '"seed": 1', 1) if '"seed": 0' in text else text.replace('"seed": ', '"seed": 9', 1))
    with pytest.raises(TrackerError, match="manifest_sha256") as e:
        read_cnn(js)
    assert str(js) in str(e.value) and "\n" not in str(e.value)


# ----------------------------------------------------------------------------- accuracy on unseen crops
def test_heldout_crops_beat_the_centroid_by_a_margin(crops):
    err, base = [], []
    for c in crops:
        m = _hand(c)
        if (m & np.isfinite(c.depth)).sum() < 20:
            continue
        d = detect(c.depth, crop_camera(c), m, "right" if c.mirror < 0 else "left")
        truth = crop_truth_xyz(c)
        err.append(1000 * np.linalg.norm(d.keypoints_xyz - truth, axis=1))
        rows, cols = np.nonzero(m & np.isfinite(c.depth))
        z = c.depth[rows, cols].astype(float)
        fx, fy, cx, cy = c.camera
        centroid = np.array([((cols - cx) * z / fx).mean(), ((rows - cy) * z / fy).mean(), z.mean()])
        base.append(1000 * np.linalg.norm(truth - centroid, axis=1))
        assert d.found.all() and np.all((d.confidence >= 0) & (d.confidence <= 1))
    assert len(err) >= 25
    ours, centroid = np.median(err), np.median(base)
    assert ours < 0.6 * centroid, (ours, centroid)
    assert ours < FLOOR_MM, ours


def test_a_right_hand_is_the_mirror_of_a_left_one(crops):
    c = next(c for c in crops if _hand(c).sum() > 200)
    cam = crop_camera(c)
    side = "right" if c.mirror < 0 else "left"
    other = "left" if side == "right" else "right"
    a = detect(c.depth, cam, _hand(c), side)
    flipped = Camera(cam.width, cam.height, cam.fx, cam.fy, cam.width - 1 - cam.cx, cam.cy)
    b = detect(c.depth[:, ::-1], flipped, _hand(c)[:, ::-1], other)
    np.testing.assert_allclose(b.keypoints_px[:, 0], cam.width - 1 - a.keypoints_px[:, 0], atol=1e-3)
    np.testing.assert_allclose(b.keypoints_px[:, 1], a.keypoints_px[:, 1], atol=1e-3)
    np.testing.assert_allclose(b.keypoints_xyz * [-1, 1, 1], a.keypoints_xyz, atol=1e-6)
    np.testing.assert_allclose(b.confidence, a.confidence, atol=1e-6)
    # and telling it the wrong hand changes the answer (the side is read, not ignored)
    w = detect(c.depth, cam, _hand(c), other)
    assert np.median(np.linalg.norm(w.keypoints_px - a.keypoints_px, axis=1)) > 1.0


# ----------------------------------------------------------------------------- bad input
def test_bad_input_gives_no_keypoints_or_one_line(crops):
    c = crops[0]
    cam = crop_camera(c)
    empty = detect(c.depth, cam, np.zeros_like(_hand(c)), "left")
    assert not empty.found.any() and empty.hand_score == 0.0 and np.all(empty.confidence == 0)
    nan = detect(np.full_like(c.depth, np.nan), cam, np.ones_like(_hand(c)), "left")
    assert not nan.found.any() and nan.hand_score == 0.0
    holes = c.depth.copy()
    holes[::2] = np.nan  # half the rows without depth: still an answer, finite
    assert detect(holes, cam, _hand(c), "left").found.all()
    for args, what in (((c.depth, cam, None, "left"), "mask"), ((c.depth, cam, _hand(c)[1:], "left"), "mask"),
                       ((c.depth, cam, _hand(c), "both"), "hand"), ((c.depth[1:], cam, _hand(c), "left"), "depth")):
        with pytest.raises(TrackerError, match=what) as e:
            detect(*args)
        assert "\n" not in str(e.value)


def test_missing_runtimes_are_named_in_one_line(monkeypatch):
    from tracker.sim.train_cnn import require_torch

    monkeypatch.setitem(sys.modules, "onnxruntime", None)
    with pytest.raises(TrackerError, match=r"pip install onnxruntime; or track with --no-detector"):
        KeypointCNN(b"", {}).session
    monkeypatch.setitem(sys.modules, "torch", None)
    with pytest.raises(TrackerError, match=r"pip install '\.\[train\]'"):
        require_torch()


# ----------------------------------------------------------------------------- training ↔ run time
def test_training_targets_decode_to_the_keypoints(crops):
    from tracker.sim.train_cnn import CnnSettings, jitter_box, sample_of, target

    rng = np.random.default_rng(1)
    checked = 0
    for c in crops[:10]:
        s = sample_of(c)
        if s is None:
            continue
        for box in (s.box, jitter_box(s, rng, CnnSettings())):
            fx, fy, cx, cy = s.camera
            uv, z, xyz = box_keypoints(target(s, box), box, s.mirror, Camera(1, 1, fx, fy, cx, cy))
            np.testing.assert_allclose(uv, s.uv, atol=1e-3)
            np.testing.assert_allclose(z, s.z, atol=1e-6)
            assert xyz.shape == (N_PARTS, 3)
        checked += 1
    assert checked >= 8


# ----------------------------------------------------------------------------- the command
def test_train_detector_cnn_bad_input_is_one_line(tmp_path):
    from typer.testing import CliRunner

    from tracker.cli import app

    def one_error(*args, part):
        r = CliRunner().invoke(app, ["train-detector", "-o", str(tmp_path), *args])
        assert r.exit_code == 2, r.output
        assert r.stderr.count("\n") == 1 and r.stderr.startswith("error: ") and part in r.stderr, r.stderr

    one_error("--family", "svm", part="--family")
    one_error("--family", "cnn", "--head", "pooled", part="--head")
    (tmp_path / "hand-keypoints-cnn-1.0.0.json").write_text("{}")
    one_error("--family", "cnn", part="exists")


@pytest.mark.slow
def test_training_is_reproducible_from_its_seed(crops):
    torch = pytest.importorskip("torch", reason="training needs pip install '.[train]'")
    from tracker.sim.train_cnn import CnnSettings, fit, sample_of

    samples = [s for s in map(sample_of, crops[:12]) if s is not None]
    st = CnnSettings(n_crops=len(samples), epochs=1, batch=4, threads=1)
    (a, la), (b, lb) = fit(samples, st, 3), fit(samples, st, 3)
    assert la == lb and all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    c, _ = fit(samples, st, 4)
    assert not all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), c.state_dict().values()))


def test_save_and_read_a_versioned_network(tmp_path):
    net = load_cnn()
    body = {k: v for k, v in net.manifest.items() if k not in ("format", "onnx_file", "onnx_sha256", "manifest_sha256")}
    out = save_cnn(tmp_path / "hand-keypoints-cnn-2.0.0.json", net.onnx_bytes, body)
    assert out.name == "hand-keypoints-cnn-2.0.0.json" and (tmp_path / "hand-keypoints-cnn-2.0.0.onnx").is_file()
    assert read_cnn(tmp_path / "hand-keypoints-cnn-2.0.0.onnx").manifest["onnx_sha256"] == net.manifest["onnx_sha256"]
    with pytest.raises(TrackerError, match="exists"):
        save_cnn(out, net.onnx_bytes, body)


def test_shipped_network_carries_no_exporter_trace():
    """torch's exporter writes each node's Python stack trace (the build machine's file paths) into the
    ONNX file; the shipped file has none (``train_cnn.without_trace``)."""
    from tracker.keypoint_cnn import cnn_path

    data = cnn_path().with_suffix(".onnx").read_bytes()
    assert b"pkg.torch.onnx.stack_trace" not in data and b"site-packages" not in data
