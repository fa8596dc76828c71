"""Hand-size calibration on one frame: :func:`tracker.scale.calibrate_scale` (one start search, the
size by golden section and a parabola, every probed size's fit context resized from the model-sized
one) next to the earlier :func:`tracker.scale.calibrate_scale_searched` (a start search per size
guess, every probed size's context built anew) on the same frames, one core.

Frames: the first frame of each realistic scene (:data:`tracker.sim.experiments.REALISTIC_SCENES` ×
Kinect v1 / RealSense SR305 noise × hands 0.8, 1.0, 1.5 × the model, as the realistic-scenes
experiment renders them) and one real SR305 frame (``../shared/data/realsense_sr305_lada``, right
hand; no true size, the two estimates are compared). Prints per frame and variant the CPU seconds
and the size error (estimate / rendered size − 1), then the means, the share within 3 % and, on the
real frame, the time of the whole first frame as ``tracker track`` runs it (observe + the tracker's
first step with ``hand_scale="auto"``): CPU time on one thread, and wall time with the start search's
batches of fits on the threads :func:`tracker.init.search_threads` gives (the cores, at most 4).

Run: .venv/bin/python benchmarks/bench_scale.py [--scenes all|N] [--no-peer] [--real-frame NAME]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

# one core: numba, OpenMP and BLAS threads (before numpy and numba are imported)
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np

from handmodel import HandModel
from handmodel.rigid import euler_to_matrix
from synergy.bundle import load_bundle
from tracker import TRACKING_HAND
from tracker.io.cameras import preset
from tracker.correspond import Silhouette
from tracker.io.images import read_depth_units, units_to_metres
from tracker.observe import observe
from tracker.scale import calibrate_scale, calibrate_scale_searched
from tracker.sim import experiments as E
from tracker.sim.hands import HandShape
from tracker.sim.motions import hand_centre, make_motion
from tracker.sim.noise import NoiseModel
from tracker.sim.render import Clutter, DepthRenderer
from tracker.init import search_threads
from tracker.track import FrameTracker, TrackerSettings, fit_context

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "realsense_sr305_lada"


def realistic_frames(hand, limit=None):
    """``(label, observation, camera, true size)`` of each realistic scene's first frame, rendered and
    observed as :func:`tracker.sim.experiments.experiment_realistic` does (seed 0)."""
    out = []
    for sensor, (cam_name, noise_name) in E.REALISTIC_SENSORS.items():
        cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
        for scale in E.REALISTIC_SCALES:
            shown = HandShape(float(scale)).apply(hand)
            truth = make_motion("open-close", hand=shown, frames=30, seed=0).theta
            for k, (scene, spec) in enumerate(E.REALISTIC_SCENES.items()):
                c = None
                if spec:
                    R = euler_to_matrix(truth[:, 3:6])
                    c = Clutter.parse(spec).sized(scale).fixed((truth[:, :3] + R @ hand_centre(shown)).mean(axis=0))
                r = DepthRenderer(shown, cam).render(truth[0], labels=False, color=True, clutter=c, incidence=True,
                                                     reflectance=True)
                d = nm.apply(r.depth, cam, np.random.default_rng([k, 0]), r.cos_incidence, r.reflectance)
                out.append((f"{sensor} ×{scale:g} {scene}", observe(d, cam, color=r.color), cam, float(scale)))
                if limit is not None and len(out) >= limit:
                    return out
    return out


def prepared(tracker, ob, cam):
    """The cloud, normals and silhouette (with the wrist cue) as the tracker's first step makes them."""
    sil = Silhouette(ob.mask, ob.depth, cam)
    sil.frame_depth = ob.frame_depth
    tracker.cue.add(sil)
    keep = np.isfinite(ob.points).all(1)
    return ob.points[keep], None if ob.normals is None else ob.normals[keep], sil


def rebuilt_contexts(tracker):
    """``context_for`` as it was: every probed size's context built anew (surface sampled again)."""
    cache = {}

    def context_for(s):
        key = round(float(s), 5)
        if key not in cache:
            h = tracker.base_hand if key == 1.0 else tracker.base_hand.scaled(key)
            cache[key] = fit_context(h, tracker.settings, tracker.synergies)[0]
        return cache[key]
    return context_for


