"""The marker IK's Gaussian posture prior and its observability report (issue 40): the prior's rows
are its density, the posterior SD is what repeated noisy fits scatter by, a joint no marker sees
follows the prior and is named prior-driven, a seen joint follows its markers, the choice and the
prior are recorded, and the simulated weakly observed protocol reproduces the failure."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from handmodel import HandModel
from handmodel.solver import SolverSettings, fit_points
from synergy.angles import markers_to_angles, read_angles_csv, write_angles_csv
from synergy.ik_priors import posterior_sd, prior_driven, prior_rows, refine_with_prior
from synergy.c3d_write import write_c3d
from synergy.cli import app
from synergy.prior import PosturePrior
from synergy.simulate import motion, simulate_markers, weak_protocol

HAND = HandModel.load()
PRIOR = PosturePrior.from_bundle("fingerfist")
POST = np.flatnonzero(~HAND.pose_mask)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2 ** 31 - 1))
def test_prior_rows_are_the_gaussian_density(seed):
    th = np.random.default_rng(seed).normal(0, 0.5, HAND.n_dofs)
    P, c = prior_rows(HAND, PRIOR)
    d = th[POST] - PRIOR.mean
    # independent: the quadratic form through a linear solve, not the eigen-whitening
    np.testing.assert_allclose(np.sum((P @ th - c) ** 2), d @ np.linalg.solve(PRIOR.cov, d), rtol=1e-8)


def test_prior_floor_and_marginals():
    assert PRIOR.name == "fingerfist@1.0.0" and PRIOR.samples > 1000
    # every direction at least the floor wide: the smallest eigenvalue is the floor's variance or more
    assert np.linalg.eigvalsh(PRIOR.cov).min() >= np.radians(PRIOR.floor_deg) ** 2 * (1 - 1e-9)
    X = np.random.default_rng(0).multivariate_normal(PRIOR.mean, PRIOR.cov, 20000)
    fitted = PosturePrior.from_postures(X, floor_deg=0.0)
    np.testing.assert_allclose(fitted.sd_deg, PRIOR.sd_deg, rtol=0.03)


def _every_node_markers():
    nodes = np.r_[np.arange(HAND.n_nodes), np.arange(HAND.n_nodes)]
    local = np.r_[np.zeros((HAND.n_nodes, 3)), np.tile([0.0, 0.0, 0.01], (HAND.n_nodes, 1))]
    return nodes, local


def _posture():
    th = np.zeros((1, HAND.n_dofs))
    th[0, :6] = [0.01, 0.02, 0.3, 0.2, -0.1, 0.3]
    th[0, POST] = np.radians([10, -20, -10, -15, 5, -40, -60, -30, 0, -45, -70, -35, -3, -50, -65, -30, -5,
                              -55, -60, -25])
    return th


def test_posterior_sd_is_the_scatter_of_noisy_fits():
    """The SD from the normal equations against 400 fits of the same posture under fresh 0.5 mm noise
    (what a wrong unit or a missing noise factor would miss by 2x or 1000x)."""
    nodes, local = _every_node_markers()
    truth = _posture()
    clean = HAND.points(truth, nodes, local)
    rng = np.random.default_rng(3)
    noisy = clean[None, 0] + rng.normal(0, 0.5e-3, (400,) + clean.shape[1:])
    fits, _ = fit_points(HAND, nodes, local, noisy, truth[0], settings=SolverSettings(iterations=15, damping=1e-6),
                         restarts=0)
    sd = posterior_sd(HAND, nodes, local, truth, None, np.ones((1, len(nodes)), bool), noise_mm=0.5)[0]
    emp = fits.std(0)
    np.testing.assert_allclose(emp[POST], sd[POST], rtol=0.2)


def test_unseen_joint_follows_the_prior_and_is_named():
    """No marker on the pinky's distal phalanx: its DIP is free for the markers, so the prior decides
    it (its conditional mean given the seen joints), its SD is infinite without the prior and the
    prior's with it, and it is the joint named prior-driven; every joint a marker sees stays where
    the markers put it."""
    keep = [k for k in range(HAND.n_nodes) if HAND.node_names[k] not in ("pinky3", "pinky_tip")]
    nodes = np.r_[keep, keep]
    local = np.r_[np.zeros((len(keep), 3)), np.tile([0.0, 0.0, 0.01], (len(keep), 1))]
    truth = _posture()
    tg = HAND.points(truth, nodes, local)
    rows = prior_rows(HAND, PRIOR)
    out = refine_with_prior(HAND, nodes, local, tg, truth, None, noise_mm=0.3, rows=rows, mean=PRIOR.mean)
    names = list(HAND.dof_names)
    free = [names.index("pinky3_flex")]
    seen = [j for j in POST if j not in free]
    assert np.degrees(np.abs(out[0, seen] - truth[0, seen])).max() < 1.0
    # the Gaussian's conditional mean of the free pair given the others at their (seen) values
    S = PRIOR.cov
    f = [list(POST).index(j) for j in free]
    o = [i for i in range(len(POST)) if i not in f]
    cond = PRIOR.mean[f] + S[np.ix_(f, o)] @ np.linalg.solve(S[np.ix_(o, o)], out[0, POST[o]] - PRIOR.mean[o])
    lim = HAND.limits[free]
    np.testing.assert_allclose(out[0, free], np.clip(cond, lim[:, 0], lim[:, 1]), atol=np.radians(0.5))
    present = np.ones((1, len(nodes)), bool)
    sd_with = posterior_sd(HAND, nodes, local, out, None, present, noise_mm=0.3, rows=rows)
    sd_without = posterior_sd(HAND, nodes, local, out, None, present, noise_mm=0.3)
    assert np.isinf(sd_without[0, free]).all() and np.isfinite(sd_without[0, seen]).all()
    assert list(prior_driven(sd_with, sd_without, names)) == ["pinky3_flex"]


def test_auto_keeps_a_well_observed_conversion_bit_for_bit(tmp_path):
    """hand19 sees every joint of an open-close trial: 'auto' chooses no posture prior, and the angles
    are those of prior=None exactly; the CSV records the choice, the noise and the SD columns."""
    th, _ = motion("open_close", duration_s=0.6, seed=2)
    tr = simulate_markers(th, "hand19", noise_mm=0.5, seed=4)
    auto = markers_to_angles(tr, "hand19", calibration=None, check_hand=None)
    off = markers_to_angles(tr, "hand19", calibration=None, check_hand=None, prior=None)
    assert auto.attrs["posture_prior"] is None and auto.attrs["diagnostics"]["prior_driven"] == {}
    np.testing.assert_array_equal(auto[HAND.dof_names].to_numpy(), off[HAND.dof_names].to_numpy())
    on = markers_to_angles(tr, "hand19", calibration=None, check_hand=None, prior="fingerfist")
    assert on.attrs["posture_prior"]["name"] == "fingerfist@1.0.0"
    # well observed: forced on, the prior costs little against the truth (its pull shows on the
    # most flexed DIPs, beyond the fingerfist postures, by a few degrees)
    err = [np.degrees(np.sqrt(np.mean((d[HAND.dof_names].to_numpy()[:, 6:] - th[:, 6:]) ** 2))) for d in (off, on)]
    assert err[1] < err[0] + 0.5, err
    write_angles_csv(on, tmp_path / "a.csv")
    back = read_angles_csv(tmp_path / "a.csv")
    assert back.attrs["posture_prior"]["name"] == "fingerfist@1.0.0" and back.attrs["marker_noise_mm"] > 0
    sd = np.degrees(back[[f"{HAND.dof_names[j]}_sd" for j in POST]].to_numpy())
    assert np.isfinite(sd).all() and 0 < sd.max() < 10
    post_sd = back.attrs["diagnostics"]["posterior_sd_deg"]
    assert all(w <= wo + 1e-9 for w, wo in post_sd.values())  # a prior never adds uncertainty


def test_weak_protocol_reproduces_the_failure():
    """The simulated protocol of issue 40: the proximal markers sit at 0.2 of the bone, the set says
    0.5. On the uncalibrated model the IK is far off (the MCP/PIP split and every last joint left to
    misplaced markers); the prior brings it closer without bending the fit of the markers."""
    tr, th = weak_protocol(1, "power_grasp", duration_s=1.0)
    assert tr.points.shape == (100, 19, 3)

    def rms(df):
        est = df[HAND.dof_names].to_numpy()
        return float(np.degrees(np.sqrt(np.mean((est[:, 6:] - th[:, 6:]) ** 2))))

    off = markers_to_angles(tr, "hand19", calibration=None, check_hand=None, prior=None)
    on = markers_to_angles(tr, "hand19", calibration=None, check_hand=None, prior="fingerfist")
    e_off, e_on = rms(off), rms(on)
    print(f"\nweak protocol, uncalibrated: {e_off:.1f}° prior off, {e_on:.1f}° on")
    assert e_off > 8.0 and e_on < 0.75 * e_off
    r_off, r_on = np.nanmedian(off["residual_mm"]), np.nanmedian(on["residual_mm"])
    assert r_on < r_off + 0.5


@pytest.mark.parametrize("prior, ok", [("none", True), ("fingerfist", True), ("no-such-bundle", False)])
def test_angles_cli_prior_option(tmp_path, prior, ok):
    tr, _ = weak_protocol(0, "fretting", duration_s=0.5)
    write_c3d(tmp_path / "t.c3d", tr.points, tr.labels, tr.rate)
    r = CliRunner().invoke(app, ["angles", str(tmp_path / "t.c3d"), "--markers", "hand19", "--hand", "left",
                                 "--no-calibration", "-o", str(tmp_path / "out"), "--prior", prior, "--plot"])
    if not ok:
        assert r.exit_code == 2 and "no-such-bundle" in r.output and "Traceback" not in r.output
        return
    assert r.exit_code == 0, r.output
    df = read_angles_csv(tmp_path / "out" / "t.csv")
    assert (df.attrs["posture_prior"] is None) == (prior == "none")
    assert (tmp_path / "out" / "t.png").stat().st_size > 10000
    if prior == "fingerfist":
        assert "posture prior: fingerfist@1.0.0" in r.output


def test_neutral_frames_are_the_open_hand_and_fix_the_calibration():
    """Without a static trial the grasp's open phases stand in for one: the frames found are open in
    truth (every finger flexion under 30°), a fretting hand has none, and the calibration they fix
    converts the weakly observed grasp better than the one without them."""
    from synergy.calibrate import calibrate, neutral_frames
    from synergy.markers import load_markerset

    ms = load_markerset("hand19")
    names = list(HAND.dof_names)
    flex = [names.index(f"{f}{k}_flex") for f in ("index", "middle", "ring", "pinky") for k in (1, 2, 3)]
    tr, th = weak_protocol(2, "power_grasp")
    n, l = ms.attachments(HAND)
    at = neutral_frames(HAND, n, l, tr.points, None)
    assert len(at) >= 5 and np.degrees(np.abs(th[np.ix_(at, flex)])).max() < 30
    fret, _ = weak_protocol(0, "fretting", duration_s=2.0)
    assert len(neutral_frames(HAND, n, l, fret.points, None)) == 0

    def rms(cal):
        df = markers_to_angles(tr, ms, calibration=cal, check_hand=None, prior=None, smooth_hz=6.0)
        return float(np.degrees(np.sqrt(np.mean((df[names].to_numpy()[:, 6:] - th[:, 6:]) ** 2))))

    with_n = calibrate(tr, ms, HAND, require_gain=0.8, neutral=True)
    without = calibrate(tr, ms, HAND, require_gain=0.8)
    assert "neutral frames" in with_n.static_source
    e_with, e_without = rms(with_n), rms(without)
    print(f"\nweak grasp, seed 2: {e_without:.1f}° calibrated without neutral frames, {e_with:.1f}° with")
    assert e_with < 4.0 and e_with < 0.5 * e_without


def test_fretting_without_open_frames_calibrates_with_the_prior():
    """A fretting hand has no open-hand frame: 'auto' holds its calibration frames' postures to the
    posture prior (as one posture), which keeps the last joints' zeros nearer the truth than the
    markers' nominal places alone do (the calibration is recorded as such)."""
    tr, th = weak_protocol(3, "fretting", duration_s=2.0)
    names = list(HAND.dof_names)

    def rms(df):
        return float(np.degrees(np.sqrt(np.mean((df[names].to_numpy()[:, 6:] - th[:, 6:]) ** 2))))

    auto = markers_to_angles(tr, "hand19", check_hand=None, smooth_hz=6.0)
    off = markers_to_angles(tr, "hand19", check_hand=None, smooth_hz=6.0, prior=None)
    assert "posture prior fingerfist@1.0.0" in auto.attrs["calibration"]["method"]
    assert "posture prior" not in off.attrs["calibration"]["method"]
    print(f"\nfretting seed 3 (2 s): {rms(off):.1f}° without the prior, {rms(auto):.1f}° auto")
    assert rms(auto) < rms(off) - 1.0


