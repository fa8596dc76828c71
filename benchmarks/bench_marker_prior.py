"""The marker IK's posture prior (issue 40), prior off / auto / on side by side (angles RMS of the 20
posture DoF against the simulated truth, degrees; joints on a limit the truth never comes within 2° of).

Protocols (all with 0.5 mm noise, a subject unlike the model):
- ``weak``: :func:`synergy.simulate.weak_protocol` — hand19 with the proximal-phalanx markers at 0.2 of
  the bone while the set says 0.5, no static trial, a 4 s fretting or power-grasp trial calibrated on
  itself (automatic calibration, as ``synergy angles`` does: with the trial's neutral frames, if any),
  markers low-passed at 6 Hz: the default (``prior='auto'``: neutral frames, else the prior in the
  calibration; the prior in the IK where a joint is weakly observed), ``prior=None`` and
  ``prior='fingerfist'``; "before" is the calibration without neutral frames and no posture prior
  (the code before issue 40); and the same trial converted with the oracle calibration (the
  subject's true bones and marker places) to tell calibration error from IK ambiguity, and once more
  with the markers on each chain's last bone at their nominal places (the subject's ±2 mm off them
  unknown), and once with only their places along the arc about their joint nominal (the rest of their
  place true): what a calibration without a known posture cannot know of the last joints' zeros. The
  default's RMS is also split into its parts (thumb flexions, MCP, PIP, DIP, abductions), and each
  joint's trial-mean error is set against the SD of its zero that the calibration reports.
- ``subjects``: :func:`synergy.simulate.subject_protocol` (benchmarks/bench_calibrate.py's protocol:
  ROM + static to calibrate, power grasp to convert, 6 Hz).
- ``overfit``: the held-out rule of the automatic calibration (:func:`synergy.subject.overfits`)
  against the rule before it (any held-out residual over 1.25× the training one was overfit, however
  far below the scale-only hand's), each trial converted as ``synergy angles`` does (default prior):
  short weakly observed trials (``--overfit-durations``, ``--weak-seeds``, ``--motions``) and the
  subjects' power grasps calibrated on themselves (``--seeds``), markers low-passed at 6 Hz and raw.
  Per trial: the held-out check (median marker residual: fitted frames, held-out frames, scale-only
  hand on them), which hand each rule converts with and its angles RMS and table residual.

Run: .venv/bin/python benchmarks/bench_marker_prior.py [--protocols weak subjects overfit] [--seeds 0-15]
     (≈ 10 s CPU per weak trial, ≈ 4 s per subject and prior setting, one core)
"""
from __future__ import annotations

import argparse
import os
from contextlib import contextmanager

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from synergy.angles import AUTO_GAIN, markers_to_angles
from synergy.calibrate import Calibration, calibrate
from synergy.markers import load_markerset
from synergy.subject import last_bone_markers
from synergy.simulate import WEAK_PROXIMAL, moved_markers, subject_protocol, weak_protocol

SMOOTH_HZ = 6.0
FINGERS = ("index", "middle", "ring", "pinky")
PRIORS = (("off", None), ("auto", "auto"), ("on", "fingerfist"))


def arc_directions(hand, node, local):
    """Orthonormal rows: where a marker at ``local`` (``node``'s frame) moves when ``node``'s own joint turns."""
    ax = hand.dof_axes[[d for d in hand.dof_idx[hand.dof_ptr[node]:hand.dof_ptr[node + 1]] if hand.dof_types[d] == 0]]
    t = np.cross(ax, local).reshape(-1, 3)
    t = t[np.linalg.norm(t, axis=1) > 1e-9]
    return np.linalg.svd(t, full_matrices=False)[2][:len(t)] if len(t) else np.zeros((0, 3))


GROUPS = {"thumb": ("thumb1_flex", "thumb2_flex", "thumb3_flex"), "MCP": tuple(f"{f}1_flex" for f in FINGERS),
          "PIP": tuple(f"{f}2_flex" for f in FINGERS), "DIP": tuple(f"{f}3_flex" for f in FINGERS),
          "abd": ("thumb1_abd",) + tuple(f"{f}1_abd" for f in FINGERS)}


def shares(df, theta):
    """Where the angles RMS of :func:`rms_deg` comes from: each group's part (degrees; the parts' squares
    sum to the RMS's square)."""
    names = HandModel.load().dof_names
    err = df[names].to_numpy() - theta
    ok = np.isfinite(err).all(1)
    return {g: float(np.degrees(np.sqrt(np.mean(np.sum(err[ok][:, [names.index(n) for n in ix]] ** 2, 1)) / 20)))
            for g, ix in GROUPS.items()}


def zero_z(df, theta):
    """Each posture joint's trial-mean error over the SD of its zero that the calibration reported
    (``diagnostics.calibration_zero_sd_deg``; empty when the calibration fitted no subject)."""
    names = HandModel.load().dof_names
    zero = df.attrs["diagnostics"].get("calibration_zero_sd_deg") or {}
    bias = np.degrees(np.nanmean(df[names].to_numpy() - theta, axis=0))
    return np.array([bias[names.index(k)] / v for k, v in zero.items() if v])


