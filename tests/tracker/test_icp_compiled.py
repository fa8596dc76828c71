"""The compiled ICP loop (tracker.icp.fit) against the Python loop kept as the reference
(tracker.icp.fit_reference), its moment-sum Gauss-Newton against the per-pair solver kernels, and the
pruned closest-point search against an exhaustive one."""
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from handmodel import HandModel
from handmodel import _geometry_kernels as GK
from handmodel import _solver_kernels as SK
from tracker import _fit_kernels as K
from tracker._kernel_arrays import HandArrays
from tracker._search_kernels import pairwise_sum
from tracker._silhouette_kernels import feature_transform
from tracker.correspond import CorrespondSettings, Matcher, Silhouette, local_offsets
from tracker.icp import IcpSettings, cauchy_weights, fit, fit_reference, search_schedule
from tracker.icp_settings import KeypointTermSettings
from tracker.observe import observe
from tracker.sim import experiments as E
from tracker.sim.render import DepthRenderer
from tracker.parts import usable_points
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
# Kinect v1 intrinsics (the tests do not depend on the camera-preset module)
CAM = SimpleNamespace(width=640, height=480, fx=575.8, fy=575.8, cx=319.5, cy=239.5, name="kinect1")


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.fixture(scope="module")
def frames(bundle):
    """Rendered frames of postures along the first synergies (truth, observation, silhouette) and, per
    frame, a start like a tracker's: the previous frame's truth."""
    model = bundle.model
    rng = np.random.default_rng(3)
    C = model.all_components_[:4]
    a = rng.uniform(-1.0, 1.0, (7, 4)) * np.sqrt(np.maximum(model.all_explained_variance_[:4], 1e-6))
    post = np.clip(model.mean_ + a @ C, HAND.limits[6:, 0], HAND.limits[6:, 1])
    truth = E.sequence(post, model.mean_, lead=2)
    ren = DepthRenderer(HAND, CAM)
    out = []
    for f in range(1, len(truth)):
        ob = observe(ren.render(truth[f], labels=False).depth, CAM, TrackerSettings.paper().observe)
        pts, nrm = usable_points(ob.points, ob.normals, 0)
        out.append((truth[f - 1], pts, nrm, Silhouette(ob.mask, ob.depth, CAM)))
    return out


def _tracker(bundle, ours, **kw):
    base = TrackerSettings().replace(scale=dict(hand_scale=1.0)) if ours else TrackerSettings.paper()
    return FrameTracker(HAND, base.replace(**kw), synergies=bundle)


def _both(tr, start, pts, nrm, sil, stages=None, **kw):
    ctx = tr.context
    args = (HAND, pts, start, tr.stages if stages is None else stages, ctx.matcher, tr.settings.icp)
    kw = dict(n_rigid=tr.settings.icp.rigid_iterations, normals=nrm, samples=ctx.samples, silhouette=sil, **kw)
    return fit_reference(*args, **kw), fit(*args, **kw), fit(*args, moments=False, **kw)


def _one(fitter, tr, theta, pts, nrm, sil, stages, n_rigid=0, **kw):
    ctx = tr.context
    return fitter(HAND, pts, theta, stages, ctx.matcher, tr.settings.icp, n_rigid=n_rigid, normals=nrm,
                  samples=ctx.samples, silhouette=sil, **kw)[0]


def _check_stage_by_stage(tr, start, pts, nrm, sil, stages, **kw):
    """Each step of the loop (the rigid steps, then every stage) from the reference's θ before it:
    the compiled step gives the reference's θ (moment sums to 2e-6, per pair to 2e-7: step halving
    amplifies round-off), unless the reference itself jumps when that θ moves by round-off
    (1e-15..1e-13: a coordinate at a PC limit switches Chan–Dubey damping on or off, a step is
    taken or not), which no reimplementation can follow bit for bit. Returns the number of such steps."""
    edges = 0
    theta = start
    steps = [([], tr.settings.icp.rigid_iterations)] + [([st], 0) for st in stages]
    for sts, n_rigid in steps:
        ref = _one(fit_reference, tr, theta, pts, nrm, sil, sts, n_rigid, **kw)
        mom = _one(fit, tr, theta, pts, nrm, sil, sts, n_rigid, **kw)
        pair = _one(fit, tr, theta, pts, nrm, sil, sts, n_rigid, moments=False, **kw)
        if np.abs(mom - ref).max() > 2e-6 or np.abs(pair - ref).max() > 2e-7:
            jumps = [np.abs(_one(fit_reference, tr, theta + eps, pts, nrm, sil, sts, n_rigid, **kw) - ref).max()
                     for eps in (1e-15, -1e-15, 1e-13, -1e-13)]
            assert max(jumps) > 1e-4, "compiled and reference fits differ"
            edges += 1
        theta = ref
    return edges


