"""The hand detectors on one core: ms per frame for the detection alone — the hand-part forest
(``tracker.detector.detect``) and the keypoint CNN (``tracker.keypoint_cnn.detect``, onnxruntime on one
thread) — for the detection plus the start fitted to its keypoints (``tracker.keypoint_fit.fit_start``),
the tracker's start with the CNN's hand first (``start.detector``: :func:`tracker.init.seeded_search`, the
full search only when the detected hand's fit scores above ``start.detector_accept_mm``), and today's
start search (``FrameTracker.track`` on a first frame, the tracker's defaults) as the peer, both at the
rendered hand's size, on the same frames in the same run, with their mean keypoint errors; and the
shipped models' install weight.

Frames: SR305 640×480 renders drawn by the detector's own data recipe with held-out seeds (hand,
clutter, noise), the hand's segmentation by the tracker (``observe``) as the mask.

Run: .venv/bin/python benchmarks/bench_detector.py [--frames 10] [--no-peer]
"""
from __future__ import annotations

import argparse
import os
import time

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from handmodel import HandModel  # noqa: E402
from synergy.bundle import load_bundle  # noqa: E402
from tracker import TRACKING_HAND  # noqa: E402
from tracker.io.cameras import preset  # noqa: E402
from tracker.detector import detect, detector_path, load_detector  # noqa: E402
from tracker.keypoint_fit import fit_start  # noqa: E402
from tracker import keypoint_cnn  # noqa: E402
from tracker.observe import observe  # noqa: E402
from tracker.sim.dataset import DataRecipe, draw_scene  # noqa: E402
from tracker.track import FrameTracker, TrackerSettings  # noqa: E402


def frames(n: int, seed: int = 777):
    """Whole SR305 frames (the crop window larger than the image), left hands at 0.4–0.9 m."""
    recipe = DataRecipe(**{**load_detector().manifest["recipe"], "window_m": 10.0, "p_right": 0.0,
                           "sensors": {"sr305": 1.0}, "distance_m": (0.4, 0.9), "orientations": "user"})
    out = []
    for i in range(n):
        c = draw_scene(recipe, np.random.default_rng([seed, i]))
        if c.depth.shape == (480, 640):
            out.append(c)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--no-peer", action="store_true")
    a = ap.parse_args()
    cam = preset("sr305")
    hand = HandModel.load(TRACKING_HAND)
    bundle = load_bundle("fingerfist")
    data = frames(a.frames)
    obs = [observe(c.depth, cam) for c in data]
    detect(data[0].depth, cam, obs[0].mask)  # compile
    keypoint_cnn.detect(data[0].depth, cam, obs[0].mask)  # the session
    rows = {}
    t_det, t_start, t_cnn, t_cnn_start, t_peer = [], [], [], [], []
    t_first, e_first, e_peer, n_first = [], [], [], []
    clock = (time.perf_counter, time.process_time)  # wall and this process's CPU: the machine may be shared
    for c, ob in zip(data, obs):
        t0 = [f() for f in clock]
        d = detect(c.depth, cam, ob.mask)
        t1 = [f() for f in clock]
        fit_start(d, hand, bundle)
        t2 = [f() for f in clock]
        t_det.append([1000 * (b - a) for a, b in zip(t0, t1)])
        t_start.append([1000 * (b - a) for a, b in zip(t0, t2)])
        t0 = [f() for f in clock]
        k = keypoint_cnn.detect(c.depth, cam, ob.mask)
        t1 = [f() for f in clock]
        fit_start(k, hand, bundle)
        t2 = [f() for f in clock]
        t_cnn.append([1000 * (b - a) for a, b in zip(t0, t1)])
        t_cnn_start.append([1000 * (b - a) for a, b in zip(t0, t2)])
        # the rendered hand's keypoints in the camera frame, and its size (its fingers ±10 % are not the model's)
        fx, fy, cx, cy = c.camera
        truth = np.stack([(c.keypoints_uv[:, 0] - cx) * c.keypoints_z / fx,
                          (c.keypoints_uv[:, 1] - cy) * c.keypoints_z / fy, c.keypoints_z], axis=1)
        size = dict(hand_scale=float(c.meta["scale"]))
        for start, times, errs, firsts in ((dict(detector=keypoint_cnn.CNN_NAME), t_first, e_first, n_first),
                                           (dict(detector=""), t_peer, e_peer, None)):
            if firsts is None and a.no_peer:
                continue
            st = TrackerSettings().replace(scale=size, start=start)
            tr = FrameTracker(hand, st, synergies=bundle)
            t3 = [f() for f in clock]
            r = tr.track(ob, cam)
            times.append([1000 * (f() - t) for f, t in zip(clock, t3)])
            ok = np.all(np.isfinite(r.theta))
            errs.append(1000 * np.linalg.norm(tr.hand.keypoints(r.theta) - truth, axis=1).mean() if ok else np.nan)
            if firsts is not None:
                firsts.append(tr.stats.detector_starts)
    rows["detect (mask from observe)"] = t_det
    rows["detect + fit_start (synergies)"] = t_start
    rows["keypoint CNN detect (mask from observe; onnxruntime, 1 thread)"] = t_cnn
    rows["keypoint CNN detect + fit_start (synergies)"] = t_cnn_start
    rows["the start, the CNN's hand first (FrameTracker.track, start.detector)"] = t_first
    if t_peer:
        rows["peer: the full start search (FrameTracker.track, first frame, --no-detector)"] = t_peer
    print(f"{len(data)} SR305 frames, one core")
    print(f"{'variant':70s} {'median ms':>10s} {'max ms':>8s} {'CPU median ms':>14s}")
    for k, v in rows.items():
        v = np.array(v)
        print(f"{k:70s} {np.median(v[:, 0]):10.1f} {np.max(v[:, 0]):8.1f} {np.median(v[:, 1]):14.1f}")
    def errors(e):
        e = np.array(e)
        return (f"mean keypoint error median {np.nanmedian(e):.1f} mm on the {np.isfinite(e).sum()} frames found "
                f"(of {len(e)}), {np.sum(e <= 20)} within 20 mm")
    print(f"the CNN's hand first: the full search skipped on {sum(n_first)} of {len(n_first)} frames; {errors(e_first)}")
    if e_peer:
        print(f"peer: {errors(e_peer)}")
    p = detector_path()
    print(f"model {p.name}: {p.stat().st_size / 1e6:.2f} MB on disk, {load_detector().arrays['thresholds'].size} nodes")
    q = keypoint_cnn.cnn_path()
    net = keypoint_cnn.load_cnn()
    print(f"model {q.with_suffix('.onnx').name}: {len(net.onnx_bytes) / 1e6:.2f} MB on disk, "
          f"{net.manifest['training']['parameters']} parameters; needs onnxruntime")


if __name__ == "__main__":
    main()
