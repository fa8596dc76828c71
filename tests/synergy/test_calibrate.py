"""Subject calibration from skin markers (simulated subjects unlike the model), its held-out check,
the handedness check, conversion diagnostics and the calibrate/angles commands."""
import numpy as np
import pytest
from typer.testing import CliRunner

from handmodel import HandModel
from handmodel.dofs import anatomical_limits
from synergy.angles import _targets, markers_to_angles, read_angles_csv
from synergy.c3d_write import write_c3d
from synergy.calibrate import Calibration, calibrate, load_calibration, save_calibration, scale_only, split_frames
from synergy.cli import app
from synergy.cli_mocap import RESIDUAL_COLUMNS, describe_trial
from synergy.errors import SynergyError
from synergy.markers import load_markerset
from synergy.simulate import motion, simulate_markers, subject_protocol, weak_protocol
from synergy.smoothing import lowpass_markers
from synergy.subject import CLEARLY_BETTER, OVERFIT_RATIO

HAND = HandModel.load()
NOISE_MM = 0.5
# The floor: 2° RMS after calibration, on every simulated subject. hand16 leaves each
# proximal phalanx unmarked, so in a fist a finger's PIP and DIP can trade (+23°/−37° moves its
# markers ~1 mm): the IK's weak DIP-PIP prior and its acceleration prior decide there; calibrating
# on low-passed markers keeps the noise from lengthening middle phalanges. Seeds 0-15 of both sets
# (benchmarks/bench_calibrate.py): hand16 ≤ 1.96°, hand19 ≤ 1.7° (docs/synergy.md, "Calibration").
ANGLE_BOUND_DEG = {"hand19": 2.0, "hand16": 2.0}


def subject_trials(markers, seed):
    """A subject with every bone ±20 % and every marker ±5 mm per axis off the model; 0.5 mm noise:
    a range-of-motion trial, a static flat-hand trial and a power grasp to convert."""
    return subject_protocol(markers, seed, noise_mm=NOISE_MM)[:4]


def false_limits(df, theta):
    """Joints on a limit in more than 5 % of frames whose true trajectory never comes within 2° of it."""
    lim = anatomical_limits(HAND)
    out = []
    for dof, share in df.attrs["diagnostics"]["limit_share"].items():
        j = HAND.dof_names.index(dof)
        if share > 0.05 and np.abs(theta[:, j, None] - lim[j][None, :]).min() >= np.radians(2):
            out.append(dof)
    return out


def rms_deg(df, theta):
    est = df[HAND.dof_names].to_numpy()
    ok = np.isfinite(est).all(1)
    return float(np.degrees(np.sqrt(np.mean((est[ok, 6:] - theta[ok, 6:]) ** 2))))


@pytest.fixture(scope="module")
def hand19_files(tmp_path_factory):
    """hand19 subject (seed 1) as C3D files, calibrated by `synergy calibrate` once: the floors below
    are checked on what the command wrote, and the command's own output in the round-trip test."""
    out = tmp_path_factory.mktemp("hand19")
    rom, static, trial, th = subject_trials("hand19", 1)
    for name, tr in (("rom", rom), ("static", static), ("grasp", trial)):
        write_c3d(out / f"{name}.c3d", tr.points, tr.labels, tr.rate)
    r = CliRunner().invoke(app, ["calibrate", str(out / "rom.c3d"), "--static", str(out / "static.c3d"),
                                 "--markers", "hand19", "-o", str(out / "subject.yaml")])
    assert r.exit_code == 0, r.output
    return out, r.output, trial, th


@pytest.fixture(scope="module", params=["hand19", "hand16"])
def calibrated(request):
    markers = request.param
    if markers == "hand19":
        out, _, trial, th = request.getfixturevalue("hand19_files")
        return markers, load_calibration(out / "subject.yaml"), trial, th
    rom, static, trial, th = subject_trials(markers, 3)
    cal = calibrate(rom, load_markerset(markers), HAND, static=static)
    return markers, cal, trial, th


