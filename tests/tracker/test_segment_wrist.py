"""The wrist cut and the finger test compiled whole (issue 39's segmentation speed) against the numpy rules
they replace (:func:`tracker.segment.forearm._cut_reference` and the functions it calls): the same pixels
to the bit on drawn hands — a palm, fingers spread or together, an arm going on past the crop's edge or
into another object, a fist at the arm's end — or the segmentation changes."""
import numpy as np
from hypothesis import given, settings, strategies as st

from tracker._segment_kernels import (blob_labels, closed_filled, filled_places, finger_pieces, front_layer, np_sum,
                                      join_surfaces, palm_place, percentile_linear, reach_part, uniform1d, wrist_cut)
from tracker.segment import constants as K
from tracker.segment.fingers import (_enough_fingers, _far_end, _far_end_reference, _finger_pieces, _finger_reference,
                                     _pieces_reference)
from tracker.segment.ops import _edt, _nearest, _points
from tracker.segment.layers import _front_reference, _join_reference
from tracker.segment.forearm import _cut_reference, _filled_places, _filled_reference, _hand_end_palm
from tracker.segment.region import _blobs_reference, _edge_pieces, _edge_reference
from tracker.segment.ops import _uniform1d

seeds = st.integers(0, 2**32 - 1)


def _limb(m, y0, x0, angle, length, width):
    """Draw a straight limb of ``width`` px from ``(y0, x0)`` along ``angle`` for ``length`` px into ``m``."""
    yy, xx = np.mgrid[:m.shape[0], :m.shape[1]]
    dy, dx = np.sin(angle), np.cos(angle)
    t = (yy - y0) * dy + (xx - x0) * dx
    s = np.abs(-(yy - y0) * dx + (xx - x0) * dy)
    m |= (t >= 0) & (t <= length) & (s <= width / 2)