@pytest.mark.parametrize("mode,ours,extra", [("full", True, {}), ("full", False, {}), ("reduced", True, {}),
                                             ("reduced", False, {}), ("reduced", True, {"icp": {"projected_steps": 2}}),
                                             ("hierarchical", True, {}), ("full", True, {"icp": {"point_to_plane": True}})])
def test_compiled_loop_gives_the_reference_result(bundle, frames, mode, ours, extra):
    """Every mode and stage entry (clamp, through, projected steps), both estimations, point-to-plane:
    the whole fit gives the reference's θ and correspondences on (nearly) every frame, and every
    step of it does (see :func:`_check_stage_by_stage`)."""
    tr = _tracker(bundle, ours, mode=mode, **extra)
    moved, same, edges = 0.0, 0, 0
    for start, pts, nrm, sil in frames:
        (t_ref, c_ref), (t_mom, c_mom), (t_pair, c_pair) = _both(tr, start, pts, nrm, sil)
        moved = max(moved, np.abs(t_ref - start).max())
        edges += _check_stage_by_stage(tr, start, pts, nrm, sil, tr.stages)
        if np.abs(t_mom - t_ref).max() > 2e-6 or np.abs(t_pair - t_ref).max() > 2e-7:
            continue
        same += 1
        for c in (c_mom, c_pair):
            assert (c.valid == c_ref.valid).all()
            assert (c.nodes[c.valid] == c_ref.nodes[c_ref.valid]).all()
            np.testing.assert_allclose(c.distance[c.valid], c_ref.distance[c_ref.valid], atol=1e-8)
    assert same >= len(frames) - 1 and edges <= 1
    assert moved > 1e-3  # the fits did move θ: equal results are not just the start returned


def test_search_schedules_match_the_reference(bundle, frames):
    """The start search's schedules: the hierarchical ladder clamped and through θ, several rigid steps."""
    tr = _tracker(bundle, True)
    ctx = tr.context
    start, pts, nrm, sil = frames[2]
    flat = start.copy()
    flat[6:] = bundle.model.mean_
    for through in (False, True):
        stages = search_schedule("hierarchical", 6, ctx.full, ctx.reduced, ctx.ladder, through=through)
        assert {s.entry for s in stages} >= {"none", "through" if through else "clamp"}
        assert _check_stage_by_stage(tr, flat, pts, nrm, sil, stages) <= 1


@pytest.mark.parametrize("ours", [True, False])
def test_reduced_steps_do_not_fail_at_the_pc_limits(bundle, frames, ours):
    """Reduced tracking fits postures pressed against the PC limits. Clamping a step solved for every
    coordinate made it fail to lower the energy at any length (10 halvings, then the stage stopped),
    and so did every step at convergence: on these frames 7 (ours) and 9 (the paper's estimation)
    times. With the active set at the limits, and the stage ending when a step could not gain more
    than round-off, no step is wasted that way."""
    tr = _tracker(bundle, ours, mode="reduced")
    ctx = tr.context
    stats = np.zeros(5, np.int64)
    for start, pts, nrm, sil in frames:
        fit(HAND, pts, start, tr.stages, ctx.matcher, tr.settings.icp, n_rigid=1, normals=nrm, samples=ctx.samples,
            silhouette=sil, stats=stats)
    assert stats[0] >= 2 * len(frames) and stats[1] == 0 and stats[2] >= stats[0]


def test_other_matchers_take_the_reference_loop(frames):
    """A matcher the compiled loop does not know (the mesh surface) gets exactly the Python loop."""
    from handmodel.subspace import Subspace
    from tracker.icp import Stage

    start, pts, nrm, _ = frames[0]
    matcher = Matcher(HAND, CorrespondSettings(model="mesh"))
    stages = [Stage(Subspace.full(HAND))] * 2
    a, ca = fit_reference(HAND, pts, start, stages, matcher, IcpSettings(), n_rigid=1, normals=nrm)
    b, cb = fit(HAND, pts, start, stages, matcher, IcpSettings(), n_rigid=1, normals=nrm)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(ca.valid, cb.valid)


