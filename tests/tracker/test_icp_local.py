"""Local passes (tracker.icp.Stage.local, IcpSettings.stages_per_pass / local_mm): the synergy stages of
reduced and hierarchical tracking re-project every data point onto the primitive it was matched to
instead of searching every primitive, while the model moved little since the pass before."""
import numpy as np
import pytest

from handmodel import HandModel
from tracker import _fit_kernels as K
from tracker.correspond import Silhouette
from tracker.icp import capsule_pass, fit, fit_reference, posed_samples
from tracker.observe import observe
from tracker.sim import experiments as E
from tracker.sim.render import DepthRenderer
from tracker.parts import usable_points
from tracker.track import FrameTracker, TrackerSettings

HAND = HandModel.load()


@pytest.fixture(scope="module")
def bundle():
    from synergy.bundle import load_bundle

    return load_bundle("fingerfist")


@pytest.fixture(scope="module")
def frames(bundle):
    """Consecutive frames of the fingerfist recording (a tracker's small frame-to-frame motion), each
    with the previous frame's truth as the start: (start, points, normals, silhouette)."""
    cam = E.default_camera()
    truth = E.sequence(E.fingerfist_postures()[3000:3008], bundle.model.mean_, lead=0)
    ren = DepthRenderer(HAND, cam)
    out = []
    for f in range(1, len(truth)):
        ob = observe(ren.render(truth[f], labels=False).depth, cam, TrackerSettings.paper().observe)
        pts, nrm = usable_points(ob.points, ob.normals, 0)
        out.append((truth[f - 1], pts, nrm, Silhouette(ob.mask, ob.depth, cam)))
    return out


def _fit(fitter, tr, start, pts, nrm, sil, stats=None, **kw):
    ctx = tr.context
    extra = {} if stats is None else {"stats": stats}
    return fitter(HAND, pts, start, tr.stages, ctx.matcher, tr.settings.icp, n_rigid=tr.settings.icp.rigid_iterations,
                  normals=nrm, samples=ctx.samples, silhouette=sil, **extra, **kw)


def _tracker(bundle, **kw):
    return FrameTracker(HAND, TrackerSettings().replace(scale=dict(hand_scale=1.0)).replace(**kw), synergies=bundle)


@pytest.mark.parametrize("mode", ["reduced", "hierarchical"])
def test_local_passes_give_the_reference_result(bundle, frames, mode):
    """The compiled loop's local passes (moment sums and per pair) against the Python reference, which
    re-projects with the same kernel but decides, pairs and solves in Python: θ to 2e-6 (moment sums)
    and 2e-7 (per pair), as the loop without local passes; and local passes did happen."""
    tr = _tracker(bundle, mode=mode)
    assert any(s.local for s in tr.stages)
    stats = np.zeros(5, np.int64)
    for start, pts, nrm, sil in frames:
        t_ref, c_ref = _fit(fit_reference, tr, start, pts, nrm, sil)
        t_mom, c_mom = _fit(fit, tr, start, pts, nrm, sil, stats=stats)
        t_pair, _ = _fit(fit, tr, start, pts, nrm, sil, moments=False)
        assert np.abs(t_mom - t_ref).max() < 2e-6 and np.abs(t_pair - t_ref).max() < 2e-7
        assert (c_mom.valid == c_ref.valid).all()
    assert stats[4] >= len(frames)


def test_reduced_fit_searches_less_and_reaches_the_same_fit(bundle, frames):
    """On the same frames a reduced fit searches every primitive 3–4 times where full does 6 (the
    rigid step, 4 stages, the final correspondences; the rest are local passes) and lands where
    reduced with a search per stage lands, within what 4 ICP iterations leave open: every model
    surface sample within 1 mm, every joint within 1°, the fit error within 0.03 mm (measured: 0.63 mm,
    0.72°, 0.022 mm at most; either fit is sometimes the closer one)."""
    full, red, red_search = _tracker(bundle), _tracker(bundle, mode="reduced"), \
        _tracker(bundle, mode="reduced", icp=dict(local=dict(stages_per_pass=1)))
    n = len(frames)
    s_full, s_red, s_search = (np.zeros(5, np.int64) for _ in range(3))
    samples = full.context.score_samples
    for start, pts, nrm, sil in frames:
        _fit(fit, full, start, pts, nrm, sil, stats=s_full)
        a, ca = _fit(fit, red, start, pts, nrm, sil, stats=s_red)
        b, cb = _fit(fit, red_search, start, pts, nrm, sil, stats=s_search)
        Pa, _ = posed_samples(HAND, samples, a)
        Pb, _ = posed_samples(HAND, samples, b)
        assert np.linalg.norm(Pa - Pb, axis=1).max() < 1e-3
        assert np.degrees(np.abs(a[6:] - b[6:]).max()) < 1.0
        assert abs(ca.fit_error_mm() - cb.fit_error_mm()) < 0.03
    assert s_full[3] == 6 * n and s_full[4] == 0
    assert s_search[3] == 6 * n
    assert s_red[3] <= 4 * n and s_red[3] + s_red[4] == 6 * n and s_red[4] >= 2 * n


