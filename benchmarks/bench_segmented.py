"""Tracking with segmentation on realistic scenes: each frame's ``observe`` (the hand segmented from
the depth and colour frame in the predicted hand's window, :meth:`FrameTracker.segment_window`, points
and normals) plus the tracker's step, CPU time of one core, next to the tracker's step alone on the
same frames (what the per-frame loop costs without finding the hand) and to the same loop with the
whole-frame segmenter (``observe`` without a window, timed on the same frames). Scenes as the
realistic-scenes experiment renders them (open/close, 30 frames, hands 1.0× with fingers 0.9–1.1×,
forearm + torso / table, Kinect v1 and SR305 noise), today's default tracker with the size calibrated;
the first frames (the start search and the size) are left out, as the rate is the tracking rate. Each
frame is observed through one :class:`tracker.segment.Segmenter` per pass, as ``tracker track`` and
the streaming API hold one (its work buffers serve every frame).

Each scene is tracked ``--repeat`` times from the start by a fresh tracker (the same work each pass:
the tracker is deterministic) and each frame's stages are timed at the fastest pass, as ``timeit``
advises on a shared machine: the other passes only add what other processes took. The mean over the
passes is printed beside it.

The windowed ``observe`` is also timed per stage in ``--stage-passes`` further passes (exclusive CPU
time of the functions named in :data:`STAGES`, each wrapped while the bench runs; "observe, rest" is
what its total leaves: the frame's conversion, the full-frame arrays, the glue between the stages):
the median over the frames of each frame's fastest such pass (and the mean). The wrappers cost about
0.2 ms a frame, which those passes' totals include and the rates above do not. A stage a tree does not
have shows "-".

``--peer DIR``: the same bench run on another checkout's ``src`` (e.g. ``git worktree add /tmp/peer
HEAD`` made before a change), scene by scene in turn with this tree's, each in a fresh process with
the same harness (this file): the two trees' rows side by side from one run.

``--depth-only``: the same frames observed without their colour frames alone, as from a depth-only
recording (no skin test: the segmenter leaves out the table's plane and prefers the surface with
fingers, :mod:`tracker.segment`); ``--colour-only``: with them alone; by default both.

``--observations FILE``: no timing; every field of every observation of the scenes' frames (the windowed
``observe`` with the windows this tree's tracker chose, and the whole-frame one; colour and depth only) as
a SHA-1 of its bytes, type and shape, written to FILE with the windows (4 scenes × 30 frames × 2 modes × 2
× 9 fields: 4,320 arrays and values). With ``--windows FILE`` (an earlier record), those windows are used
and nothing is tracked. Two trees observe alike, to the bit, when their records are the same file: a
change to the segmentation made for speed is checked so.

Run: .venv/bin/python benchmarks/bench_segmented.py [--frames 30] [--repeat 3] [--stage-passes 2]
[--depth-only | --colour-only] [--peer DIR] [--observations FILE [--windows FILE]]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

# one core: numba, OpenMP and BLAS threads (before numpy and numba are imported)
for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import importlib

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCENES = (("kinect1", "forearm,torso"), ("kinect1", "forearm,table"), ("realsense", "forearm,torso"),
          ("realsense", "forearm,box"))
MODES = ("colour", "depth only")

#: the stages of the windowed ``observe`` timed: (label, module, attribute) — a function, or a method as
#: ``Class.method``, wrapped where its callers look it up; nested stages count apart (exclusive times)
STAGES = (
    ("frame's plane (depth only)", "tracker.segment.segmenter", "Segmenter.frame_plane"),
    ("volume, skin, plane pixels", "tracker.segment.segmenter", "Segmenter._valid"),
    ("volume, skin, plane pixels", "tracker.segment.segmenter", "valid_depths"),
    ("surfaces (labels, fronts)", "tracker.segment.region", "surfaces"),
    ("surfaces (labels, fronts)", "tracker.segment.region", "surface_fronts"),
    ("surfaces (labels, fronts)", "tracker.segment.layers", "surfaces"),
    ("region (seed, reach, blobs)", "tracker.segment.segmenter", "hand_region"),
    ("fingers, arm ends", "tracker.segment.region", "_has_fingers"),
    ("fingers, arm ends", "tracker.segment.region", "_fingered_end"),
    ("fingers, arm ends", "tracker.segment.region", "_hand_end"),
    ("fingers, arm ends", "tracker.segment.region", "_far_end"),
    ("layer in front", "tracker.segment.region", "_in_front"),
    ("joins (table, body)", "tracker.segment.segmenter", "_joins"),
    ("wrist cut", "tracker.segment.segmenter", "cut_forearm"),
    ("refine (full resolution)", "tracker.segment.segmenter", "refine"),
    ("whole frame (window refused)", "tracker.segment.segmenter", "Segmenter.__call__"),
    ("points, normals", "tracker.observe", "observe_window"),
    ("dropout band", "tracker.observe", "dropout_band"),
)
#: stages whose nested calls count as theirs (the whole frame's segmentation after a refused window)
ABSORBING = {"whole frame (window refused)"}
REST = "observe, rest"


class StageTimer:
    """Exclusive CPU time per stage label while ``active`` (the wrapped calls nest: a call's time less
    its wrapped callees' goes to its label)."""

    def __init__(self):
        self.active = False
        self.times = {}
        self._stack = []  # per open call: [label, start, time spent in wrapped callees]
        self._absorbed = 0

    def wrap(self, label, fn):
        timer = self

        def timed(*args, **kwargs):
            if not timer.active or timer._absorbed:
                return fn(*args, **kwargs)
            entry = [label, time.process_time(), 0.0]
            timer._stack.append(entry)
            timer._absorbed += label in ABSORBING
            try:
                return fn(*args, **kwargs)
            finally:
                timer._absorbed -= label in ABSORBING
                timer._stack.pop()
                spent = time.process_time() - entry[1]
                timer.times[label] = timer.times.get(label, 0.0) + spent - entry[2]
                if timer._stack:
                    timer._stack[-1][2] += spent

        timed.__wrapped__ = fn
        return timed

    def install(self):
        """Wrap every stage this tree has; returns the labels found."""
        found = []
        for label, module, attr in STAGES:
            try:
                mod = importlib.import_module(module)
            except ImportError:
                continue
            owner, name = mod, attr
            if "." in attr:
                cls, name = attr.split(".")
                owner = getattr(mod, cls, None)
            if owner is None or not hasattr(owner, name):
                continue
            setattr(owner, name, self.wrap(label, getattr(owner, name)))
            found.append(label)
        return found

    def take(self):
        out, self.times = self.times, {}
        return out


def frames_of(hand, sensor, spec, n, color=True):
    from tracker.io.cameras import preset
    from tracker.sim import experiments as E
    from tracker.sim.hands import HandShape
    from tracker.sim.motions import make_motion
    from tracker.sim.noise import NoiseModel
    from tracker.sim.render import DepthRenderer

    cam_name, noise_name = E.REALISTIC_SENSORS[sensor]
    cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
    shown = HandShape(1.0, E.realistic_fingers(1.0)).apply(hand)
    truth = make_motion("open-close", hand=shown, frames=n, seed=0).theta
    clutter = E.placed_clutter(spec, hand, shown, truth)
    ren = DepthRenderer(shown, cam)
    out = []
    for f in range(n):
        r = ren.render(truth[f], labels=False, color=True, clutter=clutter, incidence=nm.needs_incidence,
                       reflectance=nm.needs_reflectance)
        out.append((nm.apply(r.depth, cam, np.random.default_rng([0, f]), r.cos_incidence, r.reflectance),
                    r.color if color else None))
    return cam, out


def skip_frames(busy) -> int:
    """The frames left out: the start and the size's work (calibration, refinement, finger lengths, spread
    over the first frames by ``scale.budget``) are not the tracking rate. ``busy``: per frame, whether the
    size's work was under way when it was tracked (``calibrating()`` or ``refining()``, which either tree
    has); the frames from the first one without it are kept."""
    return next((i for i, b in enumerate(busy) if not b), len(busy))


def track_pass(hand, bundle, cam, frames, timer, stages_on=False):
    """One pass over a scene's frames with a fresh tracker and segmenter: per frame the CPU ms of
    ``observe``, of the step, of the whole-frame ``observe``, whether the window was used, and, with
    ``stages_on``, the windowed ``observe``'s stages (ms by label; the wrappers' own cost is in them,
    ~0.2 ms a frame: the totals that give the rates come from passes without them)."""
    from tracker.observe import observe
    from tracker.segment import Segmenter
    from tracker.track import FrameTracker, TrackerSettings

    # one core: a start search's fits one after the other too (InitSettings.threads)
    tr = FrameTracker(hand, TrackerSettings().replace(init=dict(threads=1)), synergies=bundle)
    seg, seg_whole = Segmenter(), Segmenter()
    out, stages, busy = [], [], []
    for depth, color in frames:
        busy.append(tr.sizing.calibrating() or tr.sizing.refining())
        window = tr.segment_window(cam)
        timer.active = stages_on
        t0 = time.process_time()
        ob = observe(depth, cam, tr.settings.observe, segmenter=seg, color=color, window=window)
        t1 = time.process_time()
        timer.active = False
        st = timer.take()
        st[REST] = (t1 - t0) - sum(st.values())
        stages.append({k: v * 1e3 for k, v in st.items()})
        tr.track(ob, cam, color=color)
        t2 = time.process_time()
        # the whole-frame segmenter on the same frame (not tracked: the loop above is the one measured)
        observe(depth, cam, tr.settings.observe, segmenter=seg_whole, color=color)
        t3 = time.process_time()
        out.append(((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3, ob.window is not None))
    skip = skip_frames(busy)
    return np.array(out, float)[skip:], stages[skip:]


def run_scene(scene, n, repeat, colour, stage_passes):
    """This process's tree on one scene: ``{"best", "mean", "stages", "labels"}`` (JSON-ready): the
    totals of ``repeat`` passes, the stages of ``stage_passes`` more (each frame's fastest of those)."""
    from handmodel import HandModel
    from synergy.bundle import load_bundle
    from tracker import TRACKING_HAND

    timer = StageTimer()
    labels = timer.install()
    # the realistic scenes on the tracker's hand (tracker.TRACKING_HAND), as the report renders and tracks them
    hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
    sensor, spec = SCENES[scene]
    cam, frames = frames_of(hand, sensor, spec, n, color=colour)
    passes = [track_pass(hand, bundle, cam, frames, timer) for _ in range(max(repeat, 1))]
    times = np.stack([p[0] for p in passes])
    timed = [track_pass(hand, bundle, cam, frames, timer, True) for _ in range(max(stage_passes, 1))]
    names = sorted({k for _, st in timed for s in st for k in s})
    # each frame's stages at its fastest timed pass (of the whole observe)
    fastest = np.stack([p[0] for p in timed])[:, :, 0].argmin(axis=0)
    stages = {k: [timed[p][1][f].get(k, 0.0) for f, p in enumerate(fastest)] for k in names}
    return {"best": times.min(axis=0).tolist(), "mean": times.mean(axis=0).tolist(), "stages": stages,
            "staged": [timed[p][0][f, 0] for f, p in enumerate(fastest)], "labels": sorted(set(labels)) + [REST]}


def child(src, scene, n, repeat, colour, stage_passes):
    """:func:`run_scene` in a fresh process on the tree at ``src`` (its ``src`` folder), this harness."""
    env = dict(os.environ, PYTHONPATH=str(src))
    p = subprocess.run([sys.executable, __file__, "--worker", str(scene), "--frames", str(n), "--repeat",
                        str(repeat), "--stage-passes", str(stage_passes)] + ([] if colour else ["--depth-only"]),
                       env=env, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"the bench on {src} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def fps_rows(tree, results):
    """The per-scene rows and the pooled row of one tree."""
    def row(label, best, mean):
        o, t, w, win = best.mean(axis=0)
        mo, mt = mean[:, 0].mean(), mean[:, 1].mean()
        print(f"{label:36s} {o:10.2f} {win:8.0%} {t:9.2f} {1e3 / (o + t):22.0f} {1e3 / (mo + mt):16.0f} {w:22.2f} "
              f"{1e3 / (w + t):15.0f} {1e3 / t:20.0f}")

    bests, means = [], []
    for (sensor, spec), r in zip(SCENES, results):
        best, mean = np.array(r["best"]), np.array(r["mean"])
        bests.append(best)
        means.append(mean)
        row(f"{tree[:10]:10s} {sensor:9s} {spec:15s}", best, mean)
    row(f"{tree[:10]:10s} all", np.concatenate(bests), np.concatenate(means))


def stage_table(trees):
    """Median (and mean) ms per stage of the windowed observe, every scene's frames pooled, per tree."""
    labels = []
    for _, results in trees:
        for r in results:
            labels += [k for k in r["labels"] if k not in labels]
    order = [lab for lab, _, _ in STAGES] + [REST]
    labels = sorted(set(labels), key=order.index)
    print(f"{'stage of the windowed observe (ms)':36s}" + "".join(f" {t[:10] + ' median':>17s} {'mean':>6s}"
                                                                  for t, _ in trees))
    totals = []
    for t, results in trees:
        totals.append(np.concatenate([np.asarray(r["staged"]) for r in results]))
    for lab in labels:
        cells = ""
        for _, results in trees:
            if not all(lab in r["labels"] for r in results):
                cells += f" {'-':>17s} {'-':>6s}"
                continue
            v = np.concatenate([np.asarray(r["stages"].get(lab, [0.0] * len(r["best"]))) for r in results])
            cells += f" {np.median(v):17.3f} {v.mean():6.3f}"
        print(f"{lab:36s}{cells}")
    print(f"{'observe, total (stages timed)':36s}" + "".join(f" {np.median(v):17.3f} {v.mean():6.3f}"
                                                             for v in totals))


#: the fields of an observation recorded by :func:`record_observations`
OBSERVATION_FIELDS = ("points", "normals", "mask", "depth", "density", "stride", "frame_depth", "silhouette", "window")


def _digest(value):
    """A SHA-1 of an array's type, shape and bytes; a number, a window or None as its repr."""
    import hashlib

    if value is None or isinstance(value, (float, int, tuple)):
        return repr(value)
    a = np.ascontiguousarray(value)
    return hashlib.sha1(repr((a.dtype.str, a.shape)).encode() + a.tobytes()).hexdigest()


def record_observations(n, windows=None):
    """``(digests, windows)`` of every observation of the scenes' first ``n`` frames, by ``"mode:scene"``:
    per frame the windowed observation's and the whole frame's fields (:data:`OBSERVATION_FIELDS`, each
    :func:`_digest`), and the windows used — the tracker's (this tree tracks the frames), or ``windows``'."""
    from handmodel import HandModel
    from synergy.bundle import load_bundle
    from tracker import TRACKING_HAND
    from tracker.observe import observe
    from tracker.segment import Segmenter
    from tracker.track import FrameTracker, TrackerSettings

    hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
    digests, used = {}, {}
    for mode in MODES:
        for scene, (sensor, spec) in enumerate(SCENES):
            key = f"{mode}:{scene}"
            cam, frames = frames_of(hand, sensor, spec, n, color=mode == "colour")
            tr = FrameTracker(hand, TrackerSettings().replace(init=dict(threads=1)), synergies=bundle)
            seg, seg_whole = Segmenter(), Segmenter()
            digests[key], used[key] = [], []
            for f, (depth, color) in enumerate(frames):
                if windows is None:
                    window = tr.segment_window(cam)
                else:
                    w = windows[key][f]
                    window = None if w is None else tuple(tuple(slice(*p) for p in part) for part in w)
                used[key].append(None if window is None else [[(s.start, s.stop) for s in part] for part in window])
                ob = observe(depth, cam, tr.settings.observe, segmenter=seg, color=color, window=window)
                if windows is None:
                    tr.track(ob, cam, color=color)
                whole = observe(depth, cam, tr.settings.observe, segmenter=seg_whole, color=color)
                digests[key].append([{k: _digest(getattr(o, k)) for k in OBSERVATION_FIELDS} for o in (ob, whole)])
    return digests, used


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3, help="passes per scene; each frame timed at the fastest")
    ap.add_argument("--depth-only", action="store_true", help="observe without the colour frames only")
    ap.add_argument("--colour-only", action="store_true", help="observe with the colour frames only")
    ap.add_argument("--stage-passes", type=int, default=2, help="further passes per scene timing the stages")
    ap.add_argument("--peer", type=Path, default=None, help="another checkout whose src is timed in the same run")
    ap.add_argument("--observations", type=Path, default=None,
                    help="record every observation's digests (and the windows) to this JSON file instead of timing")
    ap.add_argument("--windows", type=Path, default=None,
                    help="with --observations: observe in an earlier record's windows (no tracking)")
    ap.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.observations is not None:
        given = None if a.windows is None else json.loads(a.windows.read_text())["windows"]
        digests, used = record_observations(a.frames, given)
        a.observations.write_text(json.dumps({"observations": digests, "windows": used}))
        count = sum(len(f) * len(OBSERVATION_FIELDS) * 2 for f in digests.values())
        print(f"{count} arrays and values recorded to {a.observations}")
        return
    if a.worker is not None:
        print(json.dumps(run_scene(a.worker, a.frames, a.repeat, not a.depth_only, a.stage_passes)))
        return
    modes = [m for m in MODES if not (m == "colour" and a.depth_only) and not (m == "depth only" and a.colour_only)]
    trees = [("this tree", ROOT / "src")]
    if a.peer is not None:
        if not (a.peer / "src" / "tracker").is_dir():
            raise SystemExit(f"--peer {a.peer}: no src/tracker in it")
        trees.append(("peer", a.peer.resolve() / "src"))
    print(f"bench_segmented: {a.frames} frames a scene, {a.repeat} passes, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}" + (f"; peer: {a.peer}" if a.peer is not None else ""))
    for mode in modes:
        colour = mode == "colour"
        results = {t: [] for t, _ in trees}
        for scene in range(len(SCENES)):
            for t, src in trees:  # scene by scene in turn: both trees see the same load
                results[t].append(child(src, scene, a.frames, a.repeat, colour, a.stage_passes))
        print(f"\n{mode}:")
        print(f"{'tree       sensor    scene':36s} {'observe ms':>10s} {'windowed':>8s} {'track ms':>9s} "
              f"{'fps with segmentation':>22s} {'(mean of passes)':>16s} {'whole-frame observe ms':>22s} "
              f"{'fps whole-frame':>15s} {'fps tracking alone':>20s}")
        for t, _ in trees:
            fps_rows(t, results[t])
        stage_table([(t, results[t]) for t, _ in trees])
    print("(CPU ms per frame, one core, each frame at its fastest of the passes; windowed: share of frames "
          "segmented in the predicted hand's window; stages: median over the frames, every scene pooled)")


if __name__ == "__main__":
    main()