def test_moment_sums_give_the_per_pair_energy_and_normal_equations(bundle, frames):
    """At poses away from the reference frames (where the pairs were fixed), the energy and JᵀW²J,
    JᵀW²e from the per-node moments equal the per-pair kernels' to round-off — including the model's
    rest frames being orthonormal to 1e-6 only, which a rotation-invariant shortcut would get wrong."""
    tr = _tracker(bundle, True)
    start, pts, nrm, _ = frames[1]
    c = tr.context.matcher(start, pts, nrm)
    v = c.valid
    nodes, tg = c.nodes[v], pts[v]
    loc = local_offsets(HAND, start, nodes, c.model[v])
    w = cauchy_weights(c.distance[v], 8.0)
    n, N = HAND.n_dofs, HAND.n_nodes
    G0 = HAND.node_frames(start)
    mom = np.zeros((N, K.N_MOMENTS))
    K.node_moments(nodes, loc, tg, w, G0, N, mom)
    rng = np.random.default_rng(0)
    G, wa, wo = np.empty((N, 4, 4)), np.empty((n, 3)), np.empty((n, 3))
    for scale in (0.0, 0.02, 0.2):
        th = start + rng.normal(scale=scale, size=n)
        A, b = np.empty((n, n)), np.empty(n)
        e_pair = SK.normal_equations(th, *HAND.kernel_args(), nodes, loc, tg, w, np.zeros((0, 3)), G, wa, wo, A, b,
                                     np.empty((n, 3)), np.empty(n, np.int64), np.empty(3), np.empty(3))
        A2, b2 = np.empty((n, n)), np.empty(n)
        e_mom = K.moment_normal_equations(HandArrays.of(HAND), mom, G0, G, wa, wo, A2, b2, np.empty(n, np.int64),
                                          np.empty((n, 3)), np.empty((n, 3)))
        e_at = K.moment_energy_at(th, HandArrays.of(HAND), mom, G0, G, wa, wo, np.empty((3, 3)), np.empty(3))
        assert e_pair > 1.0
        assert abs(e_mom - e_pair) <= 1e-10 * e_pair and abs(e_at - e_pair) <= 1e-10 * e_pair
        np.testing.assert_allclose(A2, A, rtol=0, atol=1e-10 * np.abs(A).max())
        np.testing.assert_allclose(b2, b, rtol=0, atol=1e-10 * np.abs(b).max())
    # projected onto the synergy subspace through its non-zeros = MᵀAM, Mᵀb
    M = tr.context.reduced.M
    m = M.shape[1]
    nz = [np.flatnonzero(M[:, c]) for c in range(m)]
    ptr = np.r_[0, np.cumsum([len(z) for z in nz])].astype(np.int64)
    rows = np.concatenate(nz).astype(np.int64)
    vals = np.concatenate([M[z, c] for c, z in enumerate(nz)])
    Aa, ba = np.empty((m, m)), np.empty(m)
    K.project_normal_equations(A, b, False, ptr, rows, vals, Aa, ba, np.empty((m, n)))
    np.testing.assert_allclose(Aa, M.T @ A @ M, rtol=1e-12, atol=1e-9 * np.abs(A).max())
    np.testing.assert_allclose(ba, M.T @ b, rtol=1e-12, atol=1e-9 * np.abs(b).max())


def _exhaustive(G, caps, points, facing, signed):
    """Every primitive for every point: the smallest (signed or absolute) distance among the
    candidates facing the camera at the origin, ties to the lowest index."""
    seg_node, shape, length, r0, r1, th = caps
    P = len(points)
    best, seg = np.full(P, np.inf), np.full(P, -1)
    loc = np.empty(7)
    for i, p in enumerate(points):
        for s in range(len(seg_node)):
            g = G[seg_node[s]]
            GK.closest_local(shape[s], length[s], r0[s], r1[s], th[s], g[:3, :3].T @ (p - g[:3, 3]), loc)
            d = loc[6] if signed else abs(loc[6])
            wp, wn = g[:3, :3] @ loc[:3] + g[:3, 3], g[:3, :3] @ loc[3:6]
            if facing and wp @ wn > 0:
                continue
            if d < best[i]:
                best[i], seg[i] = d, s
    return seg, best


def _posed_points(rng, n, spread):
    """``(node frames, points)``: the hand at a random pose and posture within limits 0.7 m away, and ``n``
    points about its keypoints (Gaussian, SD ``spread`` m)."""
    theta = HAND.zero()
    theta[2] = 0.7
    theta[3:6] = rng.normal(size=3)
    theta[6:] = rng.uniform(HAND.limits[6:, 0], HAND.limits[6:, 1])
    pts = HAND.keypoints(theta)[rng.integers(0, 21, n)] + rng.normal(scale=spread, size=(n, 3))
    return HAND.node_frames(theta), pts


