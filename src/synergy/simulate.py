"""Mocap simulator: procedural hand motions (with task labels) → marker trajectories → C3D.

Motions are generated from a seed, so demos and tests get C3D files with ground truth without
third-party data. Every motion returns θ per frame (26 DoF, metres/radians) for the default hand.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from handmodel import HandModel
from handmodel.dofs import DOF_NAMES
from handmodel.fileio import atomic_write_text

from .c3d import TASK_EVENT
from .c3d_write import write_c3d
from .errors import SynergyError
from .markers import MarkerSet, load_markerset

MOTIONS = {
    "open_close": ("general", "all fingers close to a fist and open again, thumb following"),
    "abduction": ("general", "fingers spread apart and back together"),
    "thumb_opposition": ("general", "thumb tip travels to each fingertip in turn"),
    "power_grasp": ("grasp", "reach open, wrap all fingers around a cylinder, hold, release"),
    "precision_grasp": ("grasp", "thumb–index(–middle) pinch of a small object, others relaxed"),
}
#: Motions for calibration, not part of ``--motions all`` (they are not tasks a synergy should learn).
CALIBRATION_MOTIONS = {
    "rom": ("calibration", "range of motion: every joint sweeps its range at its own pace (flexion, spread, "
                           "thumb circles), so each joint moves independently of its neighbours"),
}
#: Motions of the weakly observed protocol (:func:`weak_protocol`), not part of ``--motions all``.
PLAYING_MOTIONS = {
    "fretting": ("playing", "fingers fret a guitar neck: MCP 40-70°, PIP 60-90° flexed, a new chord every "
                            "0.35-0.7 s (each finger presses or lifts, spreads across frets), thumb behind the neck"),
}


def _smooth(t):
    t = np.clip(t, 0, 1)
    return t * t * (3 - 2 * t)


def motion(name: str, *, duration_s: float = 4.0, rate: float = 100.0, seed: int = 0):
    """θ trajectory ``(F, 26)`` of a named procedural motion; returns ``(theta, task_label)``."""
    known = {**MOTIONS, **CALIBRATION_MOTIONS, **PLAYING_MOTIONS}
    if name not in known:
        raise SynergyError(name, f"unknown motion (known: {', '.join(known)})")
    rng = np.random.default_rng(seed)
    F = max(int(round(duration_s * rate)), 2)
    t = np.arange(F) / rate
    u = t / duration_s
    names = DOF_NAMES
    th = np.zeros((F, len(names)))
    col = {n: i for i, n in enumerate(names)}
    fingers = ("index", "middle", "ring", "pinky")
    amp = rng.uniform(0.8, 1.1)
    cycles = int(rng.integers(1, 3))
    if name == "open_close":
        for k, f in enumerate(fingers):
            lag = 0.03 * k * rng.uniform(0.5, 1.5)
            c = 0.5 - 0.5 * np.cos(2 * np.pi * cycles * (u - lag))
            th[:, col[f"{f}1_flex"]] = -1.2 * amp * c
            th[:, col[f"{f}2_flex"]] = -1.5 * amp * c
            th[:, col[f"{f}3_flex"]] = -0.9 * amp * c
            th[:, col[f"{f}1_abd"]] = (0.12 - 0.08 * k) * (1 - c)
        c = 0.5 - 0.5 * np.cos(2 * np.pi * cycles * u)
        th[:, col["thumb1_flex"]] = -0.7 * c
        th[:, col["thumb2_flex"]] = -0.5 * c
        th[:, col["thumb3_flex"]] = -0.7 * c
    elif name == "abduction":
        s = np.sin(2 * np.pi * cycles * u)
        for k, f in enumerate(fingers):
            th[:, col[f"{f}1_abd"]] = amp * (0.25 - 0.17 * k) * s
            th[:, col[f"{f}1_flex"]] = -0.15 + 0.05 * rng.normal()
        th[:, col["thumb1_abd"]] = -0.35 * amp * s
    elif name == "thumb_opposition":
        seg = np.minimum((u * 4).astype(int), 3)
        w = np.sin(np.pi * ((u * 4) % 1.0)) ** 2
        for k, f in enumerate(fingers):
            on = (seg == k) * w
            th[:, col[f"{f}1_flex"]] = -0.5 * on - 0.1
            th[:, col[f"{f}2_flex"]] = -0.7 * on - 0.1
            th[:, col[f"{f}3_flex"]] = -0.4 * on
        reach = np.array([0.0, 0.25, 0.5, 0.7])[seg]
        th[:, col["thumb1_abd"]] = (0.2 + 0.2 * reach) * w
        th[:, col["thumb1_flex"]] = -(0.8 + 0.35 * reach) * w
        th[:, col["thumb2_flex"]] = -0.4 * w
        th[:, col["thumb3_flex"]] = -(0.5 - 0.3 * reach) * w
    elif name == "power_grasp":
        close = _smooth((u - 0.15) / 0.25) * (1 - _smooth((u - 0.75) / 0.2))
        r = rng.uniform(0.85, 1.15)  # object size
        for k, f in enumerate(fingers):
            th[:, col[f"{f}1_flex"]] = -(0.9 + 0.1 * k) * r * close
            th[:, col[f"{f}2_flex"]] = -1.3 * r * close
            th[:, col[f"{f}3_flex"]] = -0.8 * r * close
            th[:, col[f"{f}1_abd"]] = (0.1 - 0.07 * k) * (1 - close)
        th[:, col["thumb1_abd"]] = 0.25 * close
        th[:, col["thumb1_flex"]] = -0.9 * close
        th[:, col["thumb2_flex"]] = -0.4 * close
        th[:, col["thumb3_flex"]] = -0.5 * close
    elif name == "precision_grasp":
        close = _smooth((u - 0.2) / 0.25) * (1 - _smooth((u - 0.7) / 0.2))
        tri = rng.random() < 0.5
        for k, f in enumerate(fingers):
            active = k == 0 or (tri and k == 1)
            g = 1.0 if active else 0.45
            th[:, col[f"{f}1_flex"]] = -0.75 * g * close - 0.1
            th[:, col[f"{f}2_flex"]] = -(0.6 if active else 0.9) * close - 0.1
            th[:, col[f"{f}3_flex"]] = -(0.25 if active else 0.6) * close
        th[:, col["thumb1_abd"]] = 0.3 * close
        th[:, col["thumb1_flex"]] = -0.95 * close
        th[:, col["thumb2_flex"]] = -0.2 * close
        th[:, col["thumb3_flex"]] = -0.3 * close
    elif name == "rom":
        # incommensurate frequencies: over a few seconds every pair of joints meets in many combinations
        freq = rng.uniform(0.35, 1.1, 20) * (4.0 / duration_s) ** 0.5
        phase = rng.random(20)
        wave = 0.5 - 0.5 * np.cos(2 * np.pi * (freq * t[:, None] + phase))  # 0..1
        for k, f in enumerate(("thumb",) + fingers):
            a, f1, f2, f3 = (col[f"{f}1_abd"], col[f"{f}1_flex"], col[f"{f}2_flex"], col[f"{f}3_flex"])
            if f == "thumb":
                th[:, a] = -0.5 + 1.0 * wave[:, 0]
                th[:, f1] = -0.9 * wave[:, 1] + 0.2
                th[:, f2] = -0.8 * wave[:, 2] + 0.1
                th[:, f3] = -1.0 * wave[:, 3] + 0.2
            else:
                j = 4 * k
                th[:, a] = (0.3 - 0.15 * (k - 1)) * (2 * wave[:, j] - 1) * (1 - 0.6 * wave[:, j + 1])
                th[:, f1] = -1.3 * wave[:, j + 1] + 0.2
                th[:, f2] = -1.5 * wave[:, j + 2] + 0.05
                th[:, f3] = -0.9 * wave[:, j + 3] + 0.05
    elif name == "fretting":
        th[:] = _fretting(t, rng, col, fingers, rate)
    # natural variability and a moving, turning hand in the lab (metres)
    th[:, 6:] += rng.normal(0, 0.02, (1, 20)) + 0.01 * np.sin(2 * np.pi * (u[:, None] * rng.uniform(0.5, 2, 20) + rng.random(20)))
    th[:, 0:3] = [0.3, 0.2, 1.0] + 0.05 * np.sin(2 * np.pi * (u[:, None] * [0.5, 0.7, 0.3] + rng.random(3)))
    th[:, 3:6] = rng.uniform(-0.5, 0.5, 3) + 0.3 * np.sin(2 * np.pi * (u[:, None] * [0.4, 0.3, 0.5] + rng.random(3)))
    return th, known[name][0]


def _fretting(t, rng, col, fingers, rate):
    """θ of :data:`PLAYING_MOTIONS` ``fretting``: piecewise-constant chords, blended over ~0.1 s."""
    th = np.zeros((len(t), len(col)))
    ends = np.cumsum(rng.uniform(0.35, 0.7, int(t[-1] / 0.35) + 2))
    chord = np.searchsorted(ends, t)
    n = chord.max() + 1
    for k, f in enumerate(fingers):
        press = rng.random(n) < 0.6
        th[:, col[f"{f}1_flex"]] = np.where(press, -rng.uniform(0.85, 1.2, n), -rng.uniform(0.7, 0.9, n))[chord]
        th[:, col[f"{f}2_flex"]] = np.where(press, -rng.uniform(1.25, 1.55, n), -rng.uniform(1.05, 1.25, n))[chord]
        th[:, col[f"{f}3_flex"]] = np.where(press, -rng.uniform(0.1, 0.6, n), -rng.uniform(0.3, 0.7, n))[chord]
        th[:, col[f"{f}1_abd"]] = (rng.uniform(-0.15, 0.15, n) + 0.1 - 0.07 * k)[chord]
    th[:, col["thumb1_abd"]] = 0.3
    th[:, col["thumb1_flex"]] = -0.5 + 0.1 * np.sin(2 * np.pi * 0.3 * t)
    th[:, col["thumb2_flex"]] = -0.3
    th[:, col["thumb3_flex"]] = -0.2
    half = max(int(0.05 * rate), 1)
    win = np.hanning(2 * half + 3)[1:-1]
    win /= win.sum()
    pad = np.pad(th, ((half, half), (0, 0)), mode="edge")
    return np.stack([np.convolve(pad[:, j], win, mode="valid") for j in range(th.shape[1])], axis=1)


@dataclass
class SimulatedTrial:
    """Marker trajectories with ground truth; has the fields of :class:`synergy.c3d.MarkerData` that
    the IK needs (``labels``, ``points`` in metres with NaN gaps, ``rate``, ``first_frame``).
    ``bone_scales`` and ``marker_shift`` are the subject's truth (node → factor on top of ``scale``;
    label → metres in the node frame, added to the marker's nominal place)."""

    labels: list
    points: np.ndarray
    rate: float
    theta: np.ndarray
    task: str
    motion: str
    scale: float = 1.0
    hand: str = "left"
    first_frame: int = 1
    path: str = ""
    residuals: np.ndarray = field(default=None)
    bone_scales: dict = field(default_factory=dict)
    marker_shift: dict = field(default_factory=dict)


