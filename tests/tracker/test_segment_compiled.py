"""The segmenter's compiled shortcuts (issue 39's segmentation speed) against the numpy and scipy
expressions they replace: each must give the same values to the bit, or the segmentation changes."""
import numpy as np
from hypothesis import given, settings, strategies as st
from scipy import ndimage

from tracker._segment_kernels import fill_holes, label_extents, near_front, valid_depths
from tracker.segment import Segmenter, SupportPlane, skin_mask
from tracker.segment.ops import _in_labels, _points, _sq_dist
from tracker.segment.region import _seed_points

seeds = st.integers(0, 2**32 - 1)


def _depth(rng, h, w, holes=0.2):
    d = 0.3 + 1.4 * rng.random((h, w))
    d[rng.random((h, w)) < holes] = np.nan
    return d


@given(st.integers(1, 30), st.integers(1, 30), seeds, st.floats(0.1, 0.9))
@settings(max_examples=60, deadline=None)
def test_fill_holes_is_scipys(h, w, seed, share):
    m = np.random.default_rng(seed).random((h, w)) < share
    np.testing.assert_array_equal(fill_holes(m), ndimage.binary_fill_holes(m))


@given(st.integers(1, 30), st.integers(1, 30), seeds, st.booleans())
@settings(max_examples=60, deadline=None)
def test_label_extents_are_find_objects_spans(h, w, seed, eight):
    m = np.random.default_rng(seed).random((h, w)) < 0.4
    lab, n = ndimage.label(m, np.ones((3, 3)) if eight else None)
    rows, cols = label_extents(lab.astype(np.int32), n)
    want = [(a.stop - a.start, b.stop - b.start) for a, b in ndimage.find_objects(lab)]
    assert list(zip(rows.tolist(), cols.tolist())) == want


@given(st.integers(1, 20), st.integers(1, 20), seeds, st.integers(0, 12))
@settings(max_examples=60, deadline=None)
def test_in_labels_is_isin(h, w, seed, k):
    rng = np.random.default_rng(seed)
    lab = rng.integers(0, 9, (h, w)).astype(np.int32)
    ids = rng.integers(0, 14, k)
    np.testing.assert_array_equal(_in_labels(lab, ids), np.isin(lab, ids))
    np.testing.assert_array_equal(_in_labels(ids, lab[0]), np.isin(ids, lab[0]))


@given(st.integers(2, 40), st.integers(2, 40), seeds, st.booleans())
@settings(max_examples=60, deadline=None)
def test_near_front_is_the_band_and_reach_in_numpy(h, w, seed, reach):
    """hand_region's band and reach: the depths within the band whose points lie within reach of the
    seed's centre, with the points back-projected as ops._points does (the seed's own by _seed_points)."""
    rng = np.random.default_rng(seed)
    d = _depth(rng, h, w)
    seed_px = rng.random((h, w)) < 0.2
    seed_px &= np.isfinite(d)
    seed_px[0, 0], d[0, 0] = True, 0.6
    focal, centre, front, band, r = 300.0, (rng.uniform(0, h), rng.uniform(0, w)), 0.6, 0.3, 0.05
    X = _points(d, focal, centre)
    np.testing.assert_array_equal(_seed_points(d, seed_px, focal, *centre), X[seed_px])
    c = X[seed_px].mean(axis=0)
    with np.errstate(invalid="ignore"):
        want = np.isfinite(d) & (d <= front + band) & (d >= front - band)
        if reach:
            want &= _sq_dist(X, c) <= r ** 2
    got = near_front(d, front - band, front + band, reach, focal, centre[0], centre[1], *c, r ** 2)
    np.testing.assert_array_equal(got, want)


@given(st.integers(2, 30), st.integers(2, 30), seeds, st.booleans(), st.booleans(), st.integers(0, 200))
@settings(max_examples=80, deadline=None)
def test_valid_pixels_is_the_volume_skin_and_plane_in_numpy(h, w, seed, colour, plane, least):
    """Segmenter._valid compiled: the working volume, the skin test when enough pixels pass it, the plane's
    band left out — on strided views (the coarse search's), as the numpy expressions gave them."""
    rng = np.random.default_rng(seed)
    d = _depth(rng, 2 * h, 2 * w)[::2, ::2]
    c = rng.integers(0, 256, (2 * h, 2 * w, 3)).astype(np.uint8)[::2, ::2]
    c[rng.random((h, w)) < 0.5] = (224, 172, 140)  # skin
    pl = SupportPlane((0.0, 0.6, 0.8), 0.9, 0.05, 1.0) if plane else None
    at = (300.0, rng.uniform(0, h), rng.uniform(0, w))
    seg = Segmenter(min_pixels=least)
    with np.errstate(invalid="ignore"):
        want = np.isfinite(d) & (d > seg.z_min) & (d < seg.z_max)
    if colour:
        skin = skin_mask(c) & want
        if skin.sum() >= least:
            want = skin
    if plane:
        want &= ~pl.pixels(d, *at)
    np.testing.assert_array_equal(seg._valid(d, c if colour else None, None, plane=pl, at=at), want)
    # with the depths there and the working volume's, as Segmenter._segment used np.where for them
    args = seg._compiled_valid(c if colour else None, pl, at, True)
    valid, dv, d_all = valid_depths(np.asarray(d, np.float64), *args)
    np.testing.assert_array_equal(valid, want)
    np.testing.assert_array_equal(dv, np.where(want, d, np.nan))
    np.testing.assert_array_equal(d_all, np.where(seg._valid(d, None, None), d, np.nan))


