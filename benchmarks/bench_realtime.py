"""Real time as a user meets it: process start → first hand, then every frame's wall time, on
realistic sequences with fists, grasps and fast turns, and on the 19 labelled SR305 stills as one
recording; this tree next to a peer tree (``--peer REV``: a git revision checked out beside this
one, by default the last commit before the start-up and detector work) in the same run.

Each recording is tracked by ``tracker track``'s own path (:func:`tracker.run.run_job`, defaults,
the ``fingerfist`` bundle) in a fresh Python process per tree, with warm numba caches (one untimed
run first). Per recording and tree the table gives the time from spawning the process to the first
frame's result, and over the frames after the first: p50 / p95 / max ms and the frames over 33 ms
(a 30 fps sensor's budget). A frame's time is the wall time between two results: segmentation,
fit, the safety net's searches and re-initialisations all count.

Sequences (rendered by :func:`tracker.sim.synthesize.synthesize`, seed 0, forearm + torso): open-close
(a fist every 2 s), grasp-back (a power grasp seen from the back), rotate (palm → back), fast (1.1 m/s
sweeps), under Kinect v1 and RealSense SR305 noise, hands 0.8× and 1.5× the model.

``--search-budget-ms B`` adds this tree with the start searches' budget (``start.search_budget_ms``);
``--no-detector`` this tree without the keypoint detector (on by default: ``start.detector``), every
start the full search; ``--scale-budget N …`` this tree with each of these size-work budgets
(``scale.budget``, ICP iterations a frame; 0 = the size's work at once, as before it was spread);
``--scale-search`` this tree with the size refined as before the spread work (``scale.refine="search"``,
``scale.budget=0``); ``--changes JSON …`` this tree with each of these settings changes.

Run: .venv/bin/python benchmarks/bench_realtime.py [--frames 60] [--peer REV] [--no-peer] [--no-stills]
[--search-budget-ms B] [--no-detector] [--scale-budget N ...] [--scale-search] [--changes JSON ...]
[--only NAME ...]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STILLS = ROOT.parent / "shared" / "data" / "realsense_sr305_lada"
PEER_REV = "da35d42"  # main before the architecture, start-up and detector issues (2026-11-28)
SEQUENCES = (("open-close", "kinect1", 1.0), ("grasp-back", "kinect1", 0.8), ("rotate", "realsense", 1.0),
             ("fast", "kinect1", 1.5), ("open-close", "realsense", 1.5), ("grasp-back", "realsense", 1.0))

# what runs in the child process: only tracker.run's TrackJob / run_job, present in both trees
DRIVER = r"""
import json, sys, time
t_import = time.time()
from tracker.run import TrackJob, run_job
rec, out, synergies = sys.argv[1:4]
kw = {}
if len(sys.argv) > 4:  # settings changes as JSON (this tree only: the peer runs its defaults)
    from tracker.settings import TrackerSettings
    kw["settings"] = TrackerSettings().replace(**json.loads(sys.argv[4]))
stamps = []
run_job(TrackJob(rec, out, synergies=synergies, overwrite=True, **kw),
        on_frame=lambda frame, r, ob: stamps.append((time.time(), r.status)))
