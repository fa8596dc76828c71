"""Subject calibration from skin markers (issue 13's floor: joint angles ≤ 2° RMS after calibration):
a sweep over simulated subjects, calibrated vs hand scale only vs the oracle (the true bones and true
marker places handed to the same IK), so calibration error and IK ambiguity can be told apart.

Protocol as tests/synergy/test_calibrate.py ``subject_trials``: every bone ±20 %, markers ±5 mm per
axis, 0.5 mm noise; a 5 s range of motion + a static flat hand to calibrate, a 3 s power grasp to
convert (markers low-passed at 6 Hz). Per seed: angles RMS (fingers' 20 DoF, degrees) for the three
hands, the calibration's held-out residual, the worst joint (calibrated) and the joints on a limit in
more than 5 % of frames that the truth never comes within 2° of.

Run: .venv/bin/python benchmarks/bench_calibrate.py [--sets hand16 hand19] [--seeds 0-15]
     [--dip-prior-sd 10] [--accel-sd 3000] [--calib-smooth-hz 6]   (≈ 3 s CPU per subject, one core)
The methods before issue 13's second session (raw markers to calibrate, frames solved on their own):
     --calib-smooth-hz 0 --accel-sd 0
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from synergy.angles import (
    ACCEL_SD_DEG_S2,
    IP_COUPLING_SD_DEG,
    LIMIT_SHARE_WARN,
    markers_to_angles,
)
from synergy.calibrate import Calibration, calibrate, scale_only
from synergy.markers import load_markerset
from synergy.simulate import subject_protocol

NOISE_MM = 0.5
SMOOTH_HZ = 6.0


def subject_trials(markers, seed):
    """The test suite's protocol (:func:`synergy.simulate.subject_protocol`): ROM, static flat hand, power grasp."""
    return subject_protocol(markers, seed, noise_mm=NOISE_MM)


def oracle(ms, hand, bones, shift):
    """The subject's true hand and marker places as a calibration (what a perfect calibration gives)."""
    true = hand.scaled(1.0, bones)
    _, local = ms.attachments(true)
    offsets = {m.label: local[i] + np.asarray(shift[m.label]) for i, m in enumerate(ms.markers)}
    return Calibration(scale=1.0, bone_scales=dict(bones), offsets=offsets, method="oracle", hand="left",
                       markerset=ms.name, median_residual_mm=NOISE_MM)


def errors(df, theta, names):
    est = df[names].to_numpy()
    ok = np.isfinite(est).all(1)
    per = np.degrees(np.sqrt(np.mean((est[ok, 6:] - theta[ok, 6:]) ** 2, axis=0)))
    return float(np.degrees(np.sqrt(np.mean((est[ok, 6:] - theta[ok, 6:]) ** 2)))), per


def false_limits(df, theta, hand):
    """Joints on a limit in > 5 % of frames whose true trajectory never comes within 2° of that limit."""
    lim = anatomical_limits(hand)
    out = []
    for dof, share in df.attrs["diagnostics"]["limit_share"].items():
        j = hand.dof_names.index(dof)
        reaches = (np.abs(theta[:, j] - lim[j, 0]) < np.radians(2)).any() or (
            np.abs(theta[:, j] - lim[j, 1]) < np.radians(2)).any()
        if share > LIMIT_SHARE_WARN and not reaches:
            out.append(f"{dof} {100 * share:.0f}%")
    return out