@pytest.mark.parametrize("spread", [0.005, 0.03, 0.2])
def test_pruned_closest_points_equal_the_exhaustive_search(spread):
    """Bounding-sphere pruning and the warm start change nothing: same segment, same distance, for
    points on, near and far from the hand, inside it too (signed), in the order a scan gives them
    and shuffled."""
    rng = np.random.default_rng(int(spread * 1000))
    caps = HAND.capsules.kernel_args()
    for k in range(4):
        G, pts = _posed_points(rng, 150, spread)
        if k % 2:
            pts = pts[np.argsort(pts[:, 0])]  # scan-like order: neighbours share their winner
        P = len(pts)
        for facing, signed in ((True, False), (False, False), (False, True)):
            out = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
            if signed:
                GK.closest_points(G, *caps, pts, *out)
            else:
                GK.closest_points_facing(G, *caps, pts, np.zeros(3), facing, *out)
            seg, best = _exhaustive(G, caps, pts, facing, signed)
            np.testing.assert_array_equal(out[2], seg)
            found = seg >= 0
            np.testing.assert_allclose(out[3][found], best[found], rtol=0, atol=1e-12)
            assert found.mean() > 0.3


@pytest.mark.parametrize("spread", [0.005, 0.03, 0.2])
def test_one_search_for_the_fit_s_pass_and_the_score_s_distances_is_the_two_searches(spread):
    """:func:`tracker._fit_kernels.closest_pass_and_any` (the batched fits' last pass and the score's data
    term in one search) gives the facing pass's points, normals, segments and distances and the any-side
    search's distances to the bit, with ``facing_only`` on and off, in scan order and shuffled."""
    from tracker._kernel_arrays import CapsuleArrays

    rng = np.random.default_rng(int(spread * 1000) + 1)
    caps = HAND.capsules.kernel_args()
    for k in range(4):
        G, pts = _posed_points(rng, 200, spread)
        if k % 2:
            pts = pts[np.argsort(pts[:, 0])]
        P = len(pts)
        cam = np.array([0.0, 0.0, -0.05 * k])
        for facing in (True, False):
            lone = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
            GK.closest_points_facing(G, *caps, pts, cam, facing, *lone)
            lone_any = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
            GK.closest_points_facing(G, *caps, pts, np.zeros(3), False, *lone_any)
            both = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
            any_d = np.empty(P)
            K.closest_pass_and_any(G, CapsuleArrays(*caps), pts, cam, facing, *both, any_d)
            for a, b in zip(both, lone):
                np.testing.assert_array_equal(a, b)
            np.testing.assert_array_equal(any_d, lone_any[3])
            if facing:
                assert (lone[3] != lone_any[3]).any()  # some point's nearest surface faces away


def test_posed_samples_and_centre_shift_are_the_numpy_ones(bundle):
    """The compiled posing of the model samples is ModelSamples.pose (to round-off), and the
    re-centring's shift is the numpy medians' (bit for bit); too few facing samples give None."""
    from tracker.icp import centre_shift, posed_samples

    tr = _tracker(bundle, True)
    samples = tr.context.score_samples
    rng = np.random.default_rng(2)
    for _ in range(10):
        th = np.clip(rng.normal(0, 0.4, HAND.n_dofs), HAND.limits[:, 0], HAND.limits[:, 1])
        th[:3] = rng.normal(0, 0.05, 3) + [0, 0, 0.7]
        P, N = posed_samples(HAND, samples, th)
        P0, N0 = samples.pose(th)
        np.testing.assert_allclose(P, P0, rtol=0, atol=1e-15)
        np.testing.assert_allclose(N, N0, rtol=0, atol=1e-15)
        pts = P0[rng.choice(len(P0), 201, replace=False)] + rng.normal(0, 0.01, (201, 3))
        facing = np.einsum("ij,ij->i", N, P) < 0
        want = np.median(pts, axis=0) - np.median(P[facing], axis=0)
        np.testing.assert_array_equal(centre_shift(pts, (P, N)), want)
    # a hand seen from behind everywhere: nothing faces the camera
    assert centre_shift(pts, (P, np.abs(N) * np.sign(P))) is None


