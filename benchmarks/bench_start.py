"""Starts, the detected hand first against the full search: each frame of the harder scenes (fists seen from
the palm and the thumb side, a pinch, a grasp from the back; forearm + torso; Kinect v1 and SR305 noise;
hands 0.8/1.0/1.5× with fingers ±10 %) tracked alone by a fresh tracker at the rendered hand's size —
the tracker without a detector (``--no-detector``: every start the full search), with ``start.detector``
but without the hand-presence network (``--no-presence``: the keypoint CNN's hand fitted first, the full
search only when that scores above ``start.detector_accept_mm``), and with both (the default: the network
asked before a region is searched, overruled where the detected hand fits), one core (the search's fits on
one thread, ``--threads``), the same frames in the same run; ``--settings`` adds the default with those
changes (JSON, e.g. ``'{"init": {"halving": {"seeded": {"first": "fit"}}}}'``). Per variant: frames found (not "no
hand"), the mean keypoint error's mean / median over them, frames within 10 mm, the frames whose full
search was skipped, wall ms per start; for the starts without the full search, their wall and CPU ms (CPU:
this process's, one thread, so the machine's other load counts less) and errors.

Run: .venv/bin/python benchmarks/bench_start.py [--frames 0,10,20,30,40] [--detector hand-keypoints-cnn]
[--accept 1.5] [--presence hand-presence-cnn] [--motions fist-palm,fist-side,pinch,grasp-back] [--settings JSON]
[--threads 1]
"""
from __future__ import annotations

import argparse
import json
import os
import time

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from handmodel import HandModel  # noqa: E402
from synergy.bundle import load_bundle  # noqa: E402
from tracker import TRACKING_HAND  # noqa: E402
from tracker.io.cameras import preset  # noqa: E402
from tracker.observe import observe  # noqa: E402
from tracker.sim import experiments as E  # noqa: E402
from tracker.sim.hands import HandShape  # noqa: E402
from tracker.sim.motions import make_motion  # noqa: E402
from tracker.sim.noise import NoiseModel  # noqa: E402
from tracker.sim.render import DepthRenderer  # noqa: E402
from tracker.track import FrameTracker, TrackerSettings  # noqa: E402

SCENE = "+forearm+torso"  # the harder scenes' clutter (tools/harder_scenes.py), noise seeded by its place
MOTION_FRAMES = 45