def test_calibration_recovers_angles_beside_scale_only(calibrated):
    markers, cal, trial, th = calibrated
    full = markers_to_angles(trial, markers, calibration=cal, smooth_hz=6.0, check_hand=None)
    only = markers_to_angles(trial, markers, calibration=scale_only(cal), smooth_hz=6.0, check_hand=None)
    e_full, e_scale = rms_deg(full, th), rms_deg(only, th)
    print(f"\n{markers}: angles {e_full:.2f}° RMS calibrated, {e_scale:.2f}° hand scale only; "
          f"held-out {cal.held_out['residual_mm']:.2f} mm vs {cal.held_out['scale_only_residual_mm']:.2f} mm")
    assert e_full <= ANGLE_BOUND_DEG[markers] and e_scale > 5 * e_full
    assert not cal.overfit and cal.held_out["residual_mm"] < 0.5 * cal.held_out["scale_only_residual_mm"]
    # what was estimated is reported with uncertainties: bones that move markers are measured tightly
    assert set(cal.uncertainty["bone_scales"]) == set(cal.bone_scales)
    assert cal.uncertainty["bone_scales"]["index2"] < 0.05


def test_residual_at_noise_floor_and_no_false_limits(calibrated):
    markers, cal, trial, th = calibrated
    df = markers_to_angles(trial, markers, calibration=cal, check_hand=None)
    M = len(trial.labels)
    # a perfect model leaves the noise the 26 DoF cannot absorb: σ√3 · √((3M − 26) / 3M) per frame
    floor = NOISE_MM * np.sqrt(3) * np.sqrt((3 * M - 26) / (3 * M))
    assert df.residual_mm.median() <= 1.5 * floor
    d = df.attrs["diagnostics"]
    assert d["noise_floor_mm"] <= 1.5 * floor and (df.quality == "ok").mean() > 0.97
    assert not false_limits(df, th), d["limit_share"]
    # per-marker residuals travel with the table
    assert set(d["marker_residuals_mm"]) == set(trial.labels)


@pytest.mark.parametrize("markers,seed", [("hand16", 4), ("hand16", 9), ("hand16", 10), ("hand19", 4)])
def test_floor_on_more_subjects(markers, seed):
    """Subjects that missed the floor before the calibration low-passed its markers and the IK tied
    frames together (hand16 2.4-3.8°, hand19 2.2°; the sweep over seeds 0-15 is
    benchmarks/bench_calibrate.py)."""
    rom, static, trial, th = subject_trials(markers, seed)
    cal = calibrate(rom, load_markerset(markers), HAND, static=static)
    df = markers_to_angles(trial, markers, calibration=cal, smooth_hz=6.0, check_hand=None)
    err = rms_deg(df, th)
    print(f"\n{markers} seed {seed}: {err:.2f}° RMS")
    assert err <= ANGLE_BOUND_DEG[markers] and not false_limits(df, th)
    assert df.attrs["accel_prior_sd_deg_s2"] == 3000.0 and "low-passed at 6 Hz" in cal.method


def test_overfitting_is_caught_by_held_out_frames():
    """A real overfit: a subject the model fits as it is, 4 fitted frames, priors 20× looser and data
    weighted as if noise-free (~90 subject numbers chase noise). Its held-out residual is above its
    training one and not clearly below the scale-only hand's on the same frames: refused (as before
    issue 40's rule; the fit it refuses converts the trial at 5.8° against 4.4° on the scale-only hand)."""
    th, _ = motion("rom", duration_s=0.1, seed=1)
    short = simulate_markers(th, "hand19", noise_mm=NOISE_MM, seed=2)
    ms = load_markerset("hand19")
    loose = calibrate(short, ms, HAND, frames=4, held_out=0.5, offset_scale=20.0, bone_sd=3.0, data_sd_mm=0.05)
    h = loose.held_out
    assert h["residual_mm"] > OVERFIT_RATIO * h["train_residual_mm"] + 0.02  # the gap …
    assert not h["residual_mm"] < CLEARLY_BETTER * h["scale_only_residual_mm"]  # … not paid for
    assert loose.overfit and "not used: it does not generalise" in loose.method
    assert any("does not generalise: median marker residual on 4 held-out frames" in w for w in loose.warnings)
    assert not loose.bone_scales and not loose.offsets  # the scale-only hand
    df = markers_to_angles(short, ms, calibration=loose, check_hand=None)
    assert df.attrs["diagnostics"]["calibration_overfit"] and df.attrs["diagnostics"]["verdict"] == "poor"
    # the refusal names the figures it was decided on, in the one residual definition
    from synergy.fit import poor_reasons

    why = [r for r in poor_reasons(df.attrs["diagnostics"]) if "held-out check" in r]
    assert why and f"{h['residual_mm']:.2f} mm calibrated, {h['scale_only_residual_mm']:.2f} mm hand scale only" in why[0]