def test_feature_transform_is_scipys():
    """The compiled distance transform of the silhouette gives scipy's distances bit for bit, and its
    nearest mask pixel is at that distance (scipy may name another of equally near ones), on masks
    from a single pixel to nearly full, one row or column wide; an empty mask is reported."""
    from scipy import ndimage

    rng = np.random.default_rng(4)
    for _ in range(300):
        H, W = rng.integers(1, 50, 2)
        m = rng.random((H, W)) < rng.choice([0.002, 0.03, 0.3, 0.95])
        m[rng.integers(H), rng.integers(W)] = True
        want = ndimage.distance_transform_edt(~m)
        d, iv, iu = np.empty((H, W)), np.empty((H, W), np.int32), np.empty((H, W), np.int32)
        assert feature_transform(m, d, iv, iu)
        np.testing.assert_array_equal(d, want)
        assert m[iv, iu].all()
        np.testing.assert_array_equal(np.sqrt((iv - np.arange(H)[:, None]) ** 2.0 + (iu - np.arange(W)) ** 2.0), d)
    assert not feature_transform(np.zeros((3, 4), bool), d, iv, iu)


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 24), st.integers(1, 24), st.sampled_from([0.01, 0.05, 0.3, 0.9]), st.integers(0, 2**32 - 1))
def test_feature_transform_names_the_leftmost_then_upmost_of_equally_near_pixels(h, w, share, seed):
    """Against a brute force over every mask pixel: the distance, and of equally near mask pixels the
    one of the smallest column, then of the smallest row (the tracker's silhouette pairs and the net's
    arm entry read these pixels: another tie rule changes the tracked θ). Ties are common on small
    integer grids; a transform naming the right-hand one of two equally near pixels fails."""
    rng = np.random.default_rng(seed)
    m = rng.random((h, w)) < share
    m[rng.integers(h), rng.integers(w)] = True
    mv, mu = np.nonzero(m)
    V, U = np.mgrid[:h, :w]
    d2 = (V[..., None] - mv) ** 2 + (U[..., None] - mu) ** 2
    best = d2.min(-1)
    first = np.where(d2 == best[..., None], mu * (h + 1) + mv, np.iinfo(np.int64).max).argmin(-1)
    d, iv, iu = np.empty((h, w)), np.empty((h, w), np.int32), np.empty((h, w), np.int32)
    assert feature_transform(m, d, iv, iu)
    np.testing.assert_array_equal(d, np.sqrt(best.astype(float)))
    np.testing.assert_array_equal(iv, mv[first])
    np.testing.assert_array_equal(iu, mu[first])


def test_silhouette_matches_scipys_transform(frames):
    """A tracked frame's Silhouette holds scipy's distances and the same nearest pixels (no ties on a
    rendered hand's mask), so the silhouette pairs do not change."""
    from scipy import ndimage

    for _, _, _, sil in frames[:3]:
        sub = sil.mask[sil.v0:sil.v0 + sil.dist.shape[0], sil.u0:sil.u0 + sil.dist.shape[1]]
        d, (iv, iu) = ndimage.distance_transform_edt(~sub, return_indices=True)
        np.testing.assert_array_equal(sil.dist, d)
        assert (sil.iv == iv).mean() > 0.99 and (sil.iu == iu).mean() > 0.99


def test_model_to_data_mean_is_the_numpy_score_term(bundle, frames):
    """The compiled model→data mean (the safety net's per-frame score term) equals the mean of
    tracker.correspond.model_to_data_mm to 1e-13 relative, for hands on, beside, turned against and
    behind the camera (samples outside the silhouette, in front of the surface, behind it; every
    branch of the cost), and the cap for an empty silhouette."""
    from tracker.correspond import model_to_data_mm
    from tracker.icp import model_to_data_mean

    samples = _tracker(bundle, True).context.score_samples
    rng = np.random.default_rng(6)
    values = []
    for truth, _, _, sil in frames:
        for k in range(12):
            th = truth.copy()
            th[:3] += rng.normal(0, 0.03, 3)
            th[3:6] += rng.normal(0, 0.6, 3)
            if k == 0:
                th[2] = -0.1   # behind the camera: every sample costs the cap
            want = float(np.mean(model_to_data_mm(samples, th, sil)))
            got = model_to_data_mean(samples, th, sil)
            assert got == pytest.approx(want, rel=1e-13, abs=1e-12)
            values.append(want)
    assert min(values) < 5.0 and max(values) == pytest.approx(30.0)  # near fits and the cap were both covered
    empty = Silhouette(np.zeros((48, 64), bool), np.full((48, 64), np.nan), CAM)
    assert model_to_data_mean(samples, frames[0][0], empty) == 30.0


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 5000), st.integers(0, 2**32 - 1))
def test_pairwise_sum_is_numpys_sum_bit_for_bit(n, seed):
    """numpy's pairwise summation (blocks of 8 accumulators, halves above 128) rebuilt: the same bits
    for any length and offset (a compiled mean that ranks fits must rank them as numpy's did)."""
    rng = np.random.default_rng(seed)
    a = rng.random(n + 7) * 30.0 * (rng.random(n + 7) < 0.7) + rng.random(n + 7) * 1e-3
    lo = int(rng.integers(0, 8))
    n = min(n, len(a) - lo)
    assert pairwise_sum(a, lo, n) == np.add.reduce(a[lo:lo + n])