def random_subject(markerset, *, bone_range=0.2, marker_shift_mm=5.0, seed=0):
    """A subject unlike the model: every bone (including the metacarpals, i.e. the finger bases'
    distance from the wrist) × a factor uniform in ``1 ± bone_range``, every marker moved from its
    nominal place by up to ``marker_shift_mm`` along each axis of its node frame.
    Returns ``(bone_scales, marker_shift)`` for :func:`simulate_markers`.

    >>> b, m = random_subject("hand16", seed=1)
    >>> len(b), len(m), max(abs(v - 1) for v in b.values()) <= 0.2
    (20, 16, True)
    """

    ms = markerset if isinstance(markerset, MarkerSet) else load_markerset(markerset)
    hm = HandModel.load()
    rng = np.random.default_rng(seed)
    bones = {hm.node_names[k]: float(1 + rng.uniform(-bone_range, bone_range)) for k in range(1, hm.n_nodes)}
    shift = {m.label: rng.uniform(-marker_shift_mm, marker_shift_mm, 3) / 1000.0 for m in ms.markers}
    return bones, shift



def subject_protocol(markerset, seed, *, noise_mm=0.5, bone_range=0.2, marker_shift_mm=5.0):
    """The calibration protocol of our tests and ``benchmarks/bench_calibrate.py``: a subject unlike
    the model (:func:`random_subject`: every bone ``1 ± bone_range``, every marker up to
    ``marker_shift_mm`` per axis off its place), ``noise_mm`` marker noise, and three trials of it —
    a 5 s range of motion, a static flat hand (50 frames) and a 3 s power grasp to convert.

    Returns ``(rom, static, trial, theta, bones, shift)``: the three marker trials, the grasp's true
    θ, and the subject (bone factors, marker shifts)."""
    bones, shift = random_subject(markerset, bone_range=bone_range, marker_shift_mm=marker_shift_mm, seed=seed)
    kw = {"noise_mm": noise_mm, "bone_scales": bones, "marker_shift": shift}
    th_rom, _ = motion("rom", duration_s=5.0, seed=seed)
    rom = simulate_markers(th_rom, markerset, seed=seed + 1, **kw)
    th_st = np.zeros((50, th_rom.shape[1]))
    th_st[:, :6] = th_rom[0, :6]
    static = simulate_markers(th_st, markerset, seed=seed + 2, **kw)
    th, _ = motion("power_grasp", duration_s=3.0, seed=seed + 3)
    trial = simulate_markers(th, markerset, seed=seed + 4, **kw)
    return rom, static, trial, th, bones, shift

