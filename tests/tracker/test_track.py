"""Tracking on mesh-rendered synthetic depth with real (fingerfist) trajectories: accuracy per mode,
the occluded grasp, single-frame fits, bad input and recovery."""
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import shared
from handmodel import HandModel
from tracker.sim import experiments as E
from tracker.errors import TrackerError
from tracker.icp import through
from tracker.init import diverse
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()
# Kinect v1 intrinsics (the tests do not depend on the camera-preset module)
CAM = SimpleNamespace(width=640, height=480, fx=575.8, fy=575.8, cx=319.5, cy=239.5, name="kinect1")


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.fixture(scope="module")
def postures():
    shared("htrack_schroeder", "fingerfist.txt")
    return E.fingerfist_postures()


def _run(bundle, postures, mode, start, n=40, distance=0.75, **kw):
    truth = E.sequence(postures[start:start + n], bundle.model.mean_, distance=distance)
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(mode=mode, **kw), synergies=bundle)
    return E.run_sequence(HAND, truth, CAM, tr, lead=10), truth, tr


@pytest.mark.parametrize("start,distance", [(300, 0.6), (3000, 0.9)])
def test_full_dof_noise_free(bundle, postures, start, distance):
    r, _, _ = _run(bundle, postures, "full", start, distance=distance)
    print(f"\nfull DoF, rows {start}+, {distance} m: {r.mean_error:.2f} deg, {1000 / r.median_ms:.0f} fps")
    assert r.mean_error <= 2.0
    assert (r.status[1:] == "tracked").all()


def test_reduced_is_limited_only_by_its_subspace(bundle, postures):
    r, truth, tr = _run(bundle, postures, "reduced", 300)
    recon = float(np.mean(E.posture_error_deg(tr.reduced.project(truth), truth, HAND.pose_mask)[10:]))
    oracle = float(np.mean(E.posture_error_deg(E.subspace_oracle(HAND, tr.reduced, truth[10:]), truth[10:],
                                               HAND.pose_mask)))
    print(f"\nreduced ({tr.n_pcs} PCs, 99 %): {r.mean_error:.2f} deg; geometric optimum of the subspace "
          f"{oracle:.2f} deg; projection of the truth {recon:.2f} deg")
    # the result stays inside the subspace, and tracking adds little to what geometry allows there
    np.testing.assert_allclose(tr.reduced.project(r.theta[10:]), r.theta[10:], atol=1e-9)
    assert r.mean_error <= oracle + 0.5
    assert r.mean_error <= 3.0


def test_reduced_with_projected_steps_stays_in_the_subspace_and_gains(bundle, postures):
    """The last ICP steps with all DoF, projected onto the PCs in joint-angle space: still a reduced
    posture, closer to the truth than the α-only fit (which the geometric optimum bounds)."""
    r0, truth, _ = _run(bundle, postures, "reduced", 300)
    r2, _, tr = _run(bundle, postures, "reduced", 300, icp=dict(projected_steps=2))
    print(f"\nreduced: α-only {r0.mean_error:.2f} deg, 2 steps projected {r2.mean_error:.2f} deg")
    np.testing.assert_allclose(tr.reduced.project(r2.theta[10:]), r2.theta[10:], atol=1e-9)
    assert r2.mean_error < r0.mean_error - 0.2
    assert r2.mean_error <= 2.0


def test_subspace_oracle_recovers_postures_inside_the_subspace(bundle, postures):
    """On postures that lie in the subspace the geometric optimum is the posture itself."""
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(mode="reduced"), synergies=bundle)
    truth = tr.reduced.project(E.sequence(postures[1000:1012], bundle.model.mean_, lead=0))
    start = truth.copy()
    start[:, ~HAND.pose_mask] = bundle.model.mean_  # from the mean posture: the fit has to get there
    assert np.min(E.posture_error_deg(start, truth, HAND.pose_mask)) > 2.0
    fit = E.subspace_oracle(HAND, tr.reduced, truth, theta0=start)
    assert np.max(E.posture_error_deg(fit, truth, HAND.pose_mask)) < 0.01