def timed(fn, *a, **k):
    t0 = time.process_time()
    out = fn(*a, **k)
    return out, time.process_time() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="all", help="how many realistic first frames ('all': 30)")
    ap.add_argument("--no-peer", action="store_true", help="skip the earlier calibration (~10× slower)")
    ap.add_argument("--real-frame", default="20210326-231615_40.png", help="a depth PNG of the SR305 data set")
    a = ap.parse_args(argv)
    try:
        limit = None if a.scenes == "all" else int(a.scenes)
    except ValueError:
        print(f"bench_scale: --scenes must be 'all' or a number, got {a.scenes!r}", file=sys.stderr)
        return 2
    real = REAL / a.real_frame
    if not real.is_file():
        print(f"bench_scale: {real}: no such depth frame (see ../shared/data/realsense_sr305_lada)", file=sys.stderr)
        return 2
    # the realistic scenes and the real frame on the tracker's hand (tracker.TRACKING_HAND), as a user tracks
    hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
    # one core: the search's fits one after the other (InitSettings.threads)
    settings = TrackerSettings().replace(scale=dict(hand_scale="auto"), init=dict(threads=1))
    frames = realistic_frames(hand, limit)
    # compile once (numba) before anything is timed
    warm = FrameTracker(hand, settings, synergies=bundle)
    pts, nrm, sil = prepared(warm, *frames[0][1:3])
    calibrate_scale(warm.context_for, pts, settings.init, silhouette=sil, normals=nrm)

    rows = []
    print(f"{'frame':34s} {'ours s':>7s} {'err %':>7s}   {'peer s':>7s} {'err %':>7s}")
    for label, ob, cam, true in frames:
        tr = FrameTracker(hand, settings, synergies=bundle)
        pts, nrm, sil = prepared(tr, ob, cam)
        (s, _, _), t = timed(calibrate_scale, tr.context_for, pts, settings.init, silhouette=sil, normals=nrm)
        row = [t, s / true - 1.0, np.nan, np.nan]
        if not a.no_peer:
            (s2, _, _), t2 = timed(calibrate_scale_searched, rebuilt_contexts(tr), pts, settings.init, silhouette=sil,
                                   normals=nrm)
            row[2:] = [t2, s2 / true - 1.0]
        rows.append(row)
        print(f"{label:34s} {row[0]:7.2f} {100 * row[1]:+7.1f}   {row[2]:7.2f} {100 * row[3]:+7.1f}", flush=True)
    R = np.asarray(rows)
    for name, t, e in (("ours", R[:, 0], R[:, 1]), ("peer", R[:, 2], R[:, 3])):
        if np.isfinite(t).all():
            print(f"{name}: {t.mean():.2f} s/frame (CPU), size within 3 % on {int((np.abs(e) <= 0.03).sum())} of "
                  f"{len(e)} first frames, |error| mean {100 * np.abs(e).mean():.1f} %, median "
                  f"{100 * np.median(np.abs(e)):.1f} %")

    # the real frame: as `tracker track --hand-scale auto` runs it (observe, then the tracker's first step)
    cam = preset("sr305")
    depth = units_to_metres(read_depth_units(real, cam), cam)
    right = HandModel.load(TRACKING_HAND, right=True)
    # one thread (CPU time) and the search's threads (wall time: what a user waits; the fits of a batch
    # run side by side, InitSettings.threads)
    n_thr = search_threads(0)
    timings = {}
    for k in sorted({1, n_thr}):
        tr = FrameTracker(right, settings.replace(init=dict(threads=k)), synergies=bundle)
        c0, w0 = time.process_time(), time.perf_counter()
        ob = observe(depth, cam, settings.observe)
        res = tr.track(ob, cam)
        timings[k] = (time.process_time() - c0, time.perf_counter() - w0)
    t_first = timings[1][0]
    pts, nrm, sil = prepared(tr, ob, cam)
    given = FrameTracker(right, settings.replace(scale=dict(hand_scale=tr.scale_)), synergies=bundle)
    c0 = time.process_time()
    given.track(observe(depth, cam, settings.observe), cam)
    t_given = time.process_time() - c0
    line = (f"real frame {real.name}: first frame with the size (observe + track, auto) {t_first:.2f} s CPU "
            f"on one thread, {timings[n_thr][1]:.2f} s wall on {n_thr} thread(s) ({timings[n_thr][0]:.2f} s CPU), "
            f"size {tr.scale_:.3f} ({res.status}, fit {res.fit_mm:.1f} mm); the same frame with that size given "
            f"{t_given:.2f} s")
    if not a.no_peer:
        (s2, _, _), t2 = timed(calibrate_scale_searched, rebuilt_contexts(tr), pts, settings.init, silhouette=sil,
                               normals=nrm)
        line += f"; peer calibration alone {t2:.2f} s, size {s2:.3f}"
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