def seeds_arg(text):
    out = []
    for part in text.split(","):
        a, _, b = part.partition("-")
        out += list(range(int(a), int(b or a) + 1))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", nargs="+", default=["hand16", "hand19"])
    ap.add_argument("--seeds", type=seeds_arg, default=list(range(16)), help="e.g. 0-15 or 1,4,7")
    ap.add_argument("--dip-prior-sd", type=float, default=IP_COUPLING_SD_DEG)
    ap.add_argument("--accel-sd", type=float, default=ACCEL_SD_DEG_S2,
                    help="SD (deg/s²) of the IK's acceleration prior (0: frames solved on their own)")
    ap.add_argument("--no-scale-only", action="store_true", help="skip the scale-only conversion (faster)")
    ap.add_argument("--no-oracle", action="store_true", help="skip the oracle conversion (faster)")
    ap.add_argument("--frames", type=int, default=None, help="calibration frames (default: calibrate's)")
    ap.add_argument("--data-sd", type=float, default=None, help="calibrate's data_sd_mm (default: its own)")
    ap.add_argument("--calib-smooth-hz", type=float, default=None,
                    help="calibrate's low-pass cut-off (Hz; 0: raw markers, as before issue 13's second session)")
    ap.add_argument("--with-trial", action="store_true", help="calibrate on the ROM and the trial together")
    args = ap.parse_args()
    hand = HandModel.load()
    names = list(hand.dof_names)
    summary = {}
    print(f"{'set':7} {'seed':>4} {'calib°':>7} {'scale°':>7} {'oracle°':>7} {'held-out mm':>11} "
          f"{'worst joint':>17} {'s':>4}  pinned (truth never there)")
    for markers in args.sets:
        ms = load_markerset(markers)
        rows = []
        for seed in args.seeds:
            t0 = time.process_time()
            rom, static, trial, th, bones, shift = subject_trials(markers, seed)
            ckw = {} if args.frames is None else {"frames": args.frames}
            if args.data_sd is not None:
                ckw["data_sd_mm"] = args.data_sd
            data = rom
            if args.with_trial:
                data = type(rom)(**{**rom.__dict__, "points": np.concatenate([rom.points, trial.points]),
                                    "theta": np.concatenate([rom.theta, trial.theta])})
            if args.calib_smooth_hz is not None:
                ckw["smooth_hz"] = args.calib_smooth_hz
            cal = calibrate(data, ms, hand, static=static, **ckw)
            kw = {"smooth_hz": SMOOTH_HZ, "check_hand": None, "ip_coupling_sd_deg": args.dip_prior_sd,
                  "accel_sd_deg_s2": args.accel_sd}
            df = markers_to_angles(trial, ms, calibration=cal, **kw)
            e_cal, per = errors(df, th, names)
            e_sc = e_or = float("nan")
            if not args.no_scale_only:
                e_sc = errors(markers_to_angles(trial, ms, calibration=scale_only(cal), **kw), th, names)[0]
            if not args.no_oracle:
                e_or = errors(markers_to_angles(trial, ms, calibration=oracle(ms, hand, bones, shift), **kw),
                              th, names)[0]
            pinned = false_limits(df, th, hand)
            w = int(np.argmax(per))
            h = cal.held_out
            rows.append((e_cal, e_sc, e_or, bool(pinned)))
            print(f"{markers:7} {seed:4d} {e_cal:7.2f} {e_sc:7.2f} {e_or:7.2f} "
                  f"{h.get('residual_mm', float('nan')):5.2f}/{h.get('scale_only_residual_mm', float('nan')):5.2f} "
                  f"{names[6 + w]:>12} {per[w]:4.1f} {time.process_time() - t0:4.0f}  {', '.join(pinned) or '-'}",
                  flush=True)
        a = np.array(rows, float)
        summary[markers] = a
        fails = [s for s, r in zip(args.seeds, rows) if r[0] > 2.0]
        print(f"# {markers}: calibrated {a[:, 0].min():.2f}–{a[:, 0].max():.2f}° (median {np.median(a[:, 0]):.2f}), "
              f"scale only {np.nanmin(a[:, 1]):.2f}–{np.nanmax(a[:, 1]):.2f}°, "
              f"oracle {np.nanmin(a[:, 2]):.2f}–{np.nanmax(a[:, 2]):.2f}°; over 2°: "
              f"{', '.join(map(str, fails)) or 'none'}; false limits on {int(a[:, 3].sum())} seed(s)", flush=True)


if __name__ == "__main__":
    main()