def test_hierarchical_tracking(bundle, postures):
    r, _, _ = _run(bundle, postures, "hierarchical", 300)
    assert r.mean_error <= 2.0


def test_hierarchical_tracking_follows_motion_outside_the_synergies(bundle):
    """Random postures within the joint limits (not fingerfist-like): the synergy step must not hold
    the hand back — hierarchical stays as accurate as full DoF."""
    from tracker.sim.motions import make_motion

    th = make_motion("random", hand=HAND, frames=90, seed=3).theta
    err = {}
    for mode in ("full", "hierarchical"):
        tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(mode=mode), synergies=bundle)
        err[mode] = E.run_sequence(HAND, th, CAM, tr).mean_error
    print(f"\nrandom postures: full {err['full']:.2f} deg, hierarchical {err['hierarchical']:.2f} deg")
    assert err["hierarchical"] <= err["full"] + 1.0
    assert err["hierarchical"] <= 3.0


def test_coarse_step_through_theta_keeps_theta_feasible(bundle):
    """A posture outside the PC limits (rarer than every training posture): the subspace through it
    must admit it (α = 0), else the coarse step would clamp it back."""
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(mode="hierarchical"), synergies=bundle)
    sp = tr.reduced
    theta = np.zeros(HAND.n_dofs)
    theta[~HAND.pose_mask] = bundle.model.mean_ + 3.0 * (sp.hi[6] + 0.1) * bundle.model.all_components_[0]
    assert sp.to_alpha(theta)[6] > sp.hi[6]
    th = through(sp, theta, HAND.pose_mask)
    assert (th.lo <= 0).all() and (th.hi >= 0).all()
    np.testing.assert_allclose(th.to_theta(np.zeros(th.M.shape[1])), theta, atol=1e-12)


def test_occluded_grasp_reduced_beats_full():
    """A grasp seen from the back: the synergy subspace keeps the hidden fingers plausible (reduced
    1.8°). Full DoF now nearly matches it: the joints no data point constrains are pulled to the
    synergies' conditional mean (``unseen_prior``) and the silhouette term no longer pulls fingers
    curled away from the camera forward to the surface (full 12.2° → 2.3°, measured). Reduced must
    stay no worse than full, and full within 4°."""
    res = E.experiment_occlusion(HAND, CAM, frames=36)
    print(f"\noccluded grasp: full {res['full']:.2f} deg, reduced ({res['n_pcs']} PCs) {res['reduced']:.2f} deg")
    assert res["reduced"] <= res["full"] + 0.2 and res["full"] <= 4.0


@pytest.mark.slow
def test_single_frame_hierarchical_better_than_flat(bundle, postures):
    """From the global pose only (posture unknown), the report's settings. The paper reports 22° flat
    vs 0.4° hierarchical; the issue's floor is 1°. These rows hold a fist (5700) and a crossed index
    finger (864), the two failure kinds docs/known-limits.md lists; the rest must be well under 1°."""
    res = E.experiment_single_frame(HAND, bundle, CAM, n=6, icp=30, seed=1)
    print(f"\nsingle frame rows {res['rows']}:")
    for key, *_ in E.SINGLE_METHODS:
        print(f"  {key:20s} {np.round(res[key + '_frames'], 2)}  {res['s_' + key][0]:.2f} s/frame")
    # the paper's finding: from the mean posture, hierarchical beats flat — here with our estimation;
    # with the paper's plain least squares both fits from the mean stay far off on our renderer
    # (medians ~37° and ~21°: the report shows them), and the start search beats them by far
    assert res["hierarchical_plain"][1] < res["flat_plain"][1]
    assert res["hierarchical"][1] < res["hierarchical_paper"][1] and res["flat"][1] < res["flat_paper"][1]
    # ours: the start search makes most frames exact, and never loses to the plain fit on average
    assert res["hierarchical"][1] <= 1.0
    assert res["hierarchical_share"][1.0] >= 4 / 6
    assert res["hierarchical"][0] <= res["hierarchical_plain"][0]