#: The weakly observed protocol's proximal-phalanx markers and where they truly sit along the bone
#: (~10 mm past the knuckle) while the marker set says 0.5.
WEAK_PROXIMAL = {"IPP": 0.2, "MPP": 0.2, "RPP": 0.2, "PPP": 0.2}


def moved_markers(markerset, along):
    """``markerset`` with each segment marker in ``along`` (label → fraction of its bone) moved there."""
    ms = markerset if isinstance(markerset, MarkerSet) else load_markerset(markerset)
    out = tuple(replace(m, landmark={**m.landmark, "along": along[m.label]}) if m.label in along else m
                for m in ms.markers)
    return replace(ms, markers=out, name=f"{ms.name} (moved)")


def weak_protocol(seed, motion_name="fretting", *, markerset="hand19", noise_mm=0.5, duration_s=4.0,
                  bone_range=0.2, marker_shift_mm=2.0, along=None):
    """The weakly observed protocol of issue 40: 19 skin markers (``hand19``: 4 on the wrist and back
    of the hand, 3 per digit) whose proximal-phalanx markers truly sit at ``along`` (default
    :data:`WEAK_PROXIMAL`, 0.2 of the bone) while the set says 0.5, a subject unlike the model
    (:func:`random_subject`), ``noise_mm`` noise, no static trial: one ``motion_name`` trial
    (``fretting`` or ``power_grasp``). Returns ``(trial, theta)``; convert with the set as written.

    >>> tr, th = weak_protocol(0, duration_s=0.5)
    >>> tr.points.shape, th.shape
    ((50, 19, 3), (50, 26))
    """
    truth = moved_markers(markerset, WEAK_PROXIMAL if along is None else along)
    bones, shift = random_subject(truth, bone_range=bone_range, marker_shift_mm=marker_shift_mm, seed=seed)
    th, task = motion(motion_name, duration_s=duration_s, seed=seed + 11)
    tr = simulate_markers(th, truth, noise_mm=noise_mm, seed=seed + 12, bone_scales=bones, marker_shift=shift,
                          motion_name=motion_name, task=task)
    return tr, th