def scene_frames(hand, motion, sensor, scale, frames):
    """``(camera, [(observation, colour, true keypoints)])``: frames of ``motion`` as
    :func:`tracker.sim.experiments.experiment_realistic` renders its ``SCENE`` (seed 0)."""
    cam_name, noise_name = E.REALISTIC_SENSORS[sensor]
    cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
    shown = HandShape(scale, E.realistic_fingers(scale, 0)).apply(hand)
    truth = make_motion(motion, hand=shown, frames=MOTION_FRAMES, seed=0).theta
    clutter = E.placed_clutter(E.REALISTIC_SCENES[SCENE], hand, shown, truth)
    ren, j = DepthRenderer(shown, cam), list(E.REALISTIC_SCENES).index(SCENE)
    out = []
    for f in frames:
        r = ren.render(truth[f], labels=False, color=True, clutter=clutter, incidence=nm.needs_incidence,
                       reflectance=nm.needs_reflectance)
        depth = nm.apply(r.depth, cam, np.random.default_rng([j, f]), r.cos_incidence, r.reflectance)
        out.append((observe(depth, cam, color=r.color), r.color, shown.keypoints(truth[f])))
    return cam, out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="0,10,20,30,40", help="frame indices of each 45-frame motion")
    ap.add_argument("--motions", default="fist-palm,fist-side,pinch,grasp-back")
    ap.add_argument("--detector", default="hand-keypoints-cnn")
    ap.add_argument("--accept", type=float, default=TrackerSettings().start.detector_accept_mm)
    ap.add_argument("--presence", default="hand-presence-cnn")
    ap.add_argument("--settings", default="", help="one more variant: the default with these changes (JSON)")
    ap.add_argument("--threads", type=int, default=1, help="init.threads: a search's fits on this many threads")
    a = ap.parse_args()
    frames = [int(f) for f in a.frames.split(",")]
    hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
    variants = {"the full search (--no-detector)": {"detector": "", "presence": ""},
                f"{a.detector}'s hand first (--no-presence)": {"detector": a.detector, "detector_accept_mm": a.accept,
                                                               "presence": ""},
                "+ the presence test (default)": {"detector": a.detector, "detector_accept_mm": a.accept,
                                                  "presence": a.presence}}
    changes = {}
    if a.settings:
        changes = {f"+ {a.settings}": json.loads(a.settings)}
        variants[f"+ {a.settings}"] = variants["+ the presence test (default)"]
    res = {v: {"mm": [], "ms": [], "cpu": [], "skipped": []} for v in variants}
    for motion in a.motions.split(","):
        for sensor in E.REALISTIC_SENSORS:
            for scale in E.REALISTIC_SCALES:
                cam, obs = scene_frames(hand, motion, sensor, scale, frames)
                for ob, color, true_kp in obs:
                    for v, start in variants.items():
                        st = TrackerSettings().replace(scale=dict(hand_scale=scale), start=start,
                                                       init=dict(threads=a.threads)).replace(**changes.get(v, {}))
                        tr = FrameTracker(hand, st, synergies=bundle)
                        t0, c0 = time.perf_counter(), time.process_time()
                        r = tr.track(ob, cam, color=color)
                        res[v]["ms"].append((time.perf_counter() - t0) * 1e3)
                        res[v]["cpu"].append((time.process_time() - c0) * 1e3)
                        found = bool(np.all(np.isfinite(r.theta)))
                        res[v]["mm"].append(np.linalg.norm(tr.hand.keypoints(r.theta) - true_kp, axis=1).mean() * 1e3
                                            if found else np.nan)
                        res[v]["skipped"].append(tr.stats.detector_starts > 0)
                def mean_of(e):
                    e = np.array(e, float)
                    return f"{np.nanmean(e):.1f} mm" if np.isfinite(e).any() else "no hand"
                print(f"{motion} {sensor} {scale:g}x: " + "; ".join(
                    f"{v} {mean_of(res[v]['mm'][-len(obs):])}" for v in variants), flush=True)
    n = len(next(iter(res.values()))["mm"])
    print(f"\n{n} frames, each started alone at the rendered size, one core (wall ms)")
    print(f"{'variant':46s} {'found':>6s} {'mean mm':>8s} {'median':>7s} {'<=10 mm':>8s} {'skipped':>8s} "
          f"{'ms median':>10s} {'ms mean':>8s} {'ms max':>7s}")
    for v, d in res.items():
        e, ms, cpu, skip = np.array(d["mm"]), np.array(d["ms"]), np.array(d["cpu"]), np.array(d["skipped"], bool)
        f = np.isfinite(e)
        print(f"{v:46s} {f.sum():6d} {np.mean(e[f]):8.1f} {np.median(e[f]):7.1f} {np.sum(e[f] <= 10):8d} "
              f"{skip.sum():8d} {np.median(ms):10.0f} {np.mean(ms):8.0f} {np.max(ms):7.0f}")
        if skip.any():
            print(f"{'':46s} the starts without the full search: {np.median(ms[skip]):.0f} ms median "
                  f"(CPU {np.median(cpu[skip]):.1f} ms median, {np.mean(cpu[skip]):.1f} mean), "
                  f"{np.nanmedian(e[skip]):.2f} mm median, {np.nanmean(e[skip]):.2f} mean "
                  f"(the full search on those frames: "
                  f"{np.nanmedian(np.array(res[next(iter(res))]['mm'])[skip]):.1f} mm, "
                  f"{np.median(np.array(res[next(iter(res))]['ms'])[skip]):.0f} ms)")


if __name__ == "__main__":
    main()
