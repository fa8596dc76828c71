"""Start-up as a user meets it: a fresh process from its start to the first frame's result, warm numba
cache, next to ``python -c "import numpy, scipy"`` in the same run (the floor any numpy/scipy tool pays).

Rows (each a fresh process, ``--repeats`` times, interleaved; median wall and median CPU — user + sys
of the child — since on a shared machine wall time also measures the other jobs):

- ``python -c "import numpy, scipy"``: the reference;
- ``tracker --help``;
- ``import tracker.run``: what every tracking command loads;
- process start → first frame's result: ``tracker.run.run_job`` on one still (one SR305 frame of
  ``../shared/data/realsense_sr305_lada``, or a rendered frame without it) with ``tracker track``'s
  settings (the library's defaults and the handedness check, ``--check-hand``: on the first frame the
  mirror-image hand's start search too), the time of the first result as seen from the parent;
- ``tracker track`` of that still: the whole command, outputs written, up to the process's end;
- the same with ``--no-check-hand``: what the handedness check costs the whole command;
- ``tracker track`` of a recording that is not there: the time to its one-line error (exit status 2).

The first-frame row's line below the table splits the frame (medians): the kernels numba loads from its
cache (the time its compiler lock is held, through numba's event API; a cold cache's compiling would show
here), the size calibration and the handedness check's mirror-image search (each less the kernels loaded
within it), and the rest (the tracker's parts, the segmentation, the detectors' networks).

"Warm" is what an installed package has: numba's cache (one untimed run first fills it; ``tracker
compile`` does it at install) and Python's bytecode cache (``pip install`` compiles the modules; an
editable install writes them at the first import). The children keep their bytecode in a folder of
their own (``PYTHONPYCACHEPREFIX``, filled by that first run), also where the environment says
``PYTHONDONTWRITEBYTECODE`` (without a cache every module of the package is compiled from source at
each start: 0.10 s of ``import tracker.run``, 0.13 s of a one-still ``tracker track`` here, 8 pairs at
load ~3); ``--no-pyc`` measures that case. The kernels are this tree's (``src`` first on the path).
``--peer DIR``: the same rows with another checkout's ``src`` (e.g. a ``git worktree`` of an earlier
commit; its numba cache is its own, warmed the same way), interleaved with this tree's in the same
run, so both see the same load.

Run: .venv/bin/python benchmarks/bench_startup.py [--repeats 5] [--peer ../wt-old] [--no-pyc] [--only track]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STILL = ROOT.parent / "shared" / "data" / "realsense_sr305_lada" / "20210326-230536_110.png"

# the child: the time after its imports, each frame's result time and, up to the first result, where the
# frame's time went (the kernels loaded from numba's cache, the size calibration, the handedness check), as
# json on stdout
DRIVER = r"""
import json, sys, threading, time
from tracker.run import TrackJob, run_job
from tracker.settings import TrackerSettings
t_import = time.time()
from numba.core import event  # loaded with tracker.run: numba's event API times the compiler lock
from numba.core.registry import CPUDispatcher


class Kernels(event.Listener):
    # the time the compiler lock is held (from the first request to the last release when threads
    # overlap): loading a kernel from the cache, or compiling it when the cache is cold
    def __init__(self):
        self.lock, self.depth, self.total = threading.Lock(), 0, 0.0

    def on_start(self, ev):
        with self.lock:
            if self.depth == 0:
                self.t0 = time.perf_counter()
            self.depth += 1

    def on_end(self, ev):
        with self.lock:
            self.depth -= 1
            if self.depth == 0:
                self.total += time.perf_counter() - self.t0


kernels, spans = Kernels(), {}
event.register("numba:compiler_lock", kernels)


def timed(module, owner, name, key):
    # the wall time of a stage, less the kernels loaded within it (counted once, as kernels); a tree
    # without that function (a --peer of another time) leaves the stage out of the breakdown
    try:
        owner = getattr(__import__(module, fromlist=["_"]), owner) if owner else __import__(module, fromlist=["_"])
        f = getattr(owner, name)
    except (ImportError, AttributeError):
        return
    timing.append(key)

    def g(*a, **k):
        t, k0 = time.perf_counter(), kernels.total
        try:
            return f(*a, **k)
        finally:
            spans[key] = spans.get(key, 0.0) + (time.perf_counter() - t) - (kernels.total - k0)
    setattr(owner, name, g)