def simulate_markers(theta, markerset, *, hand="left", scale=1.0, noise_mm=0.0, gap_fraction=0.0, rate=100.0,
                     seed=0, motion_name="", task="", bone_scales=None, marker_shift=None):
    """Markers of ``markerset`` on the (scaled) default hand following ``theta``; noise and gaps.

    ``bone_scales`` (node → factor on top of ``scale``) and ``marker_shift`` (label → metres in the
    node frame, labels as in the marker set before ``{side}`` is filled) make a subject whose hand
    and marker placement differ from the model (see :func:`random_subject`); segment landmarks
    follow the subject's bones. Gaps are contiguous runs (occlusions) totalling ``gap_fraction`` of
    each marker's samples.
    """

    ms = markerset if isinstance(markerset, MarkerSet) else load_markerset(markerset)
    raw_labels = [m.label for m in ms.markers]
    ms = ms.for_hand(hand)
    right = hand == "right"
    hm = HandModel.load(right=right).scaled(scale, bone_scales or {})
    nodes, local = ms.attachments(hm, right, scale=scale)
    if marker_shift:
        local = local.copy()
        for i, lab in enumerate(raw_labels):
            if lab in marker_shift:
                d = np.asarray(marker_shift[lab], float).copy()
                if right:
                    d[0] = -d[0]
                local[i] += d
    pts = hm.points(theta, nodes, local)
    rng = np.random.default_rng(seed)
    if noise_mm:
        pts = pts + rng.normal(0, noise_mm / 1000.0, pts.shape)
    F, P = pts.shape[:2]
    if gap_fraction > 0:
        for p in range(P):
            todo = int(round(gap_fraction * F))
            while todo > 0:
                ln = int(min(todo, rng.integers(3, max(4, F // 20))))
                s = int(rng.integers(0, max(F - ln, 1)))
                pts[s:s + ln, p] = np.nan
                todo = int(round(gap_fraction * F)) - int(np.isnan(pts[:, p, 0]).sum())
    res = np.where(np.isnan(pts[..., 0]), -1.0, 0.0)
    return SimulatedTrial(labels=[m.label for m in ms.markers], points=pts, rate=rate, theta=np.asarray(theta),
                          task=task, motion=motion_name, scale=scale, hand=hand, residuals=res,
                          bone_scales=dict(bone_scales or {}), marker_shift=dict(marker_shift or {}))


def write_trials(out, names, *, trials=2, markers="hand16", hand="left", duration=4.0, rate=100.0, noise_mm=0.3,
                 gaps=0.02, scale=1.0, bone_scales=None, marker_shift=None, units="mm", prefix="Sim", seed=0,
                 on_trial=None) -> list[tuple]:
    """Simulate ``trials`` trials of each motion in ``names`` into the folder ``out``: one C3D per trial
    (with a ``task:`` event), its ground-truth angles in ``truth/<trial>.csv`` and the task map
    ``tasks.yaml``. Existing trial files are never overwritten. ``on_trial()`` is called after each
    trial. Returns one row per trial: file name, motion, task, frames, gap %."""
    out = Path(out)
    known = {**MOTIONS, **CALIBRATION_MOTIONS, **PLAYING_MOTIONS}
    rows, task_rules = [], []
    for n in names:
        for k in range(trials):
            s = seed * 1000 + list(known).index(n) * 100 + k
            th, task = motion(n, duration_s=duration, rate=rate, seed=s)
            tr = simulate_markers(th, markers, hand=hand, scale=scale, noise_mm=noise_mm, gap_fraction=gaps,
                                  rate=rate, seed=s + 7, motion_name=n, task=task, bone_scales=bone_scales,
                                  marker_shift=marker_shift)
            stem = f"{n}_{k + 1:02d}"
            path = out / f"{stem}.c3d"
            if path.exists():
                raise SynergyError(path, "exists and is never overwritten (choose another -o)")
            write_c3d(path, tr.points, tr.labels, rate, units=units, prefix=prefix,
                      events=[(f"{TASK_EVENT}{task}", 0.0, "General")])
            truth = pd.DataFrame(th, columns=list(DOF_NAMES))
            truth.insert(0, "time_s", np.arange(len(th)) / rate)
            atomic_write_text(out / "truth" / f"{stem}.csv",
                              f"# motion: {n}\n# task: {task}\n# scale: {scale}\n# hand: {hand}\n"
                              + truth.to_csv(index=False, float_format="%.9g"), overwrite=False)
            rows.append((path.name, n, task, len(th), f"{100 * np.isnan(tr.points[..., 0]).mean():.1f}"))
            task_rules.append({"glob": f"{stem}.c3d", "task": task})
            if on_trial is not None:
                on_trial()
    atomic_write_text(out / "tasks.yaml", yaml.safe_dump({"rules": task_rules}, sort_keys=False), overwrite=True)
    return rows
