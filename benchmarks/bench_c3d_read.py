"""Read time of synergy.read_c3d against raw ezc3d on the same files.

Files: the largest real C3D of ../shared/data (if present) and a simulated
20,000 frames x 40 markers trial written with write_c3d. Target: overhead <= 1.5x.

Run: .venv/bin/python benchmarks/bench_c3d_read.py [--repeats N]
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from synergy.c3d import read_c3d
from synergy.c3d_write import write_c3d

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TARGET = 1.5


def largest_real_c3d() -> Path | None:
    if not DATA.is_dir():
        return None
    files = [p for p in DATA.rglob("*") if p.suffix.lower() == ".c3d" and p.stat().st_size > 0]
    for path in sorted(files, key=lambda p: p.stat().st_size, reverse=True):
        try:
            if read_c3d(path).backend == "ezc3d":   # the peer must be able to read it
                return path
        except Exception:
            continue
    return None


def simulated(folder: Path, n_frames: int = 20_000, n_markers: int = 40) -> Path:
    rng = np.random.default_rng(0)
    t = np.arange(n_frames)[:, None, None] / 100.0
    pts = 0.5 + 0.3 * np.sin(2 * np.pi * 0.7 * t + rng.uniform(0, 6, (1, n_markers, 3)))
    pts[rng.random((n_frames, n_markers)) < 0.05] = np.nan        # 5 % gaps
    labels = [f"M{i:02d}" for i in range(n_markers)]
    return write_c3d(folder / "sim_20000x40.c3d", pts, labels, 100.0, prefix="Sim")


def time_ms(fn, repeats: int) -> float:
    fn()  # warm up (imports, page cache)
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        runs.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(runs)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()

    import ezc3d

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        files = [p for p in (largest_real_c3d(), simulated(Path(tmp))) if p is not None]
        for path in files:
            d = read_c3d(path)
            ours = time_ms(lambda: read_c3d(path), args.repeats)
            peer = time_ms(lambda: ezc3d.c3d(str(path)), args.repeats)
            rows.append((path.name, f"{d.n_frames}x{d.n_markers}", f"{path.stat().st_size / 1e6:.1f}",
                         ours, peer, ours / peer))

    head = ("file", "frames x markers", "MB", "ours ms", "ezc3d ms", "overhead")
    widths = [max(len(head[0]), *(len(r[0]) for r in rows)), 16, 5, 9, 9, 9]
    print(f"read_c3d vs raw ezc3d.c3d(), median of {args.repeats} runs (target overhead <= {TARGET}x)")
    print("  ".join(h.ljust(w) if i < 3 else h.rjust(w) for i, (h, w) in enumerate(zip(head, widths))))
    for name, shape, mb, ours, peer, ratio in rows:
        print("  ".join([name.ljust(widths[0]), shape.ljust(widths[1]), mb.ljust(widths[2]),
                         f"{ours:9.1f}", f"{peer:9.1f}", f"{ratio:8.2f}x"]))
    worst = max(r[5] for r in rows)
    print(f"worst overhead {worst:.2f}x: {'meets' if worst <= TARGET else 'MISSES'} the {TARGET}x target")


if __name__ == "__main__":
    main()