print(json.dumps({"import": t_import, "stamps": stamps}))
"""


def child_env(src: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(src)
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.setdefault(var, "1")
    return env


def track_timed(src: Path, rec: Path, out: Path, changes: dict | None = None) -> dict:
    """Spawn a process that tracks ``rec`` with the tree at ``src`` (``changes``: its
    :class:`tracker.settings.TrackerSettings` changes); the times as seen from here."""
    t0 = time.time()
    extra = [json.dumps(changes)] if changes else []
    p = subprocess.run([sys.executable, "-c", DRIVER, str(rec), str(out), "fingerfist", *extra], env=child_env(src),
                       capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"tracking {rec} with {src} failed:\n{p.stderr[-2000:]}")
    res = json.loads(p.stdout.strip().splitlines()[-1])
    t = [s[0] for s in res["stamps"]]
    per_frame = [1000.0 * (b - a) for a, b in zip(t, t[1:])]
    lost = sum(s[1] == "lost" for s in res["stamps"])
    return {"first_s": t[0] - t0, "frames_ms": per_frame, "lost": lost, "n": len(t)}


def percentile(xs, q):
    s = sorted(xs)
    if not s:
        return float("nan")
    k = (len(s) - 1) * q / 100.0
    lo, hi = int(k), min(int(k) + 1, len(s) - 1)
    return s[lo] + (s[hi] - s[lo]) * (k - lo)


def make_recordings(folder: Path, frames: int, stills: bool) -> list:
    sys.path.insert(0, str(ROOT / "src"))
    from handmodel import HandModel
    from tracker import TRACKING_HAND
    from tracker.sim.hands import HandShape
    from tracker.sim.synthesize import synthesize

    hand = HandModel.load(TRACKING_HAND)
    recs = []
    for motion, noise, scale in SEQUENCES:
        cam = "sr305" if noise == "realsense" else "kinect1"
        out = folder / f"{motion}-{noise}-{scale:g}"
        synthesize(motion, cam, noise, out, frames=frames, hand=hand, clutter="forearm,torso",
                   shape=HandShape(scale))
        recs.append((f"{motion}, {noise}, {scale:g}×", out))
    if stills and STILLS.is_dir():
        out = folder / "sr305-stills"
        p = subprocess.run([sys.executable, "-c", "from tracker.cli import main; main()", "import", str(STILLS),
                            "-o", str(out), "--camera", "sr305", "--hand", "right"], env=child_env(ROOT / "src"),
                           capture_output=True, text=True)
        if p.returncode != 0:
            raise SystemExit(f"importing the stills failed: {p.stderr[-1000:]}")
        recs.append(("SR305 stills (19, one recording)", out))
    return recs


def peer_tree(rev: str, where: Path) -> Path:
    subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", str(where), rev], check=True,
                   capture_output=True)
    return where


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--peer", default=PEER_REV, help="git revision of the peer tree")
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--no-stills", action="store_true")
    ap.add_argument("--search-budget-ms", type=float, default=0.0,
                    help="also this tree with this start-search budget (start.search_budget_ms)")
    ap.add_argument("--no-detector", action="store_true",
                    help="also this tree without the keypoint detector (start.detector \"\", every start the full search)")
    ap.add_argument("--scale-budget", type=int, nargs="*", default=[],
                    help="also this tree with each of these size-work budgets (scale.budget, ICP iterations a frame)")
    ap.add_argument("--scale-search", action="store_true",
                    help="also this tree with the size refined as before its work was spread (refine search, budget 0)")
    ap.add_argument("--changes", nargs="*", default=[],
                    help="also this tree with each of these settings changes (TrackerSettings.replace as JSON)")
    ap.add_argument("--only", nargs="*", default=None, help="only the recordings whose name starts with one of these")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_realtime_") as tmp:
        tmp = Path(tmp)
        recs = make_recordings(tmp / "recs", a.frames, not a.no_stills)
        if a.only:
            recs = [r for r in recs if any(r[0].startswith(o) for o in a.only)]
        trees = [("this tree", ROOT / "src", None)]
        for b in a.scale_budget:
            trees.append((f"scale.budget {b}", ROOT / "src", {"scale": {"budget": b}}))
        for c in a.changes:
            trees.append((c.replace(" ", "")[:14], ROOT / "src", json.loads(c)))
        if a.scale_search:
            trees.append(("size search", ROOT / "src", {"scale": {"refine": "search", "budget": 0}}))
        if a.search_budget_ms:
            trees.append((f"budget {a.search_budget_ms:g} ms", ROOT / "src",
                          {"start": {"search_budget_ms": a.search_budget_ms}}))
        if a.no_detector:
            trees.append(("no detector", ROOT / "src", {"start": {"detector": ""}}))
        if not a.no_peer:
            trees.append((f"peer {a.peer}", peer_tree(a.peer, tmp / "peer") / "src", None))
        for _, src, _ in trees:  # warm each tree's numba cache, untimed
            track_timed(src, recs[0][1], tmp / "warm.csv")
        print(f"{'recording':36s} {'tree':14s} {'first s':>8s} {'p50 ms':>7s} {'p95 ms':>7s} {'max ms':>7s} "
              f"{'>33 ms':>7s} {'lost':>5s}")
        for name, rec in recs:
            for tree, src, changes in trees:
                r = track_timed(src, rec, tmp / "t.csv", changes)
                f = r["frames_ms"]
                print(f"{name:36s} {tree:14s} {r['first_s']:8.2f} {percentile(f, 50):7.1f} {percentile(f, 95):7.1f} "
                      f"{max(f) if f else float('nan'):7.1f} {sum(x > 33.0 for x in f):4d}/{len(f):<3d}"
                      f"{r['lost']:4d}", flush=True)
        if not a.no_peer:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tmp / "peer")],
                           capture_output=True)


if __name__ == "__main__":
    main()
