"""Tracking with segmentation on realistic scenes: each frame's ``observe`` (the hand segmented from
the depth and colour frame in the predicted hand's window, :meth:`FrameTracker.segment_window`, points
and normals) plus the tracker's step, CPU time of one core, next to the tracker's step alone on the
same frames (the peer: what the per-frame loop costs without finding the hand) and to the same loop
with the whole-frame segmenter (``observe`` without a window, timed on the same frames). Scenes as the realistic-scenes experiment renders them (open/close, 30 frames, hands 1.0×
with fingers 0.9–1.1×, forearm + torso / table, Kinect v1 and SR305 noise), today's default tracker
with the size calibrated; the first frames (the start search and the size) are left out, as the rate
is the tracking rate.

Each scene is tracked ``--repeat`` times from the start by a fresh tracker (the same work each pass:
the tracker is deterministic) and each frame's stages are timed at the fastest pass, as ``timeit``
advises on a shared machine: the other passes only add what other processes took. The mean over the
passes is printed beside it.

``--depth-only``: the same frames observed without their colour frames, as from a depth-only
recording (no skin test: the segmenter leaves out the table's plane and prefers the surface with
fingers, :mod:`tracker.segment`).

Run: .venv/bin/python benchmarks/bench_segmented.py [--frames 30] [--repeat 3] [--depth-only]
"""
from __future__ import annotations

import argparse
import os
import time

# one core: numba, OpenMP and BLAS threads (before numpy and numba are imported)
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np

from handmodel import HandModel
from synergy.bundle import load_bundle
from tracker import TRACKING_HAND
from tracker.io.cameras import preset
from tracker.observe import observe
from tracker.sim import experiments as E
from tracker.sim.hands import HandShape
from tracker.sim.motions import make_motion
from tracker.sim.noise import NoiseModel
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

SCENES = (("kinect1", "forearm,torso"), ("kinect1", "forearm,table"), ("realsense", "forearm,torso"),
          ("realsense", "forearm,box"))
SKIP = TrackerSettings().scale.frames + 1  # the start and the size's refinement are not the tracking rate


def frames_of(hand, sensor, spec, n, color=True):
    cam_name, noise_name = E.REALISTIC_SENSORS[sensor]
    cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
    shown = HandShape(1.0, E.realistic_fingers(1.0)).apply(hand)
    truth = make_motion("open-close", hand=shown, frames=n, seed=0).theta
    clutter = E.placed_clutter(spec, hand, shown, truth)
    ren = DepthRenderer(shown, cam)
    out = []
    for f in range(n):
        r = ren.render(truth[f], labels=False, color=True, clutter=clutter, incidence=nm.needs_incidence,
                       reflectance=nm.needs_reflectance)
        out.append((nm.apply(r.depth, cam, np.random.default_rng([0, f]), r.cos_incidence, r.reflectance),
                    r.color if color else None))
    return cam, out


def track_pass(hand, bundle, cam, frames):
    """One pass over a scene's frames with a fresh tracker: per frame the CPU ms of ``observe``, of the
    step, of the whole-frame ``observe``, and whether the window was used."""
    # one core: a start search's fits one after the other too (InitSettings.threads)
    tr = FrameTracker(hand, TrackerSettings().replace(init=dict(threads=1)), synergies=bundle)
    out = []
    for depth, color in frames:
        t0 = time.process_time()
        ob = observe(depth, cam, tr.settings.observe, color=color, window=tr.segment_window(cam))
        t1 = time.process_time()
        tr.track(ob, cam, color=color)
        t2 = time.process_time()
        # the whole-frame segmenter on the same frame (not tracked: the loop above is the one measured)
        observe(depth, cam, tr.settings.observe, color=color)
        t3 = time.process_time()
        out.append(((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3, ob.window is not None))
    return np.array(out, float)[SKIP:]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3, help="passes per scene; each frame timed at the fastest")
    ap.add_argument("--depth-only", action="store_true", help="observe without the colour frames")
    a = ap.parse_args()
    # the realistic scenes on the tracker's hand (tracker.TRACKING_HAND), as the report renders and tracks them
    hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
    print(f"{'sensor':9s} {'scene':15s} {'observe ms':>10s} {'windowed':>8s} {'track ms':>9s} "
          f"{'fps with segmentation':>22s} {'(mean of passes)':>16s} {'whole-frame observe ms':>22s} "
          f"{'fps whole-frame':>15s} {'fps tracking alone (peer)':>26s}")
    best_all, mean_all = [], []

    def row(label, best, mean):
        o, t, w, win = best.mean(axis=0)
        mo, mt = mean[:, 0].mean(), mean[:, 1].mean()
        print(f"{label:25s} {o:10.2f} {win:8.0%} {t:9.2f} {1e3 / (o + t):22.0f} {1e3 / (mo + mt):16.0f} {w:22.2f} "
              f"{1e3 / (w + t):15.0f} {1e3 / t:26.0f}")

    for sensor, spec in SCENES:
        cam, frames = frames_of(hand, sensor, spec, a.frames, color=not a.depth_only)
        passes = np.stack([track_pass(hand, bundle, cam, frames) for _ in range(max(a.repeat, 1))])
        best, mean = passes.min(axis=0), passes.mean(axis=0)
        best_all.append(best)
        mean_all.append(mean)
        row(f"{sensor:9s} {spec:15s}", best, mean)
    row("all", np.concatenate(best_all), np.concatenate(mean_all))
    print("(CPU ms per frame, one core, each frame at its fastest of the passes; windowed: share of frames "
          "segmented in the predicted hand's window)")


if __name__ == "__main__":
    main()