def test_finger_search_finds_a_finger_flexed_alone(bundle):
    """A ring finger curled alone (PIP-led, as in fingerfist) lies outside every synergy start; the
    finger-wise restarts find it. The synergy search alone now comes close too (measured 0.43°
    against 0.26° with the restarts, on the tree of 2026-11-23; earlier more than twice as far), so
    the restarts must still improve on it."""
    from tracker.correspond import Silhouette
    from tracker.observe import observe
    from tracker.sim.render import DepthRenderer

    truth = E.sequence(bundle.model.mean_[None], bundle.model.mean_, lead=0, distance=0.7)[0]
    names = list(HAND.dof_names)
    for n in names:  # other fingers straight, ring finger curled
        if "flex" in n and not n.startswith("thumb"):
            truth[names.index(n)] = np.radians(-5.0)
    for n, deg in (("ring1_flex", -45.0), ("ring2_flex", -100.0), ("ring3_flex", -15.0)):
        truth[names.index(n)] = np.radians(deg)
    ob = observe(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM, stride=1, target_points=None, smooth=0)
    sil = Silhouette(ob.mask, ob.depth, CAM)
    start = truth.copy()
    start[~HAND.pose_mask] = bundle.model.mean_
    err = {}
    for fs in (False, True):
        tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(init=dict(finger_search=fs, icp_iterations=20)), synergies=bundle)
        th, _ = tr.fit_single_frame(ob.points, theta0=start, mode="hierarchical", silhouette=sil, normals=ob.normals)
        err[fs] = float(E.posture_error_deg(th, truth, HAND.pose_mask))
    print(f"\nring finger alone: without finger search {err[False]:.2f} deg, with {err[True]:.2f} deg")
    assert err[True] <= 1.0
    assert err[True] < err[False] - 0.1


def test_diverse_placements_keep_a_flipped_candidate():
    from handmodel.rigid import euler_to_matrix, matrix_to_euler

    base = np.zeros(HAND.n_dofs)
    near = [base.copy() for _ in range(3)]
    for i, t in enumerate(near):
        t[3:6] = [0.05 * i, 0.0, 0.0]
    flipped = base.copy()
    flipped[3:6] = matrix_to_euler(euler_to_matrix([np.pi, 0.0, 0.0]))
    scored = [(1.0, near[0]), (1.1, near[1]), (1.2, near[2]), (5.0, flipped)]
    picked = diverse(scored, 2)
    assert picked[0] is near[0] and picked[1] is flipped
    # fewer than k different ones: filled up in score order
    assert [p is q for p, q in zip(diverse(scored[:3], 2), near[:2])] == [True, True]


class _FlyingPixels:
    """10 % of the hand's pixels moved 15–45 mm along their rays (edge/multipath artefacts of real
    depth cameras): outliers inside the 50 mm rejection radius."""

    def apply(self, depth, camera, rng):
        d = depth.copy()
        idx = np.flatnonzero(np.isfinite(d))
        pick = rng.choice(idx, len(idx) // 10, replace=False)
        d.flat[pick] += rng.choice([-1.0, 1.0], len(pick)) * rng.uniform(0.015, 0.045, len(pick))
        return d


@pytest.mark.parametrize("row", [310, 320])
def test_robust_weights_resist_outliers(bundle, postures, row):
    """One tracking step from the true θ on a frame with 10 % flying pixels: least squares is dragged
    far off, the Cauchy-weighted data term stays close."""
    from tracker.observe import observe
    from tracker.segment import Segmenter
    from tracker.sim.render import DepthRenderer

    truth = E.sequence(postures[row:row + 1], bundle.model.mean_, lead=0)[0]
    depth = _FlyingPixels().apply(DepthRenderer(HAND, CAM).render(truth, labels=False).depth, CAM,
                                  np.random.default_rng(row))
    # the weights are under test, not the forearm cut: flying pixels beside a hand alone in space can make
    # the cut take a finger for an arm (row 320: 16 % of the hand cut; noted, not fixed here)
    ob = observe(depth, CAM, stride=3, target_points=600, smooth=0, segmenter=Segmenter(forearm="keep"))
    err = {}
    for c in (0.0, 8.0):
        # without the gate by the predicted hand, which would drop most flying pixels before the weights see them
        tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(icp=dict(robust_mm=c), observe=dict(smooth=0, gate_mm=0.0)), synergies=bundle)
        tr.theta, tr.lost = truth.copy(), False
        r = tr.track(ob, CAM)
        assert r.status == "tracked"
        err[c] = float(E.posture_error_deg(r.theta, truth, HAND.pose_mask))
    print(f"\n10 % flying pixels, one step from the truth: least squares {err[0.0]:.2f} deg, Cauchy {err[8.0]:.2f} deg")
    assert err[8.0] <= 3.0
    assert err[0.0] >= 3.0 * err[8.0]