def _moved_fit(truth, pts, rng, shift_m, turn_rad, share):
    """θ moved off the truth (normal, ``shift_m`` and ``turn_rad`` per axis) and correspondences holding the
    ``pts`` with about ``share`` of their pairs valid (what the scores read of a fit)."""
    from tracker.correspond import Correspondences

    th = truth.copy()
    th[:3] += rng.normal(0, shift_m, 3)
    th[3:6] += rng.normal(0, turn_rad, 3)
    valid = rng.random(len(pts)) < share
    P = len(pts)
    return th, Correspondences(np.zeros((P, 3)), np.zeros(P, np.int64), np.zeros((P, 3)), np.zeros(P), valid, pts)


def test_compiled_data_cost_is_the_numpy_score_term(bundle, frames):
    """init.data_cost_mm's compiled path equals its numpy definition (the points' distances to the
    model on any side, rejected pairs penalised, capped; numpy's mean) exactly, for fits near and
    far (the cap and the rejected pairs both covered), and with no points."""
    from tracker.correspond import Correspondences, data_to_model_mm
    from tracker.init import DATA_CAP_MM, REJECTED_PAIR_MM, data_cost_mm

    ctx = _tracker(bundle, True).context
    rng = np.random.default_rng(7)
    values = []
    for truth, pts, _, _ in frames:
        for k in range(6):
            th, corr = _moved_fit(truth, pts, rng, 0.04 if k >= 3 else 0.004, 0.8 if k >= 3 else 0.1, 0.8)
            valid = corr.valid
            want = float(np.mean(np.minimum(data_to_model_mm(ctx.matcher, th, pts) + REJECTED_PAIR_MM * ~valid,
                                            DATA_CAP_MM)))
            assert data_cost_mm(ctx, th, corr) == want
            assert data_cost_mm(ctx, th, corr, frames=ctx.hand.node_frames(th)) == want
            values.append(want)
    assert min(values) < 4.0 and max(values) > 15.0
    none = Correspondences(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool),
                           np.zeros((0, 3)))
    assert data_cost_mm(ctx, frames[0][0], none) == DATA_CAP_MM


def test_compiled_score_is_the_sum_of_its_terms(bundle, frames):
    """init.score's one compiled call equals its terms computed one by one (the data term, the
    model→data mean × its weight, the wrist cue's cost by tracker.wrist.wrist_cost_mm) to rounding (1e-12
    relative: on an AVX-512 processor the compiled sums round differently, 2e-14 mm apart), with
    and without a wrist cue, for fits near and far, a cue the hand agrees with and one it points
    up; with the data term given (the safety net's path) the terms are added as before."""
    from tracker.icp import model_to_data_mean
    from tracker.init import MODEL_TO_DATA_WEIGHT, data_cost_mm, score
    from tracker.wrist import WristCue, wrist_cost_mm

    ctx = _tracker(bundle, True).context
    rng = np.random.default_rng(8)
    costs = []
    for truth, pts, _, sil in frames[:4]:
        kp = HAND.keypoints(truth)
        for k in range(6):
            th, corr = _moved_fit(truth, pts, rng, 0.03 if k >= 3 else 0.004, 0.9 if k >= 3 else 0.1, 0.85)
            sil.__dict__.pop("wrist", None)
            plain = data_cost_mm(ctx, th, corr) + MODEL_TO_DATA_WEIGHT * model_to_data_mean(ctx.score_samples, th, sil)
            assert score(ctx, th, corr, sil) == pytest.approx(plain, rel=1e-12)
            # a cue at the wrist, the arm away from the fingers, or along them (a hand folded back)
            away = (kp[0] - kp[9]) / np.linalg.norm(kp[0] - kp[9])
            sil.wrist = WristCue(kp[0] + rng.normal(0, 0.02, 3), kp[0], away if k % 2 else -away, 0.06)
            cost = wrist_cost_mm(sil.wrist, HAND, th)
            costs.append(cost)
            assert score(ctx, th, corr, sil) == pytest.approx(plain + cost, rel=1e-12)
            near = np.minimum(np.abs(rng.normal(3.0, 2.0, len(pts))), 30.0)
            assert score(ctx, th, corr, sil, data_mm=near) == pytest.approx(
                data_cost_mm(ctx, th, corr, data_mm=near) + MODEL_TO_DATA_WEIGHT * model_to_data_mean(
                    ctx.score_samples, th, sil) + cost, rel=1e-15)
            sil.__dict__.pop("wrist", None)
    assert min(costs) == 0.0 and max(costs) > 10.0  # both sides of the cue's cost covered