def rms_deg(df, theta):
    est = df[HandModel.load().dof_names].to_numpy()
    ok = np.isfinite(est).all(1)
    return float(np.degrees(np.sqrt(np.mean((est[ok, 6:] - theta[ok, 6:]) ** 2))))


def false_limits(df, theta, hand):
    lim = anatomical_limits(hand)
    out = []
    for dof, share in df.attrs["diagnostics"]["limit_share"].items():
        j = hand.dof_names.index(dof)
        if share > 0.05 and np.abs(theta[:, j, None] - lim[j][None, :]).min() >= np.radians(2):
            out.append(dof)
    return out


def oracle(ms, hand, trial, nominal=False):
    """The subject's true calibration; ``nominal``: with the markers on each chain's last bone at their
    nominal places (what a calibration without a known posture can know of those joints' zeros);
    ``nominal='arc'``: those markers off their nominal places as the subject's are except along the arc
    about their joint (the one direction no marker motion shows: that joint's zero)."""
    truth = moved_markers(ms, WEAK_PROXIMAL)
    _, local = truth.attachments(hand.scaled(1.0, trial.bone_scales))
    nodes = truth.attachments(hand)[0]
    kept = last_bone_markers(hand.parents, nodes) if nominal else np.zeros(len(local), bool)
    offsets = {}
    for i, m in enumerate(truth.markers):
        shift = np.asarray(trial.marker_shift[m.label], float)
        if kept[i]:
            if nominal == "arc":
                Q = arc_directions(hand, int(nodes[i]), local[i])
                shift = shift - Q.T @ (Q @ shift)
            else:
                shift = 0.0 * shift
        offsets[m.label] = local[i] + shift
    return Calibration(scale=1.0, bone_scales=dict(trial.bone_scales), offsets=offsets, method="oracle",
                       hand="left", markerset=ms.name, median_residual_mm=0.5)


def rule_before(held_mm, train_mm, scale_only_mm):
    """The overfit rule before issue 40's change (for the side-by-side only): a held-out residual over
    1.25× the training one (+0.02 mm) was overfit whatever the scale-only hand's."""
    return bool(held_mm > 1.25 * train_mm + 0.02 or held_mm > scale_only_mm + 0.3)


@contextmanager
def overfit_rule(rule):
    """Run the calibration with ``rule`` in place of :func:`synergy.subject.overfits` (None: as is)."""
    import synergy.subject as subject

    kept = subject.overfits
    subject.overfits = rule or kept
    try:
        yield
    finally:
        subject.overfits = kept


def overfit_row(tag, trial, theta, ms, smooth_hz):
    """One trial converted automatically under the rule before and the rule now."""
    out = []
    for rule in (rule_before, None):
        with overfit_rule(rule):
            df = markers_to_angles(trial, ms, smooth_hz=smooth_hz, check_hand=None)
        cal = df.attrs["calibration"]
        used = ("scale" if "not used" in cal["method"] or not cal["bone_scales"] else
                "cal+N" if "neutral frames" in cal.get("static_source", "") else "cal")
        out.append((used, rms_deg(df, theta), float(np.nanmedian(df["residual_mm"])), cal["held_out"]))
    h = out[1][3]
    held = " ".join(f"{h.get(k, float('nan')):5.2f}" for k in ("train_residual_mm", "residual_mm",
                                                                 "scale_only_residual_mm"))
    mark = "  *" if out[0][:2] != out[1][:2] else ""
    print(f"{tag:34} {held} | " + " | ".join(f"{u:5} {e:6.2f}° {r:5.2f} mm" for u, e, r, _ in out) + mark, flush=True)
    return out