def test_blank_frames_lost_then_recovered(bundle, postures):
    truth = E.sequence(postures[3000:3040], bundle.model.mean_)
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(mode="full"), synergies=bundle)
    r = E.run_sequence(HAND, truth, CAM, tr, lead=10, blank=(20, 30))
    assert (r.status[20:30] == "lost").all()
    back = r.error_deg[33:]
    print(f"\nafter 10 blank frames: status {list(r.status[30:34])}, error {np.round(r.error_deg[30:36], 2)}")
    assert np.nanmean(back) <= 2.0


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.full((100, 3), np.nan), np.zeros((5, 3))])
def test_bad_points_give_lost_not_crash(bad):
    tr = FrameTracker(HAND, TrackerSettings().replace(mode="full"))
    r = tr.step(bad)
    assert r.status == "lost"


def test_a_frame_without_points_outputs_no_theta_and_tracking_goes_on():
    """A frame with nothing to fit (an unreadable file, an empty mask) is lost without θ: its row
    repeated the frame before it, which a user cannot tell from a measurement. The tracker keeps its
    last θ and tracks on from it."""
    from tracker.io.cameras import preset
    from tracker.observe import observe
    from tracker.sim.motions import make_motion
    from tracker.sim.render import DepthRenderer

    cam = preset("kinect1")
    truth = make_motion("open-close", hand=HAND, frames=6, seed=0).theta
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0), mode="full"))
    ren = DepthRenderer(HAND, cam)
    first = tr.track(observe(ren.render(truth[0]).depth, cam), cam)
    assert first.status == "reinit"
    lost = tr.step(np.zeros((0, 3)))
    assert lost.status == "lost" and np.isnan(lost.theta).all()
    assert np.isfinite(tr.theta).all()
    nxt = tr.track(observe(ren.render(truth[1]).depth, cam), cam)
    assert nxt.status in ("tracked", "reinit") and np.isfinite(nxt.theta).all()
    err = np.linalg.norm(HAND.keypoints(nxt.theta) - HAND.keypoints(truth[1]), axis=-1).mean() * 1000
    assert err < 5.0, err


def test_bad_settings():
    with pytest.raises(TrackerError, match="mode: must be full, reduced or hierarchical"):
        FrameTracker(HAND, TrackerSettings().replace(mode="fast"))
    with pytest.raises(TrackerError, match="needs a synergy bundle"):
        FrameTracker(HAND, TrackerSettings().replace(mode="reduced"))


# ----------------------------------------------------------------------------- silhouette pairs (numba kernel)
def test_silhouette_term_keeps_fingers_curled_away_from_the_camera():
    """A power grasp seen from the back, frames whose middle and end phalanges curl away from the
    camera, fitted by a tracked frame's ICP from the truth: the silhouette term must not move what the
    truth already explains. When it pulled samples outside the mask to the surface's depth, it
    brought the hidden fingers forward and unbent them (measured 9.3°, 13.9°, 15.4° off); pulling
    across the image only, they stay (measured 1.1°, 0.8°, 2.2°)."""
    from tracker.correspond import Silhouette
    from tracker.evaluate import posture_error_deg
    from tracker.icp import fit
    from tracker.observe import observe
    from tracker.sim.motions import make_motion
    from tracker.sim.render import DepthRenderer

    truth = make_motion("grasp-back", hand=HAND).theta
    tr = FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)))
    ctx, ren = tr.context, DepthRenderer(HAND, CAM)
    for f in (32, 45, 55):
        ob = observe(ren.render(truth[f], labels=False).depth, CAM, tr.settings.observe)
        th, _ = fit(HAND, ob.points, truth[f], tr.stages, ctx.matcher, tr.settings.icp, n_rigid=1,
                    normals=ob.normals, samples=ctx.samples, silhouette=Silhouette(ob.mask, ob.depth, CAM))
        assert posture_error_deg(th, truth[f], HAND.pose_mask) <= 4.0, f