@pytest.fixture(scope="module")
def weak_fretting():
    """Issue 40's failure in simulation: the weakly observed protocol (hand19, proximal markers at 0.2
    of the bone, the set says 0.5), 1 s of fretting, no static trial, converted as `synergy angles
    --smooth-hz 6` does (automatic calibration)."""
    tr, th = weak_protocol(2, "fretting", duration_s=1.0)
    return tr, th, markers_to_angles(tr, "hand19", check_hand=None, smooth_hz=6.0)


def test_a_calibration_far_better_than_the_scale_only_hand_is_kept(weak_fretting):
    """The calibration generalises worse than it trains (held out 0.27 mm, fitted 0.18 mm: the rule
    before called it overfit) but far better than the scale-only hand on the same frames (5.3 mm):
    kept. The rule before fell back to the scale-only hand: table 5.4 mm, angles 12.4° RMS, a
    'poor' verdict (8.8° with the calibration)."""
    tr, th, df = weak_fretting
    cal = df.attrs["calibration"]
    h = cal["held_out"]
    assert h["residual_mm"] > OVERFIT_RATIO * h["train_residual_mm"] + 0.02
    assert h["residual_mm"] < 0.2 * h["scale_only_residual_mm"]
    assert not h["overfit"] and "not used" not in cal["method"] and cal["bone_scales"]
    d = df.attrs["diagnostics"]
    assert not d["calibration_overfit"] and d["verdict"] != "poor"
    plain = scale_only(Calibration.from_dict(cal))
    sc = markers_to_angles(tr, "hand19", calibration=plain, check_hand=None, smooth_hz=6.0)
    e_cal, e_sc = rms_deg(df, th), rms_deg(sc, th)
    print(f"\nweak fretting 1 s, seed 2: {e_cal:.1f}° calibrated, {e_sc:.1f}° hand scale only")
    assert e_cal < e_sc - 2.0
    assert np.nanmedian(df["residual_mm"]) < 0.2 * np.nanmedian(sc["residual_mm"])


@pytest.mark.parametrize("hand_used", ["calibrated", "hand scale only"])
def test_one_residual_in_the_table_and_the_calibration_line(hand_used, weak_fretting):
    """The calibration line's held-out figure for the hand the table uses is the table's figure (the
    median over frames of a frame's RMS marker residual) on the same frames; both hands are given in
    that one definition, named."""
    if hand_used == "calibrated":
        tr, _, df = weak_fretting
        ms = load_markerset("hand19")
    else:  # a subject the model fits as it is: the fit buys nothing, the scale-only hand converts
        th, _ = motion("power_grasp", duration_s=2.0, seed=3)
        tr = simulate_markers(th, "hand16", noise_mm=0.3, seed=4)
        ms = load_markerset("hand16")
        df = markers_to_angles(tr, ms, check_hand=None, smooth_hz=6.0)
    cal = df.attrs["calibration"]
    h = cal["held_out"]
    assert ("not used" in cal["method"]) == (hand_used == "hand scale only")
    # the calibration's held-out frames, found as calibrate finds them (the markers as converted)
    tg, _ = _targets(tr, ms, None)
    _, held = split_frames(lowpass_markers(tg, tr.rate, 6.0), 150, 0.25)
    assert len(held) == h["frames"] > 20
    table = float(np.nanmedian(df["residual_mm"].to_numpy()[held]))
    mine = h["residual_mm"] if hand_used == "calibrated" else h["scale_only_residual_mm"]
    print(f"\n{hand_used}: table {table:.3f} mm on the held-out frames, calibration line {mine:.3f} mm")
    assert table == pytest.approx(mine, rel=0.1)
    line = describe_trial("t", df)[1]
    assert (f"median marker residual on {h['frames']} held-out frames {h['residual_mm']:.2f} mm calibrated, "
            f"{h['scale_only_residual_mm']:.2f} mm hand scale only") in line
    assert line.endswith(f"the table's hand: {hand_used}")
    assert RESIDUAL_COLUMNS.startswith("med/95th mm: median marker residual")