def _hand(seed):
    """A drawn hand in a crop: ``(solid, cy, cx, r, go_on, touch)`` with the palm's centre at its widest place."""
    rng = np.random.default_rng(seed)
    h, w = rng.integers(30, 90, 2)
    cy, cx = int(rng.integers(h // 4, 3 * h // 4)), int(rng.integers(w // 4, 3 * w // 4))
    r = float(rng.uniform(4.0, 12.0))
    yy, xx = np.mgrid[:h, :w]
    solid = np.hypot(yy - cy, xx - cx) <= r * rng.uniform(1.0, 1.5)
    arm = rng.uniform(0, 2 * np.pi)
    if rng.random() < 0.85:
        _limb(solid, cy, cx, arm, rng.uniform(2, 12) * r, rng.uniform(0.8, 2.2) * r)
    spread = rng.uniform(0.15, 0.5)
    for k in range(rng.integers(0, 6)):
        a = arm + np.pi + (k - 2) * spread + rng.normal(0, 0.1)
        _limb(solid, cy, cx, a, rng.uniform(1.5, 4.5) * r, rng.uniform(0.3, 0.8) * r)
    if rng.random() < 0.3:  # a thumb touching the arm outside the palm circle
        _limb(solid, cy + int(2.2 * r * np.sin(arm + 0.6)), cx + int(2.2 * r * np.cos(arm + 0.6)), arm,
              rng.uniform(1, 3) * r, 0.5 * r)
    solid ^= rng.random((h, w)) < rng.choice([0.0, 0.01, 0.03])  # outline noise and holes
    solid[cy, cx] = True
    go_on = np.zeros_like(solid)
    edges = rng.random(4) < 0.5
    go_on[:1] |= edges[0]
    go_on[-1:] |= edges[1]
    go_on[:, :1] |= edges[2]
    go_on[:, -1:] |= edges[3]
    go_on &= solid
    touch = (rng.random((h, w)) < 0.05) & solid if rng.random() < 0.3 else None
    return solid, cy, cx, r, go_on, touch


def _both(seed, at_end, m_px):
    solid, cy, cx, r, go_on, touch = _hand(seed)
    T = K.TUNING
    made, cut = wrist_cut(solid, cy, cx, r, go_on, np.zeros((1, 1), bool) if touch is None else touch,
                          touch is not None, m_px, at_end, 0.9, 2.6, T.arm_reach_r, T.opposite_arm_reach_r,
                          T.sure_arm_reach_r, T.finger_max_m, float(np.cos(np.radians(T.arm_bend_deg))),
                          T.taper_window_r, T.taper_min_samples, T.no_narrowing_wrist, T.heel_reach_r,
                          T.heel_width_tol)
    want = _cut_reference(solid, cy, cx, r, go_on, touch, m_px, at_end)
    return made, cut, want


@given(seeds, st.booleans(), st.floats(0.0005, 0.006))
@settings(max_examples=150, deadline=None)
def test_wrist_cut_is_the_numpy_rules(seed, at_end, m_px):
    made, cut, want = _both(seed, at_end, m_px)
    assert made == (want is not None)
    if made:
        np.testing.assert_array_equal(cut, want)


def test_drawn_hands_are_cut_in_most_crops():
    """The comparison above is not vacuous: most drawn hands with an arm are cut, by both, and some not."""
    made = [_both(seed, at_end, 0.002)[0] for seed in range(60) for at_end in (False, True)]
    assert 0.3 * len(made) < sum(made) < len(made)


@given(st.lists(st.floats(-1e3, 1e3) | st.sampled_from([0.0, -0.0]), max_size=400))
@settings(max_examples=150, deadline=None)
def test_np_sum_is_numpys_pairwise_sum(values):
    a = np.array(values, dtype=np.float64)
    assert np.float64(np_sum(a)).tobytes() == np.sum(a).tobytes()


@given(st.lists(st.floats(0, 500, allow_nan=False), min_size=1, max_size=80), st.integers(1, 9))
@settings(max_examples=100, deadline=None)
def test_uniform1d_is_the_running_sum(values, size):
    x = np.array(values)
    np.testing.assert_array_equal(uniform1d(x, size), _uniform1d(x, size))


@given(st.integers(1, 40), st.integers(1, 40), seeds, st.floats(0.5, 9.0), st.floats(0.0, 0.3), st.floats(0.5, 1.0))
@settings(max_examples=100, deadline=None)
def test_filled_places_is_the_numpy_expression(h, w, seed, rad, slack, least):
    """The palm's candidate places kept by how well the mask before closing fills their disk."""
    rng = np.random.default_rng(seed)
    raw = rng.random((h, w)) < rng.uniform(0.3, 1.0)
    cand = rng.random((h, w)) < rng.uniform(0.0, 0.3)
    np.testing.assert_array_equal(filled_places(cand, raw, rad, slack, least),
                                  _filled_reference(cand, raw, rad, slack, least))


@given(st.integers(1, 50), st.integers(1, 50), seeds, st.floats(200.0, 3000.0))
@settings(max_examples=100, deadline=None)
def test_finger_pieces_are_the_numpy_moments(h, w, seed, px_m):
    """The finger test's pieces: labels, sizes and which are finger-like, on random masks and on drawn
    fingers (thin limbs, which pass the test)."""
    rng = np.random.default_rng(seed)
    thin = rng.random((h, w)) < rng.uniform(0.05, 0.6)
    for _ in range(rng.integers(0, 4)):
        _limb(thin, rng.integers(0, h), rng.integers(0, w), rng.uniform(0, 2 * np.pi), rng.uniform(3, 40),
              rng.uniform(1, 6))
    T = K.TUNING
    got = finger_pieces(thin, T.finger_min_area_m2 * px_m ** 2, T.finger_elongation ** 2, T.finger_min_length_m * px_m,
                        0, 0)
    want = _pieces_reference(thin, px_m)
    for g, wnt in zip(got, want):
        np.testing.assert_array_equal(g, wnt)
        assert g.dtype == wnt.dtype


def _labelled(rng, h, w):
    """Random labels 0-9 in patches and depths (finite where labelled, some NaN elsewhere)."""
    lab = np.repeat(np.repeat(rng.integers(0, 10, (h // 2 + 1, w // 2 + 1)), 2, 0), 2, 1)[:h, :w].astype(np.int32)
    d = rng.uniform(0.4, 0.6, (h, w))
    d[(lab == 0) & (rng.random((h, w)) < 0.5)] = np.nan
    return lab, d


@given(st.integers(1, 40), st.integers(1, 40), seeds, st.floats(1e-6, 1e-3))
@settings(max_examples=100, deadline=None)
def test_blob_labels_are_the_numpy_selection(h, w, seed, blob_area):
    """hand_region's fingertip blobs: the candidates' labels whose band pixels cover less than blob_area."""
    rng = np.random.default_rng(seed)
    lab, d = _labelled(rng, h, w)
    near = np.isfinite(d) & (rng.random((h, w)) < 0.8)
    zone, core = rng.random((h, w)) < 0.7, rng.random((h, w)) < 0.2
    k = int(rng.integers(0, 10))
    got = blob_labels(lab, d, zone, near, core, k, 9, 300.0, blob_area)
    np.testing.assert_array_equal(got, _blobs_reference(lab, d, zone, near, core, k, 300.0, blob_area))


@given(st.integers(1, 40), st.integers(1, 40), seeds, st.integers(0, 3), st.floats(0.0, 0.1))
@settings(max_examples=100, deadline=None)
def test_edge_pieces_are_the_filters_in_numpy(h, w, seed, gap, jump):
    """The small pieces lying at another big surface's depths next to it."""
    rng = np.random.default_rng(seed)
    lab, d = _labelled(rng, h, w)
    small = rng.choice(np.arange(1, 10), rng.integers(1, 5), replace=False)
    others = rng.choice(np.arange(1, 12), rng.integers(1, 5), replace=False)  # some not in the image
    np.testing.assert_array_equal(_edge_pieces(lab, d, small, others, jump, gap),
                                  _edge_reference(lab, d, small, others, jump, gap))


@given(st.lists(st.floats(0.2, 2.0) | st.sampled_from([0.5, 0.5000000000000001, np.nan]), min_size=1, max_size=300),
       st.floats(0.0, 100.0))
@settings(max_examples=150, deadline=None)
def test_percentile_linear_is_numpys(values, p):
    """numpy's percentile (its quantile p / 100), to the bit; NaN with a NaN among the values."""
    a = np.array(values)
    for pct in (p, 1):
        got, want = percentile_linear(a, np.true_divide(pct, 100)), np.percentile(a, pct)
        assert np.float64(got).tobytes() == np.float64(want).tobytes() or (np.isnan(got) and np.isnan(want))


@given(seeds, st.integers(0, 6))
@settings(max_examples=100, deadline=None)
def test_far_end_is_the_numpy_expressions(seed, px):
    """An arm entering the image: the end farthest from where the surface touches the border."""
    rng = np.random.default_rng(seed)
    h, w = rng.integers(20, 70, 2)
    surface = np.zeros((h, w), bool)
    _limb(surface, rng.choice([0, h - 1]), rng.integers(0, w), rng.uniform(0, 2 * np.pi), rng.uniform(10, 80),
          rng.uniform(3, 14))
    surface[rng.integers(0, h), rng.integers(0, w)] = True
    surface ^= rng.random((h, w)) < 0.02
    d = np.where(surface, rng.uniform(0.4, 0.7, (h, w)), np.nan)
    X = _points(d, 300.0, (rng.uniform(0, h), rng.uniform(0, w)))
    reach = rng.choice([0.22, 0.05, None])
    seed_px, front = _far_end(surface, d, X, 300.0, px, reach)
    want_seed, want_front = _far_end_reference(surface, d, X, 300.0, px, reach)
    np.testing.assert_array_equal(seed_px, want_seed)
    assert np.float64(front).tobytes() == np.float64(want_front).tobytes()


@given(seeds, st.floats(300.0, 1500.0), st.integers(0, 30), st.integers(0, 30))
@settings(max_examples=100, deadline=None)
def test_finger_pieces_on_the_masks_box_are_the_whole_windows(seed, px_m, top, left):
    """_finger_pieces works on the mask's bounding box: labels, sizes and the finger-like pieces are the
    whole window's (the opening, the rim's distances and the moments there, numpy), on drawn hands placed
    anywhere in a larger window."""
    rng = np.random.default_rng(seed)
    solid, *_ = _hand(seed)
    h, w = solid.shape
    o = np.zeros((h + top + int(rng.integers(0, 30)), w + left + int(rng.integers(0, 30))), bool)
    o[top:top + h, left:left + w] = solid
    for g, want in zip(_finger_pieces(o, px_m), _finger_reference(o, px_m)):
        np.testing.assert_array_equal(g, want)


@given(seeds, st.floats(0.0, 0.1))
@settings(max_examples=150, deadline=None)
def test_palm_place_is_the_farthest_candidate_or_the_hand_end(seed, dropped):
    """Where the region goes on: the widest filled place farthest from there, or the palm at the far end
    (_hand_end_palm), as numpy chose them; on drawn hands with pixels dropped from the mask before closing."""
    solid, cy, cx, r, go_on, _ = _hand(seed)
    if not go_on.any():
        go_on[np.unravel_index(int(np.argmax(solid)), solid.shape)] = True
    rng = np.random.default_rng(seed)
    sub = solid & (rng.random(solid.shape) >= dropped)
    dt = _edt(~solid)
    far = _edt(go_on)
    cand = _filled_places(dt >= K.TUNING.palm_width_share * dt.max(), sub, float(dt.max()))
    T = K.TUNING
    got = palm_place(cand, far, dt, sub, solid, T.arm_reach_r, T.hand_end_width_share, T.palm_width_share,
                     T.palm_fill_slack, T.palm_fill_min)
    py, px = np.unravel_index(int(np.argmax(np.where(cand, far, -1.0))), dt.shape)
    want = _hand_end_palm(py, px, dt, sub, solid, far)
    assert (int(got[0]), int(got[1]), bool(got[2])) == (int(want[0]), int(want[1]), bool(want[2]))


@given(seeds, st.floats(0.0, 0.05), st.integers(3, 12), st.floats(0.0, 0.01), st.booleans(), st.sampled_from([30.0, 300.0]))
@settings(max_examples=150, deadline=None)
def test_front_layer_is_the_numpy_expressions(seed, gap, half, min_area, with_surface, focal):
    """_in_front's test: a drawn hand ``gap`` m in front of a body, its arm sinking into the body, with
    noise and dropouts; the status and the layer, outline and step masks as numpy found them (a short
    focal length makes the pixels big enough for every status, the layer taken too)."""
    rng = np.random.default_rng(seed)
    region, *_ = _hand(seed)
    h, w = region.shape
    d = 0.6 + rng.normal(0, 0.002, (h, w))
    d[region] -= gap
    sink = rng.random((h, w)) < rng.uniform(0, 0.4)
    d[region & sink] += gap * rng.uniform(0, 1)
    d[rng.random((h, w)) < 0.03] = np.nan
    region &= np.isfinite(d)
    if not region.any():
        return
    surface = np.isfinite(d) & (rng.random((h, w)) < 0.9) if with_surface else None
    (ya, xa), (yb, xb) = (int(v) for v in np.argwhere(region).min(0)), (int(v) for v in np.argwhere(region).max(0))
    big = (slice(max(ya - half, 0), min(yb + half + 1, h)), slice(max(xa - half, 0), min(xb + half + 1, w)))
    win = (slice(max(ya - 3, 0), min(yb + 4, h)), slice(max(xa - 3, 0), min(xb + 4, w)))
    back = region[big] if surface is None else (surface | region)[big]
    T = K.TUNING
    got = front_layer(d, np.ascontiguousarray(back), region, big[0].start, big[0].stop, big[1].start, big[1].stop,
                      win[0].start, win[0].stop, win[1].start, win[1].stop, half, T.front_step_m, 0.02, focal,
                      min_area, T.front_outline_share, T.front_behind_area_m2)
    want = _front_reference(region, d, back, big, win, half, 0.02, focal, min_area)
    assert got[0] == want[0]
    for g, wnt in zip(got[1:], want[1:]):
        np.testing.assert_array_equal(g, wnt)


@given(seeds, st.integers(0, 6), st.integers(0, 12))
@settings(max_examples=150, deadline=None)
def test_nearest_targets_within_px_are_the_boxs(seed, px, margin):
    """_joins transforms the region's box grown by px, not its whole window: every pixel within px of the
    region gets the same nearest region pixel (ties as scipy's transform sends them) and distance."""
    rng = np.random.default_rng(seed)
    h, w = rng.integers(5, 60, 2)
    region = rng.random((h, w)) < rng.uniform(0.01, 0.5)
    region[rng.integers(0, h), rng.integers(0, w)] = True
    (ya, xa), (yb, xb) = (int(v) for v in np.argwhere(region).min(0)), (int(v) for v in np.argwhere(region).max(0))
    win = (slice(max(ya - px - margin, 0), min(yb + px + margin + 1, h)),
           slice(max(xa - px - margin, 0), min(xb + px + margin + 1, w)))
    near = (slice(max(ya - px, 0), min(yb + px + 1, h)), slice(max(xa - px, 0), min(xb + px + 1, w)))
    dist, iy, ix = _nearest(region[win])
    sd, sy, sx = _nearest(region[near])
    oy, ox = near[0].start - win[0].start, near[1].start - win[1].start
    dist_n = dist[oy:oy + sd.shape[0], ox:ox + sd.shape[1]]
    within = dist <= px
    assert within.sum() == (sd <= px).sum()  # no pixel within px lies outside the box
    keep = sd <= px
    np.testing.assert_array_equal(sd[keep], dist_n[keep])
    np.testing.assert_array_equal(sy[keep] + oy, iy[oy:oy + sd.shape[0], ox:ox + sd.shape[1]][keep])
    np.testing.assert_array_equal(sx[keep] + ox, ix[oy:oy + sd.shape[0], ox:ox + sd.shape[1]][keep])


@given(seeds, st.floats(300.0, 1500.0), st.floats(3.0, 60.0))
@settings(max_examples=100, deadline=None)
def test_the_reach_part_closed_in_its_box_is_the_windows(seed, px_m, r):
    """_has_fingers' part: the surface within r of a point (numpy's grid arithmetic), and its closing and
    filling done in its box grown by a pixel — the whole window's pixels there, the same finger verdict."""
    rng = np.random.default_rng(seed)
    solid, *_ = _hand(seed)
    surface = np.zeros((solid.shape[0] + 40, solid.shape[1] + 40), bool)
    surface[20:-20, 20:-20] = solid
    h, w = surface.shape
    cy, cx = rng.uniform(0, h), rng.uniform(0, w)
    ri = int(np.ceil(r))
    y0, y1, x0, x1 = max(int(cy) - ri, 0), min(int(cy) + ri + 1, h), max(int(cx) - ri, 0), min(int(cx) + ri + 1, w)
    yy, xx = np.ogrid[y0:y1, x0:x1]
    want = surface[y0:y1, x0:x1] & ((yy - cy) ** 2 + (xx - cx) ** 2 <= ri * ri)
    part, ya, yb, xa, xb = reach_part(surface, y0, y1, x0, x1, cy, cx, ri)
    np.testing.assert_array_equal(part, want)
    if not want.any():
        assert ya < 0
        return
    rows, cols = np.flatnonzero(want.any(1)), np.flatnonzero(want.any(0))
    assert (ya, yb, xa, xb) == (rows[0], rows[-1], cols[0], cols[-1])
    ya, xa = max(ya - 1, 0), max(xa - 1, 0)
    box = part[ya:yb + 2, xa:xb + 2]
    whole = closed_filled(want)
    np.testing.assert_array_equal(closed_filled(np.ascontiguousarray(box)), whole[ya:yb + 2, xa:xb + 2])
    assert not whole[:ya].any() and not whole[yb + 2:].any() and not whole[:, :xa].any() and not whole[:, xb + 2:].any()
    assert _enough_fingers(closed_filled(np.ascontiguousarray(box)), px_m, (ya, xa)) == _enough_fingers(whole, px_m)
    for g, wnt in zip(_finger_pieces(closed_filled(np.ascontiguousarray(box)), px_m, (ya, xa))[1:],
                      _finger_pieces(whole, px_m)[1:]):
        np.testing.assert_array_equal(g[1:], wnt[1:])  # sizes and verdicts of the pieces (0: no piece)


@given(seeds, st.floats(0.0, 0.05), st.sampled_from([30.0, 300.0]), st.floats(0.0, 0.01))
@settings(max_examples=100, deadline=None)
def test_join_surfaces_are_the_numpy_expressions(seed, jump, focal, min_area):
    """_joins' surfaces met at the contact: the contact's pixels on a big enough surface off the hand's."""
    rng = np.random.default_rng(seed)
    lab, d = _labelled(rng, int(rng.integers(1, 40)), int(rng.integers(1, 40)))
    d += rng.normal(0, 0.01, d.shape)
    surface = lab == rng.integers(0, 10)
    close = rng.random(d.shape) < 0.5
    np.testing.assert_array_equal(join_surfaces(d, surface, close, jump, focal, min_area),
                                  _join_reference(d, surface, close, jump, focal, min_area))
