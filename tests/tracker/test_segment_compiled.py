"""The segmenter's compiled shortcuts (issue 39's segmentation speed) against the numpy and scipy
expressions they replace: each must give the same values to the bit, or the segmentation changes."""
import numpy as np
from hypothesis import given, settings, strategies as st
from scipy import ndimage

from tracker._segment_kernels import fill_holes, label_extents, near_front, valid_pixels
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
