"""The fit loop's own closest-point pass (:func:`tracker._fit_kernels.match_posed`, the search of
:func:`tracker._fit_kernels.closest_pass_and_any` on :func:`~tracker._fit_kernels.posed_primitives`) gives
:func:`tracker._correspond_kernels.match`'s pairs to the bit, its Cholesky solve
(:func:`handmodel._solver_kernels.cholesky_solve`, column by column) the row-by-row solve's answers to the bit, and a batch of fits with a start
given twice (:meth:`tracker.init.FitContext.fit_many`, which fits it once) gives each row the fit of that start
alone."""
import numpy as np
import pytest

from handmodel import HandModel
from handmodel import _geometry_kernels as GK
from tracker import _correspond_kernels as CK
from tracker import _fit_kernels as K
from tracker._kernel_arrays import CapsuleArrays, MatchRules, Pairs
from tracker.init import thin
from tracker.init.scoring import distinct_rows
from tracker.io.cameras import preset
from tracker.correspond import Silhouette
from tracker.observe import observe
from tracker.segment import Segmenter
from tracker.sim.render import DepthRenderer
from tracker.track import FrameTracker, TrackerSettings

from tests.tracker.test_icp_compiled import _posed_points

HAND = HandModel.load()


def _passes(G, caps, pts, normals, rules, seed_rows, hints):
    """``match``, ``match_posed`` and ``match_posed`` with each point's first visit from ``hints`` (any
    integers: out of range ones are no hint) on the same input, each from rows holding ``seed_rows`` (a point
    without a pair keeps its rows): ``(pairs, valid count)`` of each."""
    out = []
    P = len(pts)
    for fn, hinted in ((CK.match, None), (K.match_posed, False), (K.match_posed, True)):
        pairs = Pairs(seed_rows[0].copy(), seed_rows[1].copy(), hints.copy(), np.full(P, 7.0),
                      np.full(P, 3, np.int64), np.zeros(P, np.bool_))
        args = (np.ascontiguousarray(G), caps, pts, normals, rules, pairs)
        nv = fn(*args) if hinted is None else fn(*args, hinted)
        out.append((pairs, nv))
    return out


@pytest.mark.parametrize("spread", [0.005, 0.03, 0.2])
def test_the_fit_s_pass_is_match_to_the_bit(spread):
    """Same points, normals, primitives, distances, nodes and kept pairs as ``match``, with the camera-facing
    test on and off, the normal test on (NaN rows among the normals) and off, points on, near and far from
    the hand, in a scan's order and shuffled, with the camera off the origin, and with each point's first
    visit given (a pass before's winners: here any primitive, or none)."""
    rng = np.random.default_rng(int(spread * 1000) + 42)
    caps = CapsuleArrays(*HAND.capsules.kernel_args())
    kept = shown = 0
    for k in range(4):
        G, pts = _posed_points(rng, 300, spread)
        if k % 2:
            pts = pts[np.argsort(pts[:, 0])]  # scan-like order: neighbours share their winner
        P = len(pts)
        normals = rng.normal(size=(P, 3))
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        normals[rng.random(P) < 0.1] = np.nan
        seed = rng.normal(size=(P, 3)), rng.normal(size=(P, 3))
        for facing in (True, False):
            for nrm, agree in ((np.zeros((0, 3)), -1.0), (normals, 0.3)):
                rules = MatchRules(np.array([0.0, 0.01 * k, -0.02 * k]), facing, 0.03, agree)
                hints = rng.integers(-3, len(caps.node) + 3, P)
                (a, na), *posed = _passes(G, caps, pts, nrm, rules, seed, hints)
                for b, nb in posed:
                    assert na == nb
                    for x, y in zip(a, b):
                        np.testing.assert_array_equal(x, y)
                kept += na
                shown += P
    assert 0 < kept < shown  # some pairs kept, some not (rejected or unmatched)


