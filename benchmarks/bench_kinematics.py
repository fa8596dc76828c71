"""Forward kinematics, Jacobians and fit_keypoints throughput (one core), with a
scipy.optimize.least_squares peer on the same frames at equal accuracy.

Run: .venv/bin/python benchmarks/bench_kinematics.py [--frames 1000]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np
from scipy.optimize import least_squares

from handmodel import HandModel
from handmodel.solver import fit_keypoints, rigid_pose_from_keypoints


def best_of(fn, repeat=3):
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--peer-frames", type=int, default=200, help="frames for the (slow) scipy peer")
    args = ap.parse_args()
    hand = HandModel.load()
    rng = np.random.default_rng(0)
    F = args.frames
    lim = hand.limits
    truth = np.zeros((F, 26))
    truth[:, 6:] = rng.uniform(lim[6:, 0] + 0.02, lim[6:, 1] - 0.02, (F, 20))
    truth[:, :3] = rng.normal(0, 0.05, (F, 3)) + [0, 0, 0.7]
    truth[:, 3:6] = rng.uniform(-1.5, 1.5, (F, 3))
    kp = hand.keypoints(truth)
    hand.keypoints(truth[:2]), hand.jacobian(truth[:2]), fit_keypoints(hand, kp[:2])  # compile / load cache

    t_fk = best_of(lambda: hand.keypoints(truth))
    t_j = best_of(lambda: hand.jacobian(truth))
    t_fit = best_of(lambda: fit_keypoints(hand, kp), repeat=2)
    est, rep = fit_keypoints(hand, kp)
    err = np.degrees(np.abs(est[:, 6:] - truth[:, 6:])).mean(1)

    # peer: scipy least_squares per frame, analytic Jacobian, same start, same bounds
    P = min(args.peer_frames, F)
    starts = rigid_pose_from_keypoints(hand, kp[:P])
    lo = np.where(np.isfinite(lim[:, 0]), lim[:, 0], -np.inf)
    hi = np.where(np.isfinite(lim[:, 1]), lim[:, 1], np.inf)

    def peer():
        out = np.empty((P, 26))
        for f in range(P):
            tgt = kp[f].ravel()
            r = least_squares(lambda th: (hand.keypoints(th).ravel() - tgt) * 1000.0, starts[f],
                              jac=lambda th: hand.jacobian(th).reshape(-1, 26) * 1000.0,
                              bounds=(lo, hi), method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)
            out[f] = r.x
        return out

    t0 = time.perf_counter()
    est_p = peer()
    t_peer = time.perf_counter() - t0
    err_p = np.degrees(np.abs(est_p[:, 6:] - truth[:P, 6:])).mean(1)
    fps_fit = F / t_fit
    fps_peer = P / t_peer
    rows = [
        ("forward kinematics (21 keypoints)", f"{F / t_fk:,.0f} frames/s", ""),
        ("keypoint Jacobian (21×3×26)", f"{F / t_j:,.0f} frames/s", ""),
        ("fit_keypoints, exact keypoints, from the flat hand", f"{fps_fit:,.0f} frames/s",
         f"mean posture error {err.mean():.4f}°, median {np.median(err):.5f}°"),
        ("peer: scipy least_squares (trf, analytic J, bounds)", f"{fps_peer:,.0f} frames/s",
         f"mean posture error {err_p.mean():.4f}°, median {np.median(err_p):.5f}° ({P} frames)"),
        ("speed-up over the peer", f"{fps_fit / fps_peer:,.1f}×", ""),
    ]
    w = max(len(r[0]) for r in rows)
    print(f"bench_kinematics: {F} random in-limit postures, default hand, one core")
    for a, b, c in rows:
        print(f"  {a:<{w}}  {b:>18}  {c}")


if __name__ == "__main__":
    main()