def test_a_large_motion_searches_again(bundle, frames):
    """A start 2 cm off moves the model more than ``local_mm`` in the rigid step: every stage searches
    (no local pass), so the fit is exactly the one with a search per stage."""
    start, pts, nrm, sil = frames[0]
    off = start.copy()
    off[:3] += [0.02, 0.0, 0.0]
    red, red_search = _tracker(bundle, mode="reduced"), _tracker(bundle, mode="reduced", icp=dict(local=dict(stages_per_pass=1)))
    stats = np.zeros(5, np.int64)
    a, _ = _fit(fit, red, off, pts, nrm, sil, stats=stats)
    b, _ = _fit(fit, red_search, off, pts, nrm, sil)
    assert stats[4] == 0 and stats[3] == 6
    np.testing.assert_array_equal(a, b)


def test_a_local_pass_at_the_same_pose_is_the_search(bundle, frames):
    """Re-projected at the pose it searched at, every point gets the search's closest point, normal,
    distance and validity back (the search's winner is the closest on its own primitive)."""
    tr = _tracker(bundle)
    start, pts, nrm, _ = frames[1]
    c, seg = capsule_pass(HAND, tr.context.matcher, start, pts, nrm)
    ref = tr.context.matcher(start, pts, nrm)
    np.testing.assert_array_equal(c.valid, ref.valid)
    np.testing.assert_allclose(c.model[c.valid], ref.model[ref.valid], atol=1e-12)
    c2, seg2 = capsule_pass(HAND, tr.context.matcher, start, pts, nrm, seg)
    np.testing.assert_array_equal(seg2, seg)
    np.testing.assert_array_equal(c2.valid, c.valid)
    np.testing.assert_allclose(c2.model, c.model, atol=1e-12)
    np.testing.assert_allclose(c2.distance[c.valid], c.distance[c.valid], atol=1e-12)
    np.testing.assert_array_equal(c2.nodes[c.valid], c.nodes[c.valid])


def test_moved_is_the_largest_displacement():
    """pairs_moved and matches_moved: the largest distance a pair's model point moved between two
    poses, against hand.points."""
    rng = np.random.default_rng(0)
    a = HAND.zero()
    a[:3] = [0.0, 0.0, 0.7]
    b = a.copy()
    b[6:] += rng.normal(0, 0.02, HAND.n_dofs - 6)
    b[:3] += [0.001, -0.002, 0.0]
    nodes = rng.integers(0, HAND.n_nodes, 50)
    loc = rng.normal(0, 0.01, (50, 3))
    Ga, Gb = HAND.node_frames(a), HAND.node_frames(b)
    want = np.linalg.norm(HAND.points(b, nodes, loc) - HAND.points(a, nodes, loc), axis=1).max()
    assert K.pairs_moved(Ga, Gb, nodes, loc, 50) == pytest.approx(want, rel=1e-9)
    world = HAND.points(a, nodes, loc)
    valid = np.ones(50, np.bool_)
    valid[np.argmax(np.linalg.norm(HAND.points(b, nodes, loc) - world, axis=1))] = False
    want_v = np.linalg.norm(HAND.points(b, nodes, loc) - world, axis=1)[valid].max()
    # the kernel takes a frame's inverse rotation as its transpose: the frames are orthonormal to ~1e-6
    assert K.matches_moved(Ga, Gb, world, nodes.astype(np.int64), valid) == pytest.approx(want_v, rel=1e-4)
