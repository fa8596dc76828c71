"""Single-frame start search: successive halving (the default, ``InitSettings(strategy="halving")``) next
to the exhaustive search it replaced (``strategy="exhaustive"``, every start refined on the full cloud)
on the same frames, one core.

The experiments' protocol (:func:`tracker.sim.experiments.experiment_single_frame`): random fingerfist
rows (seeded), the hand at 0.6–0.9 m, every pixel, full cloud, our settings with 30 ICP iterations per
refinement; from the true global pose (posture unknown) and from no pose at all (placements found from
the cloud). Prints per variant seconds per frame (wall clock and this process's CPU time: the machine
may be shared) and the posture error (mean / max °).

Run: .venv/bin/python benchmarks/bench_single_frame.py [--frames 24] [--mode hierarchical] [--no-peer]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

# one core: numba, OpenMP and BLAS threads (before numpy and numba are imported)
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np

from handmodel import HandModel
from synergy.bundle import load_bundle
from synergy.errors import SynergyError
from tracker.io.cameras import preset
from tracker.correspond import Silhouette
from tracker.evaluate import posture_error_deg
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim import experiments as E
from tracker.sim.render import DepthRenderer


def frames(hand, bundle, cam, n, seed):
    """``(truth, observation, silhouette, start)`` per frame; ``start`` is the truth's global pose
    with the synergy mean as posture (what the search is given "from the global pose")."""
    P = E.fingerfist_postures()
    rows = np.random.default_rng(seed).choice(len(P), n, replace=False)
    ren = DepthRenderer(hand, cam)
    # the rendered hand has no forearm, so nothing is cut: the benchmark times the search, not the segmentation
    seg = Segmenter(forearm="keep")
    out = []
    for i, row in enumerate(rows):
        truth = E.sequence(P[row:row + 1], bundle.model.mean_, lead=0, distance=0.6 + 0.3 * (i % 4) / 3)[0]
        ob = observe(ren.render(truth, labels=False).depth, cam, stride=1, target_points=None, smooth=0, segmenter=seg)
        start = truth.copy()
        start[~hand.pose_mask] = bundle.model.mean_
        out.append((truth, ob, Silhouette(ob.mask, ob.depth, cam), start))
    return rows, out


def run(tracker, data, mode, from_pose):
    """Wall and CPU seconds per frame and the per-frame posture errors (°)."""
    hand = tracker.hand
    wall, cpu, err = [], [], []
    for truth, ob, sil, start in data:
        t0, c0 = time.perf_counter(), time.process_time()
        th, _ = tracker.fit_single_frame(ob.points, theta0=start if from_pose else None, mode=mode, silhouette=sil,
                                         normals=ob.normals)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        err.append(float(posture_error_deg(th, truth, hand.pose_mask)))
    return float(np.mean(wall)), float(np.mean(cpu)), np.asarray(err)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--mode", default="hierarchical", choices=("full", "hierarchical"))
    ap.add_argument("--icp", type=int, default=30, help="ICP iterations per refinement (the experiments': 30)")
    ap.add_argument("--no-peer", action="store_true", help="skip the exhaustive search (slow)")
    a = ap.parse_args(argv)
    if a.frames < 1:
        print("bench_single_frame: --frames must be at least 1", file=sys.stderr)
        return 2
    hand = HandModel.load()
    try:
        bundle = load_bundle("fingerfist")
    except (OSError, SynergyError) as e:
        print(f"bench_single_frame: {e}", file=sys.stderr)
        return 2
    cam = preset("kinect1")
    rows, data = frames(hand, bundle, cam, a.frames, a.seed)
    strategies = ("halving",) if a.no_peer else ("halving", "exhaustive")
    trackers = {s: E._tracker(hand, bundle, mode="full",
                                init=dict(icp_iterations=a.icp, strategy=s, threads=1)) for s in strategies}
    # compile and warm up outside the timing (numba caches, first-call allocations)
    for tr in trackers.values():
        tr.fit_single_frame(data[0][1].points, theta0=data[0][3], mode=a.mode, silhouette=data[0][2],
                            normals=data[0][1].normals)
    print(f"single frame, {len(data)} fingerfist rows (seed {a.seed}), {a.mode}, one core; "
          f"{np.mean([len(d[1].points) for d in data]):.0f} points per frame")
    print(f"{'search':12s} {'start':12s} {'s/frame':>8s} {'CPU s':>7s} {'mean °':>7s} {'max °':>7s} {'≤ 2°':>6s}")
    res = {}
    for from_pose in (True, False):
        for s, tr in trackers.items():
            wall, cpu, err = run(tr, data, a.mode, from_pose)
            res[s, from_pose] = (wall, cpu, err)
            print(f"{s:12s} {'global pose' if from_pose else 'no pose':12s} {wall:8.3f} {cpu:7.3f} {err.mean():7.2f} "
                  f"{err.max():7.2f} {np.mean(err <= 2.0):6.0%}", flush=True)
    if not a.no_peer:
        for from_pose in (True, False):
            (w1, c1, _), (w0, c0, _) = res["halving", from_pose], res["exhaustive", from_pose]
            print(f"speed-up {'global pose' if from_pose else 'no pose'}: {w0 / w1:.1f}× wall, {c0 / c1:.1f}× CPU")
    worst = {s: rows[int(np.argmax(res[s, True][2]))] for s in strategies}
    print("worst row from the global pose: " + ", ".join(f"{s} {r}" for s, r in worst.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