def test_last_bone_markers_keep_their_places_without_a_known_posture():
    """Without a known posture, the markers on each chain's last bone (hand19: the five nails) keep
    their nominal places, which alone fix the last joints' zeros (free, they moved 1.7-3.2 mm on this
    trial); with a static trial they are fitted as before."""
    from synergy.calibrate import calibrate
    from synergy.markers import load_markerset
    from synergy.simulate import subject_protocol
    from synergy.subject import last_bone_markers

    ms = load_markerset("hand19")
    held = [m.label for m, h in zip(ms.markers, last_bone_markers(HAND.parents, ms.attachments(HAND)[0])) if h]
    assert held == ["TNAIL", "INAIL", "MNAIL", "RNAIL", "PNAIL"]
    tr, _ = weak_protocol(3, "fretting", duration_s=2.0)
    cal = calibrate(tr, ms, HAND, require_gain=0.8, neutral=True, posture_prior=PRIOR, prior_frames=1.0)
    assert "last-bone markers within 1.5 mm" in cal.method
    assert max(cal.marker_shift_mm[k] for k in held) < 1.0
    rom, static, *_ = subject_protocol("hand19", 0)
    cal = calibrate(rom, ms, HAND, static=static, posture_prior=PRIOR, frames=40)
    assert "static posture" in cal.method and "last-bone" not in cal.method


