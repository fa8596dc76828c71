"""Marker IK: simulate → angles round trips (noise, gaps, hand size), calibration, CSV output."""
import numpy as np
import pytest

from handmodel import HandModel
from synergy.angles import lowpass_markers, markers_to_angles, read_angles_csv, write_angles_csv
from synergy.calibrate import calibrate
from synergy.markers import load_markerset
from synergy.simulate import MOTIONS, motion, simulate_markers

HAND = HandModel.load()
POSTURE = HAND.dof_names[6:]


def rms_deg(df, theta):
    est = df[HAND.dof_names].to_numpy()
    ok = np.isfinite(est).all(1)
    return np.degrees(np.sqrt(np.mean((est[ok, 6:] - theta[ok, 6:]) ** 2)))


@pytest.mark.parametrize("name", list(MOTIONS))
def test_noise_free_round_trip(name):
    th, task = motion(name, duration_s=2.0, seed=3)
    tr = simulate_markers(th, "hand16", seed=1)
    df = markers_to_angles(tr, "hand16")
    assert rms_deg(df, th) <= 0.05
    assert (df.quality == "ok").all() and df.residual_mm.max() < 0.01
    assert task == MOTIONS[name][0]


@pytest.mark.parametrize("scale", [0.85, 1.0, 1.15])
def test_noise_gaps_and_hand_size(scale):
    th, _ = motion("power_grasp", duration_s=4.0, seed=5)
    tr = simulate_markers(th, "hand16", scale=scale, noise_mm=0.5, gap_fraction=0.05, seed=2)
    df = markers_to_angles(tr, "hand16", smooth_hz=6.0)
    cal = df.attrs["calibration"]
    assert abs(cal["scale"] - scale) / scale < 0.01        # calibration finds the hand size
    err = rms_deg(df, th)
    # 0.5 mm noise on markers 15–25 mm apart: the per-frame Cramér-Rao bound of hand16 is ~4° RMS;
    # 6 Hz smoothing brings it to ~1.5°. Without calibration the error is much larger (next test).
    assert err <= 2.5, err
    assert np.isnan(tr.points[..., 0]).mean() > 0.04


def test_calibration_matters():
    th, _ = motion("open_close", duration_s=3.0, seed=6)
    tr = simulate_markers(th, "hand16", scale=1.15, seed=2)
    good = rms_deg(markers_to_angles(tr, "hand16"), th)
    bad = rms_deg(markers_to_angles(tr, "hand16", calibration=None), th)
    assert good < 0.05 and bad > 10 * good


def test_static_trial_calibration_and_right_hand():
    th, _ = motion("abduction", duration_s=2.0, seed=7)
    static = simulate_markers(th[:50], "hand16", scale=1.1, hand="right", seed=3)
    trial = simulate_markers(th, "hand16", scale=1.1, hand="right", seed=4)
    # noise-free markers: the calibration's low-pass would only bend this short moving trial at its
    # ends (0.05° instead of 0.01° below)
    cal = calibrate(static, load_markerset("hand16"), HandModel.load(right=True), right=True, smooth_hz=None)
    assert abs(cal.scale - 1.1) < 0.005
    df = markers_to_angles(trial, "hand16", hand="right", calibration=cal)
    assert rms_deg(df, th) < 0.05
    assert df.attrs["hand"] == "right"


def test_joint_centre_protocol_calibrates_bones():
    """ART-like joint centres on a hand with other proportions: bone lengths are measured."""
    th, _ = motion("open_close", duration_s=2.0, seed=8)
    subject = HAND.scaled(1.2, {"index2": 1.2, "thumb2": 0.8, "pinky3": 1.1})
    kp = subject.keypoints(th)

    class Data:
        labels = ["LHAN", "LTIN", "LTMI", "LTOU", "LTTI", "LIFI", "LIFM", "LIFO", "LIFT", "LMFI", "LMFM", "LMFO",
                  "LMFT", "LRFI", "LRFM", "LRFO", "LRFT", "LPIN", "LPMI", "LPOU", "LPTI"]
        points = kp
        rate = 60.0
        first_frame = 1

    df = markers_to_angles(Data(), "art-joint-centres", hand="left")
    assert df.residual_mm.median() < 1e-3
    assert rms_deg(df, th) < 0.05
    assert df.attrs["calibration"]["method"].startswith("bone lengths")


def test_gap_frames_and_quality_flags():
    th, _ = motion("open_close", duration_s=1.0, seed=9)
    tr = simulate_markers(th, "hand16", seed=1)
    tr.points[10:15, 3:] = np.nan  # only 3 markers left: not solvable
    df = markers_to_angles(tr, "hand16")
    assert (df.quality[10:15] == "gap").all() and df.loc[10:14, POSTURE].isna().all().all()
    ok = df.quality == "ok"
    assert ok.sum() == len(df) - 5
    # tracking resumes right after the gap
    est = df[HAND.dof_names].to_numpy()
    assert np.degrees(np.abs(est[15:, 6:] - th[15:, 6:])).max() < 0.1


def test_csv_round_trip(tmp_path):
    th, _ = motion("precision_grasp", duration_s=1.0, seed=2)
    tr = simulate_markers(th, "hand16", seed=1)
    df = markers_to_angles(tr, "hand16")
    p = write_angles_csv(df, tmp_path / "t.csv")
    back = read_angles_csv(p)
    np.testing.assert_allclose(back[HAND.dof_names].to_numpy(), df[HAND.dof_names].to_numpy(), rtol=1e-8, atol=1e-12)
    assert back.attrs["markerset"] == "hand16" and back.attrs["calibration"]["scale"] == df.attrs["calibration"]["scale"]
    with pytest.raises(FileExistsError):
        write_angles_csv(df, p)


def test_lowpass_keeps_gaps_and_removes_noise():
    rng = np.random.default_rng(0)
    t = np.arange(1000) / 100.0
    clean = np.stack([np.sin(2 * np.pi * 0.5 * t)] * 3, -1)[:, None, :].repeat(2, 1)
    noisy = clean + rng.normal(0, 0.01, clean.shape)
    noisy[300:320, 1] = np.nan
    out = lowpass_markers(noisy, 100.0, 6.0)
    assert np.isnan(out[300:320, 1]).all() and not np.isnan(out[:300]).any()
    ok = ~np.isnan(out[..., 0])
    assert np.std((out - clean)[ok]) < 0.45 * np.std((noisy - clean)[ok])