def test_profiles_of_spheres_and_points_on_the_axes_are_closest_local_s():
    """The profile constants (:func:`tracker._fit_kernels.posed_primitives`) stand for ``_round_cone_2d``'s
    own in every case: cones that are the hull of their two spheres, cones whose one sphere holds the other
    (base or end the bigger), for points on a primitive's axis, at a sphere's centre, inside and outside;
    the nearest facing and any-side surface as the lone searches give them, to the bit."""
    rng = np.random.default_rng(7)
    node, shape, length, r0, r1, th = (np.array(a) for a in HAND.capsules.kernel_args())
    # every third capsule a sphere in a sphere (|r0 - r1| >= L), the bigger sphere at either end
    length, r0, r1 = length.copy(), r0.copy(), r1.copy()
    cone = np.flatnonzero(shape == GK.CAPSULE)
    for k, s in enumerate(cone[::3]):
        length[s] = 0.004
        r0[s], r1[s] = (0.012, 0.006) if k % 2 else (0.006, 0.012)
    caps = CapsuleArrays(node, shape, length, r0, r1, th)
    theta = HAND.zero()
    theta[2] = 0.6
    theta[3:6] = rng.normal(size=3)
    G = HAND.node_frames(theta)
    pts = [HAND.keypoints(theta)[rng.integers(0, 21, 200)] + rng.normal(scale=0.02, size=(200, 3))]
    for s in cone:
        g = G[node[s]]
        # on the axis (inside, at the ends' centres, beyond them) and off it
        for y in (-0.01, 0.0, 0.5 * length[s], length[s], length[s] + 0.01):
            pts.append((g[:3, 3] + y * g[:3, 1])[None])
            pts.append((g[:3, 3] + y * g[:3, 1] + 0.003 * g[:3, 0])[None])
    pts = np.ascontiguousarray(np.concatenate(pts))
    P = len(pts)
    for facing in (True, False):
        cam = np.zeros(3)
        lone = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
        GK.closest_points_facing(G, *caps, pts, cam, facing, *lone)
        lone_any = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
        GK.closest_points_facing(G, *caps, pts, cam, False, *lone_any)
        both = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
        any_d = np.empty(P)
        K.closest_pass_and_any(G, caps, pts, cam, facing, *both, any_d)
        for a, b in zip(both, lone):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(any_d, lone_any[3])
        alone = np.zeros((P, 3)), np.zeros((P, 3)), np.empty(P, np.int64), np.empty(P)
        K.closest_pass_and_any(G, caps, pts, cam, facing, *alone, None)
        for a, b in zip(alone, lone):
            np.testing.assert_array_equal(a, b)
        # each point started at another primitive (what a pass before found at a nearby pose)
        hinted = np.zeros((P, 3)), np.zeros((P, 3)), rng.integers(0, len(node), P), np.empty(P)
        any_h = np.empty(P)
        K.closest_pass_and_any(G, caps, pts, cam, facing, *hinted, any_h, True)
        for a, b in zip(hinted, lone):
            np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(any_h, lone_any[3])
    # the sphere-in-sphere primitives won points (else the case went untested)
    assert np.isin(lone[2], cone[::3]).sum() > 10