def test_neutral_frames_kept_where_they_generalise_worse_but_far_better_than_scale_only():
    """A 1 s weakly observed grasp: the calibration with its neutral frames generalises worse than it
    trains (held out 0.32 mm, fitted 0.22 mm) and far better than the scale-only hand (5.1 mm). The
    rule before called that overfit and fell back to the fit without neutral frames (21.3° RMS, its
    last joints' zeros left to the markers); kept, the grasp converts at 4.1°."""
    from synergy.subject import OVERFIT_RATIO

    tr, th = weak_protocol(2, "power_grasp", duration_s=1.0)
    df = markers_to_angles(tr, "hand19", check_hand=None, smooth_hz=6.0)
    cal = df.attrs["calibration"]
    h = cal["held_out"]
    assert "neutral frames" in cal["static_source"] and "not used" not in cal["method"] and not h["overfit"]
    assert h["residual_mm"] > OVERFIT_RATIO * h["train_residual_mm"] + 0.02
    err = float(np.degrees(np.sqrt(np.mean((df[HAND.dof_names].to_numpy()[:, 6:] - th[:, 6:]) ** 2))))
    print(f"\nweak grasp 1 s, seed 2: {err:.1f}° with the neutral frames' calibration")
    assert err < 5.0


def test_calibration_names_the_joint_zeros_it_leaves_open():
    """Without a known posture, a nail marker's place along its arc is its joint's zero, which no marker
    motion shows: the subject fit leaves the five last joints' zeros open by 10-20° (SD of the trial's
    mean angle, :func:`synergy.subject.joint_zero_sd`), the table's lines name them although every
    frame's own SD is ~2°, and the trial's true constant errors lie within 2.5 SD (the largest 1.7 on
    this trial and seeds 0, 1). With a static trial every zero is fixed within a few degrees."""
    from synergy.angles import OPEN_ZERO_DEG
    from synergy.calibrate import calibrate
    from synergy.cli_mocap import describe_trial
    from synergy.markers import load_markerset
    from synergy.simulate import subject_protocol

    tr, th = weak_protocol(3, "fretting", duration_s=2.0)
    df = markers_to_angles(tr, "hand19", check_hand=None, smooth_hz=6.0)
    d = df.attrs["diagnostics"]
    zero = d["calibration_zero_sd_deg"]
    last = ["thumb3_flex", "index3_flex", "middle3_flex", "ring3_flex", "pinky3_flex"]
    assert set(zero) == set(np.array(HAND.dof_names)[POST]) and min(zero[k] for k in last) > 10.0
    assert set(last) <= set(d["calibration_open_zeros"])
    assert max(zero[f"{f}1_flex"] for f in ("index", "middle", "ring", "pinky")) < min(zero[k] for k in last)
    bias = np.degrees(df[HAND.dof_names].to_numpy() - th).mean(0)
    assert all(abs(bias[HAND.dof_names.index(k)]) < 2.5 * v for k, v in zero.items())
    assert max(d["posterior_sd_deg"][k][0] for k in last) < 3.0  # what the per-frame SD says
    line = [s for s in describe_trial("t", df) if "calibration-driven zeros" in s]
    assert len(line) == 1 and all(k in line[0] for k in last)

    ms = load_markerset("hand19")
    rom, static, *_ = subject_protocol("hand19", 0)
    cal = calibrate(rom, ms, HAND, static=static, frames=40)
    assert max(cal.uncertainty["joint_zero_deg"].values()) < OPEN_ZERO_DEG