timing, stamps, first = [], [], {}
timed("tracker.sizing", "SizeCalibration", "calibrate", "size")
timed("tracker.track", None, "check_hand", "hand_check")


def loaded():
    # each kernel once (a module that imports another's kernel holds the same dispatcher)
    found = {id(d): d for m in list(sys.modules.values()) for d in list(getattr(m, "__dict__", {}).values())
             if isinstance(d, CPUDispatcher)}
    return sum(sum(d.stats.cache_hits.values()) for d in found.values())


def on_frame(frame, r, ob):
    stamps.append(time.time())
    if not first:
        first.update({k: spans.get(k, 0.0) for k in timing}, kernels=kernels.total, loaded=loaded())


settings = TrackerSettings().replace(start=dict(check_hand=True))  # tracker track's --check-hand, its default
run_job(TrackJob(sys.argv[1], sys.argv[2], settings=settings, overwrite=True), on_frame=on_frame)
print(json.dumps({"import": t_import, "stamps": stamps, "first": first}))
"""


#: the rows: short name (``--only``) → label
ROWS = {"reference": 'python -c "import numpy, scipy" (reference)', "help": "tracker --help",
        "import": "import tracker.run", "first": "process start -> first frame's result (one still)",
        "track": "tracker track of one still (whole command)",
        "nocheck": "the same, --no-check-hand",
        "missing": "tracker track of a missing recording (its error)"}

#: where the children keep their bytecode (None: as the environment says); set by main()
PYCACHE: Path | None = None


def env(src=ROOT / "src"):
    e = dict(os.environ)
    e["PYTHONPATH"] = str(src) + os.pathsep + e.get("PYTHONPATH", "")
    if PYCACHE is None:
        e["PYTHONDONTWRITEBYTECODE"] = "1"  # --no-pyc: every module compiled at each start
    else:
        e.pop("PYTHONDONTWRITEBYTECODE", None)
        e["PYTHONPYCACHEPREFIX"] = str(PYCACHE)
    return e


def timed(cmd, src=ROOT / "src", status=0):
    """``(wall s, cpu s, stdout, start time)`` of one child process (cpu: the child's user + sys) with
    the package of ``src``; it must end with exit ``status``."""
    before = os.times()
    t0 = time.time()
    p = subprocess.run(cmd, env=env(src), capture_output=True, text=True)
    wall = time.time() - t0
    after = os.times()
    if p.returncode != status:
        raise SystemExit(f"{' '.join(map(str, cmd))} failed:\n{p.stderr[-2000:]}")
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return wall, cpu, p.stdout, t0


def make_still(folder: Path) -> Path:
    """A one-frame recording: the SR305 still, or a rendered frame when the data is not beside the checkout."""
    rec = folder / "still"
    if STILL.is_file():
        src = folder / "png"
        src.mkdir()
        shutil.copy(STILL, src / STILL.name)
        timed([sys.executable, "-m", "tracker.cli", "import", str(src), "-o", str(rec), "--camera", "sr305",
               "--hand", "right"])
        return rec
    timed([sys.executable, "-m", "tracker.cli", "synth", "--motion", "grasp-back", "--noise", "realsense",
           "--camera", "sr305", "--frames", "1", "-o", str(rec)])
    return rec


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--peer", type=Path, default=None,
                    help="another checkout (its src/) timed with the same rows, interleaved")
    ap.add_argument("--no-pyc", action="store_true",
                    help="no bytecode cache: the children compile every module at each start (PYTHONDONTWRITEBYTECODE)")
    ap.add_argument("--only", default=",".join(ROWS),
                    help=f"the rows to time, comma-separated, of {', '.join(ROWS)} [all]; e.g. --only track "
                         "--repeats 16 for the whole command alone, more often")
    args = ap.parse_args()
    only = [k.strip() for k in args.only.split(",") if k.strip()]
    if not only or set(only) - set(ROWS):
        raise SystemExit(f"--only: rows are {', '.join(ROWS)}, got {args.only!r}")
    global PYCACHE
    py = sys.executable
    trees = {"this tree": ROOT / "src"}
    if args.peer is not None:
        if not (args.peer / "src" / "tracker").is_dir():
            raise SystemExit(f"--peer {args.peer}: no src/tracker in it")
        trees["peer"] = args.peer.resolve() / "src"
    with tempfile.TemporaryDirectory(prefix="bench-startup-") as tmp:
        tmp = Path(tmp)
        PYCACHE = None if args.no_pyc else tmp / "pycache"
        rec = make_still(tmp)
        out = tmp / "out.csv"
        commands = {
            "reference": [py, "-c", "import numpy, scipy"],
            "help": [py, "-m", "tracker.cli", "--help"],
            "import": [py, "-c", "import tracker.run"],
            "first": [py, "-c", DRIVER, str(rec), str(out)],
            "track": [py, "-m", "tracker.cli", "track", str(rec), "-o", str(out), "--overwrite"],
            "nocheck": [py, "-m", "tracker.cli", "track", str(rec), "-o", str(out), "--overwrite", "--no-check-hand"],
            "missing": [py, "-m", "tracker.cli", "track", str(tmp / "none"), "-o", str(out), "--overwrite"],
        }
        for src in trees.values():
            # warms numba's cache and the bytecode cache (the driver's imports too)
            timed(commands["track"], src)
            timed(commands["first"], src)
        rows = {ROWS[k]: commands[k] for k in ROWS if k in only}
        failing = {ROWS["missing"]}
        walls = {(t, k): [] for t in trees for k in rows}
        cpus = {(t, k): [] for t in trees for k in rows}
        first = {t: [] for t in trees}
        for r in range(args.repeats):
            for label, cmd in rows.items():
                # the trees take turns to go first: neither always meets the other's wake
                for tree, src in list(trees.items())[:: 1 if r % 2 == 0 else -1]:
                    wall, cpu, stdout, t0 = timed(cmd, src, status=2 if label in failing else 0)
                    if label.startswith("process start"):
                        res = json.loads(stdout.strip().splitlines()[-1])
                        first[tree].append((res["import"] - t0, res["stamps"][0] - t0, res["first"]))
                        wall = res["stamps"][0] - t0
                    walls[tree, label].append(wall)
                    cpus[tree, label].append(cpu)
    print(f"bench_startup: median of {args.repeats} fresh processes each, warm numba cache, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}"
          + (", no bytecode cache" if args.no_pyc else "")
          + (f"; peer: {args.peer}" if args.peer is not None else ""))
    # a tree without ../shared beside it times another frame: its figures do not compare with the README's
    frame = (f"the SR305 still {STILL.name}" if STILL.is_file()
             else f"a rendered SR305 frame ({STILL.parent} is absent): not the still of the README's row")
    print(f"  timed on {frame}")
    for tree in trees:
        print(f"  {tree + ':':58s} {'wall s':>8s} {'CPU s':>8s}")
        for label in rows:
            print(f"  {label:58s} {statistics.median(walls[tree, label]):8.2f} "
                  f"{statistics.median(cpus[tree, label]):8.2f}")
        if not first[tree]:
            continue
        imp = statistics.median(a for a, _, _ in first[tree])
        frame = statistics.median(b - a for a, b, _ in first[tree])
        print(f"  first frame: imports {imp:.2f} s, then the frame (size calibration, start search, "
              f"handedness check) {frame:.2f} s (wall, medians); CPU of the whole child above")
        parts = [p for _, _, p in first[tree]]
        med = {k: f"{statistics.median(p[k] for p in parts):.2f} s" if k in parts[0] else "-"
               for k in ("kernels", "size", "hand_check")}
        rest = statistics.median(b - a - sum(p.get(k, 0.0) for k in ("kernels", "size", "hand_check"))
                                 for a, b, p in first[tree])
        print(f"    the frame: {statistics.median(p['loaded'] for p in parts):.0f} kernels loaded from numba's cache "
              f"{med['kernels']}, size calibration {med['size']}, handedness check {med['hand_check']} (each "
              f"without the kernels it loaded), the rest (the tracker, segmentation, detectors) {rest:.2f} s")


if __name__ == "__main__":
    main()