def seeds_arg(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--protocols", nargs="+", default=["weak", "subjects"])
    ap.add_argument("--seeds", type=seeds_arg, default=list(range(16)))
    ap.add_argument("--weak-seeds", type=seeds_arg, default=list(range(4)))
    ap.add_argument("--motions", nargs="+", default=["fretting", "power_grasp"])
    ap.add_argument("--overfit-durations", nargs="+", type=float, default=[0.5, 1.0, 2.0])
    args = ap.parse_args()
    hand = HandModel.load()
    kw = {"smooth_hz": SMOOTH_HZ, "check_hand": None}
    cols = " ".join(f"{n:>6}" for n, _ in PRIORS)
    if "weak" in args.protocols:
        ms = load_markerset("hand19")
        print("weak protocol (hand19, proximal markers at 0.2, no static): angles RMS (°) before | default "
              "(auto) | prior none | prior fingerfist | oracle calibration: none, fingerfist, none with the "
              "last-bone markers at their nominal places, none with only their places along the arc nominal | "
              "neutral frames, auto's IK prior | false limits (before/default/none/fingerfist) | the default's "
              "RMS in parts (degrees, squares sum to its square)")
        zs = []
        for motion in args.motions:
            for seed in args.weak_seeds:
                tr, th = weak_protocol(seed, motion)
                old = calibrate(tr, ms, hand, require_gain=AUTO_GAIN)
                runs = [markers_to_angles(tr, ms, calibration=old, prior=None, **kw)]
                runs += [markers_to_angles(tr, ms, prior=pr, **kw) for pr in ("auto", None, "fingerfist")]
                orc = oracle(ms, hand, tr)
                orc_got = [rms_deg(markers_to_angles(tr, ms, calibration=orc, prior=pr, **kw), th)
                           for pr in (None, "fingerfist")]
                for nominal in (True, "arc"):
                    orc_got.append(rms_deg(markers_to_angles(tr, ms, calibration=oracle(ms, hand, tr, nominal=nominal),
                                                             prior=None, **kw), th))
                src = runs[1].attrs["calibration"].get("static_source", "")
                neutral = src.split(" ")[0] if src else "0"
                chose = (runs[1].attrs["posture_prior"] or {}).get("name") or "none"
                lims = "/".join(",".join(false_limits(df, th, hand)) or "-" for df in runs)
                print(f"{motion:12} {seed:3d} " + " | ".join(f"{rms_deg(df, th):6.2f}" for df in runs) + " | "
                      + " ".join(f"{x:6.2f}" for x in orc_got) + f" | {neutral} {chose} | {lims} | default's parts: "
                      + " ".join(f"{g} {x:.2f}" for g, x in shares(runs[1], th).items()), flush=True)
                z = zero_z(runs[1], th)
                if len(z):
                    zs.append(z)
                    print(f"{'':16} default's calibration: |trial-mean error| / SD of the zero: RMS "
                          f"{np.sqrt(np.mean(z ** 2)):.2f}, max {np.abs(z).max():.2f}", flush=True)
        if zs:
            z = np.concatenate(zs)
            print(f"# zeros' SD against the errors, {len(z)} joint-trials: RMS {np.sqrt(np.mean(z ** 2)):.2f}, "
                  f"within 1 SD {100 * np.mean(np.abs(z) < 1):.0f} %, within 2 SD {100 * np.mean(np.abs(z) < 2):.0f} %",
                  flush=True)
    if "subjects" in args.protocols:
        for markers in ("hand16", "hand19"):
            ms = load_markerset(markers)
            rows = []
            print(f"{markers} subjects (ROM + static, power grasp): angles RMS (°) prior {cols} | auto chose")
            for seed in args.seeds:
                rom, static, trial, th, _, _ = subject_protocol(markers, seed, noise_mm=0.5)
                cal = calibrate(rom, ms, hand, static=static)
                got, chose = [], ""
                for name, pr in PRIORS:
                    df = markers_to_angles(trial, ms, calibration=cal, prior=pr, **kw)
                    got.append(rms_deg(df, th))
                    if name == "auto":
                        chose = (df.attrs["posture_prior"] or {}).get("name") or "none"
                rows.append(got)
                print(f"{markers:7} {seed:3d} " + " ".join(f"{x:6.2f}" for x in got) + f" | {chose}", flush=True)
            a = np.array(rows)
            print(f"# {markers}: max " + " ".join(f"{x:6.2f}" for x in a.max(0)) + ", seeds over 2°: "
                  + " ".join(str(int((a[:, k] > 2.0).sum())) for k in range(a.shape[1])), flush=True)


    if "overfit" in args.protocols:
        print("overfit rule, automatic calibration: held-out check (median marker residual, mm: fitted frames, "
              "held-out frames, scale-only hand on them) | before: hand, angles RMS, table residual | now: "
              "the same (* where they differ; cal+N: with the trial's neutral frames)")
        rows = []
        for motion in args.motions:
            for dur in args.overfit_durations:
                for seed in args.weak_seeds:
                    tr, th = weak_protocol(seed, motion, duration_s=dur)
                    for hz in (SMOOTH_HZ, None):
                        rows.append(overfit_row(f"weak {motion} {dur:g} s {seed} {hz or 'raw'}", tr, th,
                                                load_markerset("hand19"), hz))
        for markers in ("hand16", "hand19"):
            for seed in args.seeds:
                _, _, trial, th, _, _ = subject_protocol(markers, seed, noise_mm=0.5)
                for hz in (SMOOTH_HZ, None):
                    rows.append(overfit_row(f"{markers} grasp {seed} {hz or 'raw'}", trial, th,
                                            load_markerset(markers), hz))
        changed = [(b[1], n[1]) for b, n in rows if b[:2] != n[:2]]
        if changed:
            a = np.array(changed)
            print(f"# {len(changed)} of {len(rows)} trials converted differently: angles RMS before "
                  f"{a[:, 0].mean():.2f}° mean ({a[:, 0].max():.2f} worst), now {a[:, 1].mean():.2f}° "
                  f"({a[:, 1].max():.2f}); better on {int((a[:, 1] < a[:, 0]).sum())}", flush=True)
        else:
            print(f"# {len(rows)} trials, every one converted as before", flush=True)


if __name__ == "__main__":
    main()