def _silhouette_pairs_reference(samples, theta, sil, tolerance_px=1.5):
    """The straightforward numpy version: pose all samples, keep the front-facing ones, project,
    look up the distance transform (plus the overshoot outside its window), fetch the nearest
    silhouette pixel's depth, or the sample's own where it is farther (the pull is across the image:
    a hidden part behind the surface keeps its depth). Also returns how many kept samples fell
    outside the window."""
    cam = sil.camera
    G = HAND.node_frames(theta)[samples.nodes]
    P = np.einsum("pij,pj->pi", G[:, :3, :3], samples.local) + G[:, :3, 3]
    N = np.einsum("pij,pj->pi", G[:, :3, :3], samples.local_n)
    z = P[:, 2]
    ok = (np.einsum("ij,ij->i", P, N) < 0) & (z > 1e-3)
    u = np.rint(cam.fx * P[ok, 0] / z[ok] + cam.cx).astype(np.int64) - sil.u0
    v = np.rint(cam.fy * P[ok, 1] / z[ok] + cam.cy).astype(np.int64) - sil.v0
    h, w = sil.dist.shape
    uu, vv = np.clip(u, 0, w - 1), np.clip(v, 0, h - 1)
    d_px = sil.dist[vv, uu] + np.hypot(u - uu, v - vv)
    far = d_px > tolerance_px
    idx = np.flatnonzero(ok)[far]
    tv, tu = sil.iv[vv[far], uu[far]] + sil.v0, sil.iu[vv[far], uu[far]] + sil.u0
    d = np.fmax(sil.depth[tv, tu], z[ok][far])
    d[~np.isfinite(sil.depth[tv, tu])] = np.nan
    tgt = np.stack([(tu - cam.cx) / cam.fx * d, (tv - cam.cy) / cam.fy * d, d], 1)
    good = np.isfinite(d)
    n_outside = int(((u != uu) | (v != vv)).sum())
    return samples.nodes[idx[good]], samples.local[idx[good]], tgt[good], n_outside, int((~good).sum())


@pytest.fixture(scope="module")
def silhouette_scenes():
    """(θ, Silhouette) of rendered frames: a half-closed hand in the middle, near the top edge, and
    shifted so that it partly leaves the image on the right (and so its distance-transform window)."""
    from tracker.sim.motions import make_motion
    from tracker.observe import observe
    from tracker.sim.render import DepthRenderer
    from tracker.correspond import Silhouette

    base = make_motion("open-close", hand=HAND, frames=20).theta[12]
    ren = DepthRenderer(HAND, CAM)
    out = []
    for shift in [(0.0, 0.0, 0.0), (0.0, -0.25, 0.0), (0.45, 0.0, 0.0)]:
        th = base.copy()
        th[:3] += shift
        ob = observe(ren.render(th, labels=False).depth, CAM, stride=3, target_points=None, smooth=0)
        out.append((th, Silhouette(ob.mask, ob.depth, CAM)))
    return out


@pytest.fixture(scope="module")
def model_samples():
    from tracker.correspond import ModelSamples

    return ModelSamples(HAND)


def _assert_same_pairs(got, ref):
    assert got[0].dtype == ref[0].dtype == np.int64
    assert got[1].dtype == got[2].dtype == np.float64
    np.testing.assert_array_equal(got[0], ref[0])
    np.testing.assert_allclose(got[1], ref[1], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[2], ref[2], rtol=0, atol=1e-12)