def _ransac_one_at_a_time(P, w, tries, tol, every, keep, max_cos):
    """plane_ransac as it was written before the planes were weighed four at a time (each plane's weight
    by _plane_weight), the reference."""
    from tracker._segment_kernels import _plane_weight

    K = len(tries)
    N, D, S = np.zeros((K, 3)), np.zeros(K), np.full(K, -1.0)
    for k in range(K):
        a, b, c = P[tries[k, 0]], P[tries[k, 1]], P[tries[k, 2]]
        e1, e2 = b - a, c - a
        n = np.array([e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]])
        s = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if s < 1e-9:
            continue
        n /= s
        m = a + b + c
        if abs(n[0] * m[0] + n[1] * m[1] + n[2] * m[2]) > max_cos * np.sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]):
            continue
        N[k], D[k] = n, n[0] * a[0] + n[1] * a[1] + n[2] * a[2]
        S[k] = _plane_weight(P, w, n, D[k], tol, every)
    order = np.argsort(-S, kind="mergesort")
    best = (np.zeros(3), 0.0, 0.0)
    for j in range(min(keep, K)):
        k = order[j]
        if S[k] < 0.0:
            break
        total = _plane_weight(P, w, N[k], D[k], tol, 1)
        if total > best[2]:
            best = (N[k].copy(), D[k], total)
    return best


@given(seeds, st.integers(3, 400), st.integers(1, 40), st.integers(1, 9), st.integers(1, 8))
@settings(max_examples=60, deadline=None)
def test_plane_ransac_weighs_four_planes_as_one_at_a_time(seed, n, tries, every, keep):
    """The four-at-a-time weights are each plane's own sum: the same plane, offset and weight to the bit
    (points on a tilted plane with outliers, duplicate triplets, collinear ones)."""
    from tracker._segment_kernels import plane_ransac

    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n)
    P = np.stack([x, y, 1.0 + 0.6 * y + 0.01 * rng.standard_normal(n)], 1)
    P[rng.random(n) < 0.3, 2] += rng.uniform(-0.3, 0.3)
    P[:3] = P[0]  # a degenerate triplet
    w = rng.uniform(0.0, 1e-3, n)
    T = rng.integers(0, n, (tries, 3))
    T[0] = (0, 1, 2)
    got = plane_ransac(P, w, T, 0.012, every, keep, 0.87)
    want = _ransac_one_at_a_time(P, w, T, 0.012, every, keep, 0.87)
    np.testing.assert_array_equal(got[0], want[0])
    assert (got[1], got[2]) == (want[1], want[2])


@given(st.integers(1, 30), st.integers(1, 30), seeds)
@settings(max_examples=40, deadline=None)
def test_mask_sums_give_nonzeros_means(h, w, seed):
    from tracker._segment_kernels import mask_sums

    m = np.random.default_rng(seed).random((h, w)) < 0.3
    m[h // 2, w // 2] = True
    n, sr, sc = mask_sums(m)
    v, u = np.nonzero(m)
    assert (n, sr / n + 3, sc / n + 5) == (v.size, float(v.mean()) + 3, float(u.mean()) + 5)


@given(st.integers(2, 30), st.integers(2, 30), seeds)
@settings(max_examples=40, deadline=None)
def test_touch_close_is_the_numpy_test(h, w, seed):
    from tracker._segment_kernels import touch_close
    from tracker.segment.ops import _nearest

    rng = np.random.default_rng(seed)
    region = rng.random((h, w)) < 0.2
    region[0, 0] = True
    d, da = _depth(rng, h, w), _depth(rng, h, w)
    dist, iy, ix = _nearest(region)
    with np.errstate(invalid="ignore"):
        want = (dist <= 3) & (np.abs(da - d[iy, ix]) <= 0.2)
    np.testing.assert_array_equal(touch_close(dist, iy, ix, da, d, 3.0, 0.2), want)


@given(st.integers(1, 25), st.integers(1, 25), seeds, st.integers(1, 14))
@settings(max_examples=80, deadline=None)
def test_touches_border_is_the_four_slices(h, w, seed, px):
    from tracker.segment.surfaces import _touches_border

    m = np.random.default_rng(seed).random((h, w)) < 0.03
    want = bool(m[:px].any() or m[-px:].any() or m[:, :px].any() or m[:, -px:].any())
    assert _touches_border(m, px) == want
    assert _touches_border(m[::2, 1:], px) == bool(m[::2, 1:][:px].any() or m[::2, 1:][-px:].any()
                                                   or m[::2, 1:][:, :px].any() or m[::2, 1:][:, -px:].any())
