"""The weak priors of the marker IK: the DIP–PIP coupling (synergy.ik_priors.refine_with_coupling)
decides a DIP the markers do not see and leaves one they do see where the markers put it; the
acceleration prior (refine_trajectory) ties frames together where the markers leave a joint free and
does not slow a joint they see."""
import numpy as np

from handmodel import HandModel
from synergy.ik_priors import (
    IP_COUPLING,
    ip_coupling_pairs,
    refine_trajectory,
    refine_with_coupling,
)

HAND = HandModel.load()
PAIRS = ip_coupling_pairs(HAND)


def posture(pip, dip):
    th = np.zeros((1, HAND.n_dofs))
    th[0, :6] = [0.01, 0.02, 0.3, 0.2, -0.1, 0.3]
    th[0, PAIRS[:, 0]] = pip
    th[0, PAIRS[:, 1]] = dip
    return th


def test_observed_dip_stays_where_the_markers_put_it():
    # a marker at every node and one above it: each DIP is measured; truth far from the coupling
    nodes = np.r_[np.arange(HAND.n_nodes), np.arange(HAND.n_nodes)]
    local = np.r_[np.zeros((HAND.n_nodes, 3)), np.tile([0.0, 0.0, 0.01], (HAND.n_nodes, 1))]
    truth = posture(-1.0, 0.0)
    tg = HAND.points(truth, nodes, local)
    out = refine_with_coupling(HAND, nodes, local, tg, truth, None, noise_mm=0.3)
    # the coupling says DIP −38°; two markers see each DIP at 0.25–0.29 mm/° against 0.3 mm noise,
    # so the posterior gives way by ~1° (a prior in the wrong units or 10× too strong: tens of degrees)
    assert np.degrees(np.abs(out - truth)[0, 6:]).max() < 1.5


def test_unseen_dip_follows_its_pip():
    # no marker on a distal phalanx or beyond: the data leave every DIP free
    seen = [k for k in range(HAND.n_nodes) if not HAND.node_names[k].endswith(("3", "_tip"))
            or HAND.node_names[k].startswith("thumb")]
    nodes, local = np.array(seen), np.tile([0.0, 0.0, 0.01], (len(seen), 1))
    truth = posture(-1.2, -0.2)
    tg = HAND.points(truth, nodes, local)
    out = refine_with_coupling(HAND, nodes, local, tg, truth, None, noise_mm=0.3)
    np.testing.assert_allclose(out[0, PAIRS[:, 1]], IP_COUPLING * out[0, PAIRS[:, 0]], atol=1e-3)
    np.testing.assert_allclose(out[0, PAIRS[:, 0]], -1.2, atol=1e-3)  # the PIPs the markers see stay
    # frames without a posture (unsolved) pass through untouched
    both = refine_with_coupling(HAND, nodes, local, np.r_[tg, tg], np.r_[truth, np.full_like(truth, np.nan)],
                                None, noise_mm=0.3)
    assert np.isnan(both[1]).all()


def test_trajectory_prior_keeps_fast_observed_motion():
    # every DIP seen by two markers; PIPs and DIPs swing 30° at 4 Hz (~19000°/s² peak, 6× the prior's SD)
    nodes = np.r_[np.arange(HAND.n_nodes), np.arange(HAND.n_nodes)]
    local = np.r_[np.zeros((HAND.n_nodes, 3)), np.tile([0.0, 0.0, 0.01], (HAND.n_nodes, 1))]
    t = np.arange(60) / 100.0
    truth = np.repeat(posture(-0.8, -0.5), len(t), axis=0)
    truth[:, PAIRS.ravel()] += np.radians(30) * np.sin(2 * np.pi * 4 * t)[:, None]
    tg = HAND.points(truth, nodes, local)
    out = refine_trajectory(HAND, nodes, local, tg, truth, None, noise_mm=0.3, rate=100.0, accel_sd_deg_s2=3000.0,
                            ip_sd_deg=None)
    # the swing stays within ~2° inside the trial (4° at its ends, where one side has no frames to
    # be tied to); a prior 10× too strong flattens it by 21-25°, and at 30000°/s² the same swing
    # comes out within 0.2°
    err = np.degrees(np.abs(out - truth)[:, 6:])
    assert err[5:-5].max() < 2.5 and err.max() < 5.0, err.max(1)


def test_trajectory_prior_steadies_a_joint_the_markers_leave_free():
    seen = [k for k in range(HAND.n_nodes) if not HAND.node_names[k].endswith(("3", "_tip"))
            or HAND.node_names[k].startswith("thumb")]
    nodes, local = np.array(seen), np.tile([0.0, 0.0, 0.01], (len(seen), 1))
    truth = np.repeat(posture(-1.2, -0.6), 40, axis=0)
    tg = HAND.points(truth, nodes, local)
    start = truth.copy()
    start[:, PAIRS[:, 1]] += np.random.default_rng(0).normal(0, np.radians(10), (40, len(PAIRS)))  # flips
    start[20] = np.nan  # an unsolved frame: passes through, and its neighbours are not tied across it
    out = refine_trajectory(HAND, nodes, local, tg, start, None, noise_mm=0.3, rate=100.0, accel_sd_deg_s2=3000.0,
                            ip_sd_deg=None)
    assert np.isnan(out[20]).all() and np.isfinite(np.delete(out, 20, axis=0)).all()
    jump_in = np.degrees(np.abs(np.diff(start[:20, PAIRS[:, 1]], axis=0))).mean()
    jump_out = np.degrees(np.abs(np.diff(out[:20, PAIRS[:, 1]], axis=0))).mean()
    assert jump_out < 0.1 * jump_in, (jump_in, jump_out)
    # the PIPs the markers see stay
    np.testing.assert_allclose(np.delete(out, 20, axis=0)[:, PAIRS[:, 0]], -1.2, atol=1e-3)


def test_joint_centre_exports_get_no_dip_prior():
    """Joint centres at the PIP and DIP and a fingertip fix each DIP by geometry: the prior has
    nothing to decide and must not bend a measured angle (it cost ART's real recording 1.58 →
    1.60 mm); skin-marker sets keep it."""
    from synergy.angles import markers_to_angles
    from synergy.ik_priors import dip_fixed_fingers
    from synergy.markers import load_markerset
    from synergy.simulate import motion, simulate_markers

    assert dip_fixed_fingers(load_markerset("art-joint-centres")) == {"index", "middle", "ring", "pinky"}
    assert dip_fixed_fingers(load_markerset("hand16")) == set() == dip_fixed_fingers(load_markerset("hand19"))
    assert len(ip_coupling_pairs(HAND, {"index", "ring"})) == 2 and ip_coupling_pairs(HAND, set(PAIRS_FINGERS)).shape == (0, 2)
    th, _ = motion("power_grasp", duration_s=0.4, seed=3)
    for name, equal in (("art-joint-centres", True), ("hand16", False)):
        tr = simulate_markers(th, name, noise_mm=0.5, seed=1)
        on = markers_to_angles(tr, name, calibration=None, check_hand=None)
        off = markers_to_angles(tr, name, calibration=None, check_hand=None, ip_coupling_sd_deg=None)
        diff = np.abs(on[HAND.dof_names].to_numpy() - off[HAND.dof_names].to_numpy()).max()
        assert (diff == 0.0) if equal else (diff > 1e-4), (name, diff)


PAIRS_FINGERS = ("index", "middle", "ring", "pinky")