def test_distinct_rows_keep_the_first_of_equal_rows_in_order():
    """Rows equal by their bytes are one: the first of them kept, in order; 0.0 and -0.0 differ, a NaN row
    equals its copy; the rows rebuilt from the kept ones are the input to the bit."""
    a = np.array([[1.0, 2.0], [0.0, 1.0], [1.0, 2.0], [-0.0, 1.0], [np.nan, 1.0], [np.nan, 1.0], [0.0, 1.0]])
    first, which = distinct_rows(a)
    np.testing.assert_array_equal(first, [0, 1, 3, 4])
    np.testing.assert_array_equal(which, [0, 1, 0, 2, 3, 3, 1])
    assert a[first][which].tobytes() == a.tobytes()
    first, which = distinct_rows(np.zeros((0, 3)))
    assert first.size == 0 and which.size == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_a_start_given_twice_is_fitted_as_if_alone(threads):
    """A batch with repeated starts (the synergy grid clipped to the PCs' limits repeats postures) gives
    every row the θ and score of its start's own batch of one, to the bit, on one thread and on two."""
    from dataclasses import replace

    from synergy.bundle import load_bundle

    cam = preset("kinect1")
    tr = FrameTracker(HAND, TrackerSettings(), synergies=load_bundle("fingerfist"))
    ctx = replace(tr.context, threads=threads)
    truth = HAND.zero()
    truth[2] = 0.7
    truth[~HAND.pose_mask] = ctx.synergies.mean_
    ob = observe(DepthRenderer(HAND, cam).render(truth, labels=False).depth, cam, stride=1, target_points=None,
                 smooth=0, segmenter=Segmenter(forearm="keep"))
    sil = Silhouette(ob.mask, ob.depth, cam)
    sub = thin(ob.points, 200)
    pts, nrm = ob.points[sub], ob.normals[sub]
    rng = np.random.default_rng(3)
    starts = [truth + np.r_[rng.normal(0.0, 0.01, 6), rng.normal(0.0, 0.2, HAND.n_dofs - 6)] for _ in range(3)]
    batch = [starts[0], starts[1], starts[0], starts[2], starts[1], starts[0]]
    T, S = ctx.fit_many(batch, pts, "full", 1, 2, silhouette=sil, normals=nrm)
    for th0, th, s in zip(batch, T, S):
        T1, S1 = ctx.fit_many([th0], pts, "full", 1, 2, silhouette=sil, normals=nrm)
        np.testing.assert_array_equal(th, T1[0])
        assert s == S1[0]
    assert not np.array_equal(T[0], T[1])  # different starts stay different fits


def _cholesky_by_rows(A, b, x, L):
    """The textbook row-by-row Cholesky solve (handmodel's before it went column by column): the reference."""
    m = A.shape[0]
    for i in range(m):
        for j in range(i + 1):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            if i == j:
                if s <= 0.0:
                    return False
                L[i, i] = np.sqrt(s)
            else:
                L[i, j] = s / L[j, j]
    for i in range(m):
        s = b[i]
        for k in range(i):
            s -= L[i, k] * x[k]
        x[i] = s / L[i, i]
    for i in range(m - 1, -1, -1):
        s = x[i]
        for k in range(i + 1, m):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return True


def test_the_column_cholesky_solve_is_the_row_by_row_one_to_the_bit():
    """:func:`handmodel._solver_kernels.cholesky_solve` (column by column, four rows at once; the fit kernels
    use it too) gives the row-by-row solve's answer and x to the bit, for 1–30 unknowns (the row blocks of
    four and the rows left over), scales from 1e-6 to 1e6, on strided views as the solver passes them, and
    refuses exactly the matrices it refuses (a zero row, a negative direction)."""
    from numba import njit

    from handmodel import _solver_kernels as SK

    by_rows = njit(cache=False)(_cholesky_by_rows)
    rng = np.random.default_rng(11)
    refused = 0
    for trial in range(600):
        m = int(rng.integers(1, 31))
        B = rng.normal(size=(m, m)) * 10.0 ** rng.uniform(-3, 3)
        A = B @ B.T + rng.uniform(0, 1) * np.eye(m)
        if trial % 4 == 0:
            k = rng.integers(m)
            A[k, :] = A[:, k] = 0.0 if trial % 8 == 0 else -A[k, :]
            A[k, k] = 0.0 if trial % 8 == 0 else -1.0
        b = rng.normal(size=m)
        x0, x1 = np.full(m, 7.0), np.full(m, 7.0)
        ok0 = by_rows(A, b, x0, np.zeros((m, m)))
        big = np.zeros((32, 32))
        big[:m, :m] = A
        ok1 = SK.cholesky_solve(big[:m, :m], b, x1, np.zeros((32, 32))[:m, :m])
        assert ok0 == ok1
        if ok0:
            np.testing.assert_array_equal(x1, x0)
        refused += not ok0
    assert 50 < refused < 300
