"""Synergy PCA fit on 1,000,000 × 20 postures: ours (sufficient statistics + limits pass)
next to scikit-learn's exact PCA (full SVD) on the same data, in the same run.

Run: ``.venv/bin/python benchmarks/bench_synergy.py``; exits 1 if our fit misses its floor.
"""
from __future__ import annotations

import sys
import time

import numpy as np
from rich.console import Console
from rich.table import Table
from sklearn.decomposition import PCA

from synergy.pca import SufficientStats, SynergyModel

N, D = 1_000_000, 20
FLOOR_S = 5.0
REPEATS = 3


def postures(n=N, d=D, seed=0):
    """Posture-like data: a few strong synergies plus noise, radians."""
    rng = np.random.default_rng(seed)
    latent = rng.normal(size=(n, 6)) * np.array([0.8, 0.3, 0.25, 0.2, 0.15, 0.1])
    mix = rng.normal(size=(6, d)) / np.sqrt(d)
    return latent @ mix * 3 + 0.02 * rng.normal(size=(n, d)) - 0.5


def best_of(fn, repeats=REPEATS):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> int:
    X = postures()
    chunks = np.array_split(X, 7)

    def streamed():
        m = SufficientStats.merge_all(SufficientStats.from_array(c) for c in chunks).finalize()
        for c in chunks:
            m.update_limits(c)
        return m

    t_ours, ours = best_of(lambda: SynergyModel().fit(X))
    t_stream, stream = best_of(streamed)
    t_sk, sk = best_of(lambda: PCA(svd_solver="full").fit(X))

    dv = np.abs(ours.explained_variance_ - sk.explained_variance_).max()
    dv_rel = dv / sk.explained_variance_[0]
    dv_stream = np.abs(stream.explained_variance_ - sk.explained_variance_).max()
    cos = np.abs(np.sum(ours.components_[:6] * sk.components_[:6], axis=1)).min()

    t = Table(title=f"PCA fit, {N:,} × {D} postures, best of {REPEATS}")
    t.add_column("method")
    t.add_column("seconds", justify="right")
    t.add_column("max |Δ variance| vs sklearn", justify="right")
    t.add_row("ours: SynergyModel().fit", f"{t_ours:.3f}", f"{dv:.1e}")
    t.add_row("ours: 7 chunks, merge+limits", f"{t_stream:.3f}", f"{dv_stream:.1e}")
    t.add_row("sklearn PCA(svd_solver='full')", f"{t_sk:.3f}", "-")
    console = Console(width=100)
    console.print(t)
    console.print(
        f"ours includes the PC-limits pass; relative Δ variance {dv_rel:.1e}\n"
        f"min |cos| PC1-6 vs sklearn {cos:.12f}\n"
        f"speed-up vs sklearn {t_sk / t_ours:.1f}×; floor {FLOOR_S:.1f} s: "
        f"{'ok' if t_ours <= FLOOR_S else 'MISSED'}"
    )
    return 0 if t_ours <= FLOOR_S and dv_rel < 1e-9 else 1


if __name__ == "__main__":
    sys.exit(main())
