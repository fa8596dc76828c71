"""`make demo` (foundation stage): plausible postures → noisy keypoints → fit_keypoints → summary + PNGs.

Run: python -m handmodel.demo --out out
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def plausible_postures(hand, n, rng):
    """Procedural natural-looking postures: a grasp aperture shared by the fingers (the first
    synergy), thumb opposition, small independent deviations, fingers adducted when flexed."""
    lim = hand.limits
    th = np.zeros((n, hand.n_dofs))
    close = rng.beta(1.3, 1.3, n)  # 0 open … 1 fist
    names = hand.dof_names
    for f, spread in zip(["index", "middle", "ring", "pinky"], [0.15, 0.0, -0.12, -0.25]):
        th[:, names.index(f"{f}1_abd")] = (1 - close) * spread * rng.uniform(0.3, 1.2, n) + rng.normal(0, 0.03, n)
        for k, depth in zip((1, 2, 3), (1.1, 1.4, 0.9)):
            th[:, names.index(f"{f}{k}_flex")] = -depth * close * rng.uniform(0.8, 1.05, n) + rng.normal(0, 0.04, n)
    th[:, names.index("thumb1_abd")] = 0.15 * close + rng.normal(0, 0.05, n)
    th[:, names.index("thumb1_flex")] = -0.9 * close + rng.normal(0, 0.08, n)
    th[:, names.index("thumb2_flex")] = -0.5 * close + rng.normal(0, 0.05, n)
    th[:, names.index("thumb3_flex")] = -0.6 * close + rng.normal(0, 0.05, n)
    th[:, 6:] = np.clip(th[:, 6:], lim[6:, 0] + 1e-3, lim[6:, 1] - 1e-3)
    th[:, :3] = rng.normal(0, 0.03, (n, 3)) + [0.0, 0.0, 0.6]
    th[:, 3:6] = rng.uniform(-0.6, 0.6, (n, 3))
    return th


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", default="out")
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--noise-mm", type=float, default=1.0)
    args = ap.parse_args(argv)
    # a command-line entry point: the libraries load after parsing, so that --help answers at once
    from rich.console import Console
    from rich.table import Table

    from . import HandModel
    from .plots import mesh_figure, skeleton_figure
    from .solver import fit_keypoints

    con = Console()
    out = Path(args.out)
    hand = HandModel.load()
    rng = np.random.default_rng(0)
    truth = plausible_postures(hand, args.frames, rng)
    kp = hand.keypoints(truth)
    rows = []
    for label, noise in [("exact keypoints", 0.0), (f"{args.noise_mm:g} mm noise", args.noise_mm / 1000)]:
        obs = kp + rng.normal(0, noise, kp.shape) if noise else kp.copy()
        if noise:
            obs[rng.random(kp.shape[:2]) < 0.1] = np.nan  # and 10 % of the keypoints missing
            obs[:, 0] = kp[:, 0]
        fit_keypoints(hand, obs[:2])
        t = time.perf_counter()
        est, rep = fit_keypoints(hand, obs)
        dt = time.perf_counter() - t
        err = np.degrees(np.abs(est[:, 6:] - truth[:, 6:])).mean(1)
        rows.append((label + (", 10 % missing" if noise else ""), len(obs), f"{err.mean():.3f}", f"{np.percentile(err, 95):.3f}",
                     f"{np.nanmedian(rep.rms_mm):.3f}", f"{len(obs) / dt:,.0f}"))
    tab = Table(title="fit_keypoints on procedural postures (default hand)")
    for c in ("input", "frames", "mean posture error °", "95th pct °", "median RMS mm", "frames/s"):
        tab.add_column(c, justify="right")
    for r in rows:
        tab.add_row(*map(str, r))
    con.print(tab)
    pick = [int(np.argmin(np.abs(truth[:, 12] - v))) for v in (0.0, -0.5, -1.0, -1.4)]
    skel = out / "hand_skeleton.png"
    skeleton_figure(hand, [np.r_[np.zeros(6), truth[i, 6:]] for i in pick], [f"posture {i}" for i in pick], skel,
                    estimates=[np.r_[np.zeros(6), est[i, 6:]] for i in pick])
    mesh = out / "hand_mesh.png"
    mesh_figure(hand, [np.r_[np.zeros(6), truth[i, 6:]] for i in pick], [f"posture {i}" for i in pick], mesh)
    con.print(f"wrote {skel} (truth coloured, fit grey) and {mesh}")


if __name__ == "__main__":
    main()