def test_wrong_hand_stops_or_warns():
    th, _ = motion("open_close", duration_s=1.5, seed=2)
    tr = simulate_markers(th, "hand19", noise_mm=0.3, seed=3)
    with pytest.raises(SynergyError, match="left hand fits these markers better"):
        markers_to_angles(tr, "hand19", hand="right")
    df = markers_to_angles(tr, "hand19", hand="right", check_hand="warn", calibration=None)
    d = df.attrs["diagnostics"]
    assert d["handedness"]["verdict"] == "wrong hand" and d["verdict"] == "poor"
    # the limit check of the floors above sees what a wrong hand does: joints held on limits the
    # true motion never reaches
    assert false_limits(df, th)
    ok = markers_to_angles(tr, "hand19", hand="left", calibration=None)
    assert ok.attrs["diagnostics"]["handedness"]["verdict"] == "ok"


def test_poor_frames_relative_to_noise_floor():
    th, _ = motion("abduction", duration_s=2.0, seed=4)
    tr = simulate_markers(th, "hand16", noise_mm=0.3, seed=5)
    bad = tr.points.copy()
    bad[50:80, 3] += 0.010  # a marker knocked 10 mm for 0.3 s: ~2.5 mm RMS, far below the old fixed 10 mm
    tr.points = bad
    df = markers_to_angles(tr, "hand16", calibration=None)
    q = df.quality.to_numpy()
    assert (q[50:80] == "poor").mean() >= 0.9 and (q[:45] == "ok").all()
    d = df.attrs["diagnostics"]
    assert d["poor_threshold_mm"] < 3.0 and d["marker_residuals_mm"]["MC3"][1] > 2.0


def test_subject_file_round_trip_and_commands(hand19_files, tmp_path):
    files, output, trial, th = hand19_files
    runner = CliRunner()
    assert "held-out frames" in output and max(len(line) for line in output.splitlines()) <= 80
    for name in ("grasp.c3d", "subject.yaml"):
        (tmp_path / name).write_bytes((files / name).read_bytes())
    cal = load_calibration(tmp_path / "subject.yaml")
    assert cal.hand == "left" and cal.markerset == "hand19" and len(cal.source_sha256) == 64
    assert cal.scale != 1.0 and cal.bone_scales and cal.uncertainty["offsets_mm"]
    assert cal.method.endswith("(markers low-passed at 6 Hz)")  # synergy calibrate's default
    r = runner.invoke(app, ["calibrate", str(files / "rom.c3d"), "--markers", "hand19", "--smooth-hz", "-3",
                            "-o", str(tmp_path / "s2.yaml")])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "--smooth-hz" in r.output
    with pytest.raises(FileExistsError):
        save_calibration(cal, tmp_path / "subject.yaml")
    r = runner.invoke(app, ["angles", str(tmp_path / "grasp.c3d"), "--markers", "hand19", "--subject",
                            str(tmp_path / "subject.yaml"), "--plot", "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert max(len(line) for line in lines) <= 80
    assert "worst markers" in r.output and "median marker residual on" in r.output
    # the calibration is reported as estimated, not "1.000"
    assert f"{cal.scale:.3f}" in r.output
    assert (tmp_path / "out" / "grasp.png").stat().st_size > 10_000
    df = read_angles_csv(tmp_path / "out" / "grasp.csv")
    assert df.attrs["diagnostics"]["marker_residuals_mm"]["INAIL"][0] < 1.5
    assert rms_deg(df, th) < 5.0  # unsmoothed (noise-limited per frame); smoothed bounds are tested above
    assert df.attrs["dip_prior"] == {"ratio": pytest.approx(2 / 3), "sd_deg": 10.0}
    assert df.attrs["accel_prior_sd_deg_s2"] is None  # frames tied together only when the markers are low-passed
    r = runner.invoke(app, ["angles", str(tmp_path / "grasp.c3d"), "--markers", "hand19", "--dip-prior-sd", "-1",
                            "-o", str(tmp_path / "o3")])
    assert r.exit_code == 2 and "--dip-prior-sd" in r.output and len(r.output.strip().splitlines()) == 1
    # a calibration for the other hand is refused
    r = runner.invoke(app, ["angles", str(tmp_path / "grasp.c3d"), "--markers", "hand19", "--hand", "right",
                            "--no-hand-check", "--subject", str(tmp_path / "subject.yaml"), "-o", str(tmp_path / "o2")])
    assert r.exit_code == 2 and "calibrated for the left hand" in r.output
