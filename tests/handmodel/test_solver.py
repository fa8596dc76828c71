"""The shared solver: Jacobians vs finite differences, keypoint fits, subspaces and schedules."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from handmodel import HandModel, SolverError
from handmodel.rigid import euler_to_matrix, horn, matrix_to_euler
from handmodel.solver import SolverSettings, fit_keypoints, solve
from handmodel.subspace import Subspace, hierarchical_schedule

HAND = HandModel.load()


def random_postures(rng, n, hand=HAND, margin=0.02):
    lim = hand.limits
    th = np.zeros((n, hand.n_dofs))
    th[:, 6:] = rng.uniform(lim[6:, 0] + margin, lim[6:, 1] - margin, size=(n, hand.n_dofs - 6))
    th[:, :3] = rng.normal(0, 0.05, (n, 3)) + [0, 0, 0.7]
    th[:, 3:6] = rng.uniform(-np.pi / 2, np.pi / 2, (n, 3))
    return th


def posture_error_deg(a, b):
    return np.degrees(np.abs(np.asarray(a)[..., 6:] - np.asarray(b)[..., 6:])).mean(-1)


@given(st.integers(0, 2**31 - 1), st.booleans())
@settings(max_examples=30, deadline=None)
def test_jacobian_matches_central_differences(seed, right):
    hand = HandModel.load(right=right)
    rng = np.random.default_rng(seed)
    th = random_postures(rng, 1, hand)[0]
    nodes = rng.integers(0, hand.n_nodes, 8)
    local = rng.normal(0, 0.01, (8, 3))
    J = hand.jacobian(th, nodes, local)
    h = 1e-6
    num = np.empty_like(J)
    for d in range(hand.n_dofs):
        e = np.zeros(hand.n_dofs)
        e[d] = h
        num[:, :, d] = (hand.points(th + e, nodes, local) - hand.points(th - e, nodes, local)) / (2 * h)
    scale = np.abs(num).max()
    assert np.abs(J - num).max() <= 1e-6 * scale
    # keypoint Jacobian (no offsets) is the default
    Jk = hand.jacobian(th)
    assert Jk.shape == (21, 3, 26)
    assert np.all(Jk[0, :, 6:] == 0)  # the wrist does not move with the fingers


def test_fit_keypoints_exact_from_flat_hand():
    rng = np.random.default_rng(1)
    truth = random_postures(rng, 200)
    est, rep = fit_keypoints(HAND, HAND.keypoints(truth))
    err = posture_error_deg(est, truth)
    assert err.mean() <= 0.01, err.mean()
    assert np.median(rep.rms_mm) < 1e-3
    assert rep.iterations.min() >= 1


def _observable(kp_present):
    """Posture DoFs fixed by the visible keypoints: a joint's DoFs are observable when the joint's
    own keypoint and the next one down the chain are both visible."""
    obs = np.zeros(20, bool)
    for f in range(5):
        base = 1 + 4 * f
        chain = kp_present[base:base + 4]
        ok1 = chain[0] and chain[1]
        obs[4 * f:4 * f + 2] = ok1                  # abduction + flexion of joint 1
        obs[4 * f + 2] = chain[1] and chain[2]      # joint 2 flexion
        obs[4 * f + 3] = chain[2] and chain[3]      # joint 3 flexion
    return obs


def test_fit_keypoints_with_missing_keypoints():
    rng = np.random.default_rng(2)
    truth = random_postures(rng, 100)
    kp = HAND.keypoints(truth)
    for f in range(len(kp)):  # 30 % of the keypoints missing (6 of 21), any of them
        kp[f, rng.choice(21, size=6, replace=False)] = np.nan
    est, rep = fit_keypoints(HAND, kp)
    assert np.all(np.isfinite(est))
    # converged: the visible keypoints are reached
    fitted = HAND.keypoints(est)
    vis = ~np.isnan(kp[..., 0])
    dist_mm = np.linalg.norm(fitted - np.nan_to_num(kp), axis=-1)[vis] * 1000
    assert np.median(dist_mm) < 0.05 and np.mean(dist_mm < 0.5) > 0.95
    # the DoFs the visible keypoints determine are recovered
    errs = [np.degrees(np.abs(e[6:] - t[6:]))[_observable(v)] for e, t, v in zip(est, truth, vis)]
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.01 and np.mean(errs) < 1.0, (np.median(errs), np.mean(errs))


def _crb_mean_abs_error_deg(truth, sigma):
    """Linearised Cramér-Rao bound: expected mean |posture error| of any unbiased estimator."""
    out = []
    for th in truth:
        J = HAND.jacobian(th).reshape(-1, 26)
        sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J))[6:]) * sigma
        out.append(np.degrees(sd * np.sqrt(2 / np.pi)).mean())
    return np.mean(out)


def test_fit_keypoints_with_noise_is_efficient():
    """2 mm keypoint noise: our error equals the Cramér-Rao bound of the problem (not more).

    On the default hand's short distal bones (10–13 mm) 2 mm per-axis noise alone implies a mean
    posture error near 7° for postures drawn uniformly inside the limits."""
    rng = np.random.default_rng(3)
    truth = random_postures(rng, 200)
    kp = HAND.keypoints(truth) + rng.normal(0, 0.002, (200, 21, 3))
    est, rep = fit_keypoints(HAND, kp)
    err = posture_error_deg(est, truth).mean()
    bound = _crb_mean_abs_error_deg(truth[:60], 0.002)
    print(f"\n2 mm noise, uniform postures: mean posture error {err:.2f} deg, Cramer-Rao bound {bound:.2f} deg")
    assert err <= 1.05 * bound
    assert 1.5 < np.median(rep.rms_mm) < 3.5


def test_fit_keypoints_with_half_mm_noise():
    rng = np.random.default_rng(9)
    truth = random_postures(rng, 200)
    est, _ = fit_keypoints(HAND, HAND.keypoints(truth) + rng.normal(0, 0.0005, (200, 21, 3)))
    assert posture_error_deg(est, truth).mean() <= 2.0


def test_warm_start_sequence_matches_truth():
    rng = np.random.default_rng(4)
    a, b = random_postures(rng, 2)
    b[:6] = a[:6]
    t = np.linspace(0, 1, 50)[:, None]
    truth = (1 - t) * a + t * b
    est, rep = fit_keypoints(HAND, HAND.keypoints(truth), theta0=truth[0], warm_start=True,
                             settings=SolverSettings(iterations=10))
    assert posture_error_deg(est, truth).max() < 0.01


def test_energy_decreases_monotonically():
    rng = np.random.default_rng(5)
    truth = random_postures(rng, 20)
    _, rep = fit_keypoints(HAND, HAND.keypoints(truth) + rng.normal(0, 0.003, (20, 21, 3)))
    for tr in rep.trace:
        t = tr[~np.isnan(tr)]
        assert np.all(np.diff(t) < 0)


def test_limits_clamp_and_report():
    # targets from a hyperextended posture beyond the model's limits: the fit stays inside
    th = np.zeros(26)
    th[2] = 0.7
    th[12] = 0.6  # index1_flex far above the 0.1 limit
    est, rep = fit_keypoints(HAND, HAND.keypoints(th))
    assert est[12] <= HAND.limits[12, 1] + 1e-12
    assert rep.at_limit[0, 12]
    free = SolverSettings(iterations=30, clamp=False, joint_limit_avoidance=False)
    est2, _ = fit_keypoints(HAND, HAND.keypoints(th), subspace=Subspace.full(HAND, np.c_[np.full(26, -np.inf), np.full(26, np.inf)]),
                            settings=free)
    assert abs(est2[12] - 0.6) < 1e-5


def _fingerfist_pca(ff):
    X = ff[:, 6:]
    mu = X.mean(0)
    U, s, Vt = np.linalg.svd(X - mu, full_matrices=False)
    proj = (X - mu) @ Vt.T
    return Vt, mu, proj.min(0), proj.max(0)


def test_subspace_maps_and_fit_stays_in_subspace(fingerfist):
    C, mu, lo, hi = _fingerfist_pca(fingerfist)
    sp = Subspace.from_synergies(HAND, C, mu, lo, hi, n_components=5)
    assert sp.dim == 11
    th = np.zeros(26)
    th[6:] = fingerfist[100, 6:]
    a = sp.to_alpha(th)
    th = sp.to_theta(a)
    np.testing.assert_allclose(sp.to_alpha(sp.to_theta(a)), a, atol=1e-12)
    # J_PC = J M equals the finite-difference Jacobian with respect to α
    J = HAND.jacobian(th).reshape(-1, 26)
    Jpc = sp.jacobian(J)
    h = 1e-6
    num = np.stack([(HAND.keypoints(sp.to_theta(a + h * e)) - HAND.keypoints(sp.to_theta(a - h * e))).ravel() / (2 * h)
                    for e in np.eye(sp.dim)], 1)
    np.testing.assert_allclose(Jpc, num, atol=1e-7)
    truth = np.zeros((30, 26))
    truth[:, 6:] = fingerfist[::200, 6:]
    truth[:, 2] = 0.7
    est, _ = fit_keypoints(HAND, HAND.keypoints(truth), subspace=sp)
    # inside the subspace: projection changes nothing, PC limits hold
    np.testing.assert_allclose(sp.project(est), est, atol=1e-10)
    alpha = sp.to_alpha(est)[:, 6:]
    assert np.all(alpha >= lo[:5] - 1e-9) and np.all(alpha <= hi[:5] + 1e-9)


@pytest.mark.parametrize("limit_avoidance", [False, True])
def test_steps_at_pc_limits_reach_the_bounded_optimum(fingerfist, limit_avoidance):
    """Postures outside a tight PC box: the solve must reach the box-constrained least-squares optimum
    (scipy's bounded ``least_squares`` as the peer). A step that clamps a coordinate pushed against
    its limit after solving for all of them fails to lower the energy at any length and stops the
    solve at 1–4 iterations with 2–4× the optimal energy; with the active set (coordinates at a
    limit and pushed outwards frozen for the step) it does not."""
    from scipy.optimize import least_squares

    C, mu, lo, hi = _fingerfist_pca(fingerfist)
    sp = Subspace.from_synergies(HAND, C, mu, 0.3 * lo, 0.3 * hi, n_components=5)
    truth = np.zeros((12, 26))
    truth[:, 6:] = fingerfist[::500, 6:]
    truth[:, 2] = 0.7
    start = sp.to_theta(np.r_[0, 0, 0.7, np.zeros(3 + 5)])
    tg = HAND.keypoints(truth)
    est, rep = solve(HAND, start, np.arange(21), np.zeros((21, 3)), tg, subspace=sp,
                     settings=SolverSettings(iterations=40, damping=0.01, joint_limit_avoidance=limit_avoidance))
    a0 = np.clip(sp.to_alpha(start), sp.lo + 1e-6, sp.hi - 1e-6)
    at_limit = 0
    for f in range(len(tg)):
        peer = least_squares(lambda a, t=tg[f]: (HAND.keypoints(sp.to_theta(a)) - t).ravel() * 1000.0, a0,
                             bounds=(sp.lo, sp.hi), method="trf", xtol=1e-14, ftol=1e-14, gtol=1e-14, max_nfev=2000)
        assert rep.energy[f] <= 1.01 * peer.cost + 1e-9
        a = sp.to_alpha(est[f])
        at_limit += int(np.any((a - sp.lo < 1e-3) | (sp.hi - a < 1e-3)))
    assert at_limit >= len(tg) // 2  # the limits were in play


def test_flat_vs_hierarchical_on_fingerfist(fingerfist):
    """100 fingerfist postures from the flat hand: the hierarchical schedule must not be worse."""
    C, mu, lo, hi = _fingerfist_pca(fingerfist)
    rng = np.random.default_rng(6)
    rows = rng.choice(len(fingerfist), 100, replace=False)
    truth = np.zeros((100, 26))
    truth[:, 6:] = fingerfist[rows, 6:]
    truth[:, 2] = 0.7
    truth[:, 3:6] = rng.uniform(-0.5, 0.5, (100, 3))
    kp = HAND.keypoints(truth)
    # data-derived joint limits, as the original tracker sets them when PCA is on
    lim = HAND.limits.copy()
    lim[6:, 0] = fingerfist[:, 6:].min(0)
    lim[6:, 1] = fingerfist[:, 6:].max(0)
    full = Subspace.full(HAND, lim)
    flat0 = np.tile(HAND.zero(), (100, 1))
    from handmodel.solver import rigid_pose_from_keypoints

    flat0 = rigid_pose_from_keypoints(HAND, kp)
    st_ = SolverSettings(iterations=10)
    est_flat, _ = fit_keypoints(HAND, kp, theta0=flat0, subspace=full, settings=st_)
    sched = hierarchical_schedule(HAND, C, mu, lo, hi, steps=(1, 4), n_pcs=4, full_limits=lim)
    assert [sp.dim for sp in sched] == [7, 10, 26]
    est_h, _ = fit_keypoints(HAND, kp, theta0=flat0, schedule=sched, settings=st_)
    e_flat = posture_error_deg(est_flat, truth).mean()
    e_h = posture_error_deg(est_h, truth).mean()
    print(f"\nfingerfist, 100 postures from the flat hand: flat {e_flat:.4f} deg, hierarchical {e_h:.4f} deg")
    assert e_h <= e_flat + 1e-6
    assert e_h < 0.5


def test_hierarchical_schedule_stages(fingerfist):
    """The stages the tracker runs: coarse PC steps below n_pcs, PC(n_pcs), then all DoF with given limits."""
    C, mu, lo, hi = _fingerfist_pca(fingerfist)
    lim = HAND.limits.copy()
    lim[6:] = [-2.0, 1.0]
    sched = hierarchical_schedule(HAND, C, mu, lo, hi, steps=(4, 1, 9, 4), n_pcs=6, full_limits=lim)
    assert [sp.dim for sp in sched] == [7, 10, 12, 26]
    for sp, k in zip(sched[:3], (1, 4, 6)):
        np.testing.assert_array_equal(sp.M[6:, 6:], C[:k].T)
        np.testing.assert_array_equal(sp.lo[6:], lo[:k])
        np.testing.assert_array_equal(sp.hi[6:], hi[:k])
        np.testing.assert_array_equal(sp.mu[6:], mu)
    assert sched[-1].is_identity and np.array_equal(sched[-1].lo, lim[:, 0])
    assert [sp.dim for sp in hierarchical_schedule(HAND, C[:3], mu, steps=(1, 4))] == [7, 9, 26]
    assert [sp.dim for sp in hierarchical_schedule(HAND, C, mu, steps=(), n_pcs=1)] == [7, 26]
    for bad in ({"n_pcs": 0}, {"n_pcs": 21}, {"steps": (0, 2)}):
        with pytest.raises(SolverError, match="schedule"):
            hierarchical_schedule(HAND, C, mu, **bad)


def test_point_to_plane_terms_converge():
    rng = np.random.default_rng(7)
    truth = random_postures(rng, 1)[0]
    th0 = truth.copy()
    th0[6:] += rng.normal(0, 0.05, 20)
    nodes = np.repeat(np.arange(21), 6)
    local = rng.normal(0, 0.004, (len(nodes), 3))
    tg = HAND.points(truth, nodes, local)
    nrm = rng.normal(size=tg.shape)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    est, rep = solve(HAND, th0, nodes, local, tg, normals=nrm, settings=SolverSettings(iterations=40))
    assert rep.rms_mm[0] < 1e-3
    assert posture_error_deg(est, truth) < 0.05


def test_solver_input_errors():
    with pytest.raises(SolverError, match="targets"):
        fit_keypoints(HAND, np.zeros((20, 3)))
    # a frame without enough keypoints is not solved: NaN θ, iterations −1 (a batch never crashes)
    kp = HAND.keypoints(np.zeros((3, 26)))
    kp[1, 2:] = np.nan
    th, rep = fit_keypoints(HAND, kp)
    assert np.all(np.isnan(th[1])) and rep.iterations[1] == -1 and np.all(np.isfinite(th[[0, 2]]))
    with pytest.raises(SolverError, match="correspondences"):
        solve(HAND, HAND.zero(), [0, 1], np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(SolverError, match="weights"):
        solve(HAND, HAND.zero(), [0], np.zeros((1, 3)), np.zeros((1, 3)), weights=[-1.0])
    from handmodel import HandModelError

    with pytest.raises(HandModelError, match="NaN"):
        solve(HAND, np.full(26, np.nan), [0], np.zeros((1, 3)), np.zeros((1, 3)))


@given(st.lists(st.floats(-3, 3), min_size=3, max_size=3), st.integers(0, 1000))
@settings(max_examples=50, deadline=None)
def test_horn_recovers_rigid_transform(angles, seed):
    rng = np.random.default_rng(seed)
    R0 = euler_to_matrix(np.array(angles))
    t0 = rng.normal(size=3)
    p = rng.normal(size=(6, 3))
    R, t = horn(p, p @ R0.T + t0)
    np.testing.assert_allclose(R, R0, atol=1e-9)
    np.testing.assert_allclose(t, t0, atol=1e-9)
    np.testing.assert_allclose(euler_to_matrix(matrix_to_euler(R0)), R0, atol=1e-9)