def _cue_beside(theta, offset_m):
    """A wrist cue whose arm line runs along the hand's axis at ``theta`` but ``offset_m`` to the side of
    its crease (across the image), as a forearm seen beside where the model puts its wrist would give."""
    from tracker.wrist import WristCue

    crease = HAND.wrist_crease(theta)
    R = HAND.node_frames(theta)[0, :3, :3]
    down = -R[:, 1]  # from the hand into the arm
    across = np.cross(crease / np.linalg.norm(crease), down)
    across /= np.linalg.norm(across)
    return WristCue(crease + offset_m * across, np.zeros(2), down, 0.06), across


def _across(theta, cue):
    from tracker.wrist import arm_line_normal

    return abs(float(arm_line_normal(cue) @ HAND.wrist_crease(theta)))


@pytest.mark.parametrize("weight,free_mm", [(IcpSettings().wrist_line_weight, IcpSettings().wrist_line_mm), (1.0, 0.0),
                                            (1.0, 3.0)])
def test_wrist_line_pair_matches_the_reference_and_pulls_the_crease_across(bundle, frames, weight, free_mm):
    """The wrist-line pair (``IcpSettings.wrist_line_weight``, ``wrist_line_mm``) in the compiled loop gives
    the reference loop's θ step by step. Its geometry against an independent construction: a cue line
    10 mm beside the true crease, parallel to the hand's axis, is 10 mm from the crease measured by the
    plane's normal (:func:`tracker.wrist.arm_line_normal`); with no weight the data keep the crease where
    it is, a dominant weight puts it on the line (within 1 mm), or ``wrist_line_mm`` from it; the default
    settings, against a rendered hand that the data pin down, move it only a little of the way (0.1–2 mm
    of 10): the term settles what the data leave open (a real hand unlike the model), it does not
    override them. A cue that stays within ``wrist_line_mm`` of the crease changes nothing."""
    tr = _tracker(bundle, True, icp=dict(wrist_line=dict(weight=weight, mm=free_mm)))
    start, pts, nrm, sil = frames[3]
    truth = frames[4][0]  # the frame's own truth (each frame's start is the frame before's)
    cue, _ = _cue_beside(truth, 0.010)
    assert _across(truth, cue) == pytest.approx(0.010, abs=2e-6)  # (the plane tilts by 10 mm over ~0.7 m)
    stages = tr.stages
    assert _check_stage_by_stage(tr, start, pts, nrm, sil, stages, wrist=cue) <= 1
    held = _one(fit, tr, start, pts, nrm, sil, stages, 1, wrist=cue)
    free = _one(fit, tr, start, pts, nrm, sil, stages, 1)
    np.testing.assert_allclose(_one(fit_reference, tr, start, pts, nrm, sil, stages, 1, wrist=cue), held, atol=2e-6)
    assert _across(free, cue) > 0.008  # the data alone: the crease stays near the truth
    if weight < 1.0:
        assert 0.0001 < _across(free, cue) - _across(held, cue) < 0.002
    else:
        assert abs(_across(held, cue) - free_mm / 1000.0) < 0.001
    if free_mm:
        # from the truth, where the crease stays within 3 mm of a line 1 mm beside it at every stage
        near, _ = _cue_beside(truth, 0.001)
        np.testing.assert_array_equal(_one(fit, tr, truth, pts, nrm, sil, stages, 1, wrist=near),
                                      _one(fit, tr, truth, pts, nrm, sil, stages, 1))


@pytest.mark.parametrize("strategy", ["halving", "exhaustive"])
def test_a_start_given_the_wrist_cue_ends_nearer_its_line(bundle, frames, strategy):
    """``fit_single_frame(..., wrist=cue)``: the winner's last fits take the wrist-line pair in either
    search strategy — a cue line 10 mm beside the rendered crease draws the start's crease towards it
    (the default weight: by 0.1–3 mm; the data pin a rendered hand), and the same start without the cue
    stays where the data put it."""
    from tracker.init import InitSettings, fit_single_frame

    tr = _tracker(bundle, True)
    _, pts, nrm, sil = frames[3]
    truth = frames[4][0]
    cue, _ = _cue_beside(truth, 0.010)
    st = InitSettings(strategy=strategy, finger_search=False)
    free, _ = fit_single_frame(tr.context, pts, st, theta0=truth, silhouette=sil, normals=nrm, search=False)
    held, _ = fit_single_frame(tr.context, pts, st, theta0=truth, silhouette=sil, normals=nrm, search=False,
                               wrist=cue)
    assert 0.0001 < _across(free, cue) - _across(held, cue) < 0.003