def test_silhouette_pairs_kernel_matches_numpy_reference(silhouette_scenes, model_samples):
    from tracker.correspond import silhouette_pairs

    rng = np.random.default_rng(7)
    n_outside = 0
    for th, sil in silhouette_scenes:
        assert not sil.empty
        # at the rendered θ few samples are outside; perturbed, many are
        got = silhouette_pairs(model_samples, th, sil)
        _assert_same_pairs(got, _silhouette_pairs_reference(model_samples, th, sil))
        for _ in range(6):
            p = th.copy()
            p[:3] += rng.normal(0.0, 0.03, 3)
            p[3:] += rng.normal(0.0, 0.15, len(p) - 3)
            for tol in (1.5, 0.0, 6.0):
                got = silhouette_pairs(model_samples, p, sil, tolerance_px=tol)
                ref = _silhouette_pairs_reference(model_samples, p, sil, tolerance_px=tol)
                _assert_same_pairs(got, ref)
                assert len(got[0]) > 0
                n_outside += ref[3]
    # the samples projecting beyond the distance transform's window were exercised
    assert n_outside > 0


def test_silhouette_pairs_kernel_drops_missing_depth(silhouette_scenes, model_samples):
    """Silhouette pixels without depth (NaN) give no pair, in both implementations."""
    from tracker.correspond import Silhouette, silhouette_pairs

    rng = np.random.default_rng(3)
    th, sil = silhouette_scenes[0]
    depth = sil.depth.copy()
    v, u = np.nonzero(sil.mask)
    hole = rng.random(len(v)) < 0.3
    depth[v[hole], u[hole]] = np.nan
    holed = Silhouette(sil.mask, depth, CAM)
    p = th.copy()
    p[:3] += (0.02, -0.015, 0.0)
    p[3:] += rng.normal(0.0, 0.15, len(p) - 3)
    ref = _silhouette_pairs_reference(model_samples, p, holed)
    assert ref[4] > 0 and len(ref[0]) > 0
    _assert_same_pairs(silhouette_pairs(model_samples, p, holed), ref)


def test_silhouette_pairs_empty_silhouette(model_samples):
    from tracker.correspond import Silhouette, silhouette_pairs

    sil = Silhouette(np.zeros((CAM.height, CAM.width), bool), np.full((CAM.height, CAM.width), np.nan), CAM)
    n, loc, tg = silhouette_pairs(model_samples, HAND.zero(), sil)
    assert n.shape == (0,) and loc.shape == (0, 3) and tg.shape == (0, 3)


def test_model_samples_pose_agrees_with_node_frames(model_samples):
    """``ModelSamples.pose`` (no longer on the hot path) still poses points and normals by the node frames."""
    th = HAND.zero()
    th[2] = 0.6
    th[3:6] = (0.3, -0.2, 0.5)
    P, N = model_samples.pose(th)
    nodes = model_samples.nodes
    np.testing.assert_allclose(P, HAND.points(th, nodes, model_samples.local), atol=1e-12)
    origin = HAND.points(th, nodes, np.zeros_like(model_samples.local_n))
    np.testing.assert_allclose(N, HAND.points(th, nodes, model_samples.local_n) - origin, atol=1e-12)


def test_output_rotation_is_wrapped():
    """A hand whose θ has turned round several times (a start on an SR305 frame came out at −17.8 rad,
    and the lost frames after it repeated it) is output as the same rotation in [−π, π)."""
    from test_init_orientation import CAM, scene

    hand = HandModel.load()
    th, ob, _ = scene(hand, "palm", np.zeros(hand.n_dofs - 6))
    turned = th + np.r_[0, 0, 0, np.array([6.0, -4.0, 2.0]) * np.pi, np.zeros(hand.n_dofs - 6)]
    tr = FrameTracker(hand, TrackerSettings().replace(scale=dict(hand_scale=1.0), net=dict(enabled=False), refine=dict(finger_restart_deg=0.0)))
    tr.theta, tr.lost = turned.copy(), False
    r = tr.track(ob, CAM)
    assert r.status == "tracked" and np.all(np.abs(r.theta[3:6]) <= np.pi)
    assert np.allclose(hand.keypoints(r.theta), hand.keypoints(th), atol=0.004)  # and it fits the frame