def _keypoints_beside(theta, offset_m, seed=0):
    """The hand's 21 keypoints at ``theta``, each moved ``offset_m`` in a random direction, all confident."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(21, 3))
    return HAND.keypoints(theta) + offset_m * d / np.linalg.norm(d, axis=1, keepdims=True), np.ones(21)


@pytest.mark.parametrize("weight,mm", [(KeypointTermSettings().weight, KeypointTermSettings().mm), (1.0, 20.0),
                                       (50.0, 1000.0)])
def test_keypoint_pairs_match_the_reference_and_pull_the_keypoints(bundle, frames, weight, mm):
    """The detected keypoints' pairs (``KeypointTermSettings.weight``, ``mm``) in the compiled loop
    give the reference loop's θ step by step. Against the truth: keypoints detected 15 mm beside the
    rendered hand draw the fit's keypoints towards them — the default weight a little (the data pin a
    rendered hand: the term decides what they leave open); the hand's keypoints moved 15 mm as one
    (a pose the model can take) are reached under a dominant weight (within 1.5 mm); keypoints 300 mm off
    (a detection on something else) barely pull a default fit (their Cauchy weight: under 1 mm on average,
    where without it they would drag the hand off the data); a weight of 0 or no keypoints leaves the fit
    as it was, to the bit."""
    tr = _tracker(bundle, True)
    term = KeypointTermSettings(weight=weight, mm=mm)
    start, pts, nrm, sil = frames[3]
    truth = frames[4][0]
    kp = _keypoints_beside(truth, 0.015)
    stages = tr.stages
    assert _check_stage_by_stage(tr, start, pts, nrm, sil, stages, keypoints=kp, keypoint_term=term) <= 1
    held = _one(fit, tr, start, pts, nrm, sil, stages, 1, keypoints=kp, keypoint_term=term)
    free = _one(fit, tr, start, pts, nrm, sil, stages, 1)
    np.testing.assert_allclose(_one(fit_reference, tr, start, pts, nrm, sil, stages, 1, keypoints=kp,
                                    keypoint_term=term), held, atol=2e-6)

    def to(th, target):
        return float(np.linalg.norm(HAND.keypoints(th) - target, axis=1).mean())

    assert to(free, kp[0]) > 0.012  # the data alone keep the hand near the truth, ~15 mm from the keypoints
    assert to(held, kp[0]) < to(free, kp[0]) - 0.0002
    if weight < 1.0:
        assert to(free, kp[0]) - to(held, kp[0]) < 0.005
        far = _keypoints_beside(truth, 0.300)
        assert to(_one(fit, tr, start, pts, nrm, sil, stages, 1, keypoints=far, keypoint_term=term),
                  HAND.keypoints(free)) < 0.001
    if mm > 100:
        shifted = HAND.keypoints(truth) + np.array([0.015, -0.005, 0.0])
        assert to(_one(fit, tr, start, pts, nrm, sil, stages, 1, keypoints=(shifted, np.ones(21)), keypoint_term=term),
                  shifted) < 0.0015
    np.testing.assert_array_equal(_one(fit, tr, start, pts, nrm, sil, stages, 1, keypoints=kp,
                                       keypoint_term=KeypointTermSettings(weight=0.0)), free)
    np.testing.assert_array_equal(_one(fit, tr, start, pts, nrm, sil, stages, 1, keypoints=None, keypoint_term=term),
                                  free)


def test_keypoint_pairs_refuse_bad_shapes_and_skip_what_was_not_found():
    from tracker._fit_arrays import keypoint_pairs
    from tracker.errors import TrackerError

    st = KeypointTermSettings()
    xyz, conf = _keypoints_beside(HAND.zero(), 0.0)
    conf[[3, 7]] = 0.0
    xyz[[5]] = np.nan
    kps = keypoint_pairs((xyz, conf), st)
    assert kps.on and list(kps.nodes) == [k for k in range(21) if k not in (3, 5, 7)]
    np.testing.assert_allclose(kps.share, st.weight / 21.0)
    assert not keypoint_pairs((xyz, np.zeros(21)), st).on and not keypoint_pairs(None, st).on
    with pytest.raises(TrackerError, match="keypoints"):
        keypoint_pairs((xyz[:20], conf[:20]), st)
    for bad in (-0.1, float("nan")):
        with pytest.raises(TrackerError, match="keypoints.weight must not be negative"):
            TrackerSettings().replace(refine=dict(keypoints=dict(weight=bad))).check()
    with pytest.raises(TrackerError, match="got 0.02 and 0.0"):
        TrackerSettings().replace(refine=dict(keypoints=dict(mm=0.0))).check()
    assert not TrackerSettings().refine.keypoints.on and not TrackerSettings.paper().refine.keypoints.on
    assert not keypoint_pairs((xyz, conf), KeypointTermSettings(weight=0.0)).on
