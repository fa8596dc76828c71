"""Numba kernels of the correspondences (:mod:`tracker.correspond`): the closest-point pass of the
data on the capsule model and its local pass (:func:`match_same`), the model samples posed, and the
model→data cost's mean. Tested against the numpy definitions in :mod:`tracker.correspond`
(tests/tracker/test_icp_compiled.py)."""
from __future__ import annotations

import numpy as np
from numba import njit

from handmodel._geometry_kernels import closest_on_primitive, closest_points_facing, to_world
from handmodel.kinematics import fk_single

from ._kernel_arrays import HandArrays, SampleArrays, SilhouetteArrays

#: below this depth (m) a model point is at or behind the camera: it has no pixel
MIN_DEPTH_M = 1e-3
MM = 1000.0


@njit(cache=True, inline="always")
def hand_frames(theta, hand, G, wa, wo):
    """The node frames of ``hand`` (:class:`~tracker._kernel_arrays.HandArrays`) at θ into ``G``
    (``wa``/``wo``: the DoF axes and origins, scratch)."""
    fk_single(theta, hand.parents, hand.rest, hand.dof_ptr, hand.dof_idx, hand.dof_types, hand.dof_axes, G, wa, wo)


@njit(cache=True, inline="always")
def new_frames(hand):
    """Scratch for :func:`hand_frames`: ``(G, wa, wo)``."""
    n = hand.dof_axes.shape[0]
    return np.empty((hand.parents.shape[0], 4, 4)), np.empty((n, 3)), np.empty((n, 3))


@njit(cache=True)
def match(G, caps, points, normals, rules, out):
    """Data→model pairs at the node frames ``G`` (:class:`tracker.correspond.Matcher` with capsules,
    ``caps``: :class:`~tracker._kernel_arrays.CapsuleArrays`) into ``out``
    (:class:`~tracker._kernel_arrays.Pairs`): the closest front-facing capsule point, rejected
    (:class:`~tracker._kernel_arrays.MatchRules`) at ``reject_m`` or farther and, with data
    ``normals`` (rows; NaN rows unknown), when the normals' cosine is below ``agreement`` (−1 = off).
    Returns the number of valid pairs."""
    closest_points_facing(G, caps.node, caps.shape, caps.length, caps.r0, caps.r1, caps.thickness, points,
                          rules.camera, rules.facing_only, out.p, out.n, out.seg, out.d)
    return kept_pairs(caps, points, normals, rules, out)


@njit(cache=True, inline="always")
def kept_pairs(caps, points, normals, rules, out):
    """The pairs of a closest-point pass in ``out`` (its ``seg``, ``n``, ``d``): each point's node, and whether
    its pair is kept (:func:`match`'s rules); returns the number kept. The fits' own passes
    (:mod:`tracker._fit_kernels`) end with it too."""
    # the tuples' arrays as locals before the loop: an array taken from a tuple inside it costs a
    # reference count update at each use
    node, seg, out_n, out_d, out_node, out_valid = caps.node, out.seg, out.n, out.d, out.node, out.valid
    reject, agreement = rules.reject_m, rules.agreement
    use_n = normals.shape[0] == points.shape[0] and agreement > -1.0
    nv = 0
    for i in range(points.shape[0]):
        s = seg[i]
        out_node[i] = node[s] if s >= 0 else 0
        ok = s >= 0 and _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n)
        out_valid[i] = ok
        if ok:
            nv += 1
    return nv


@njit(cache=True, inline="always")
def _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n):
    """Pair ``i`` kept: nearer than ``reject`` and, with normals, agreeing by at least ``agreement``."""
    if not out_d[i] < reject:  # as written, a NaN distance is rejected
        return False
    if use_n:
        c = normals[i, 0] * out_n[i, 0] + normals[i, 1] * out_n[i, 1] + normals[i, 2] * out_n[i, 2]
        if c < agreement:  # NaN (unknown normal) keeps the pair
            return False
    return True


@njit(cache=True)
def match_same(G, caps, points, normals, rules, out):
    """:func:`match` with every point kept on the primitive it was matched to (``out.seg``): its
    closest point there at the frames ``G``, no search over the others (a point whose primitive now
    faces away, or that had none, is left unpaired). Returns the number of valid pairs."""
    # the tuples' arrays as locals before the loop (see match)
    out_p, out_n, out_d, out_valid, seg = out.p, out.n, out.d, out.valid, out.seg
    node, shape, length, r0, r1, thickness = caps.node, caps.shape, caps.length, caps.r0, caps.r1, caps.thickness
    cam, facing_only, reject, agreement = rules.camera, rules.facing_only, rules.reject_m, rules.agreement
    use_n = normals.shape[0] == points.shape[0] and agreement > -1.0
    q = np.empty(3)
    loc = np.empty(7)
    nv = 0
    for i in range(points.shape[0]):
        s = seg[i]
        out_valid[i] = False
        if s < 0:
            continue
        j = node[s]
        closest_on_primitive(G, j, shape[s], length[s], r0[s], r1[s], thickness[s], points[i, 0], points[i, 1],
                             points[i, 2], q, loc)
        to_world(G, j, loc, out_p[i], out_n[i])
        out_d[i] = abs(loc[6])
        if facing_only:
            view = ((out_p[i, 0] - cam[0]) * out_n[i, 0] + (out_p[i, 1] - cam[1]) * out_n[i, 1]
                    + (out_p[i, 2] - cam[2]) * out_n[i, 2])
            if view > 0.0:
                continue
        ok = _pair_ok(normals, out_n, out_d, i, reject, agreement, use_n)
        out_valid[i] = ok
        if ok:
            nv += 1
    return nv

@njit(cache=True)
def pose_samples(theta, hand, samples, P, N):
    """Model surface ``samples`` stored in their nodes' frames (:class:`tracker.correspond.ModelSamples`
    as :class:`~tracker._kernel_arrays.SampleArrays`) posed at θ: points into ``P``, normals into
    ``N`` (what ``ModelSamples.pose`` returns)."""
    G, wa, wo = new_frames(hand)
    hand_frames(theta, hand, G, wa, wo)
    nodes, local, local_n = samples.nodes, samples.local, samples.local_n
    for i in range(nodes.shape[0]):
        j = nodes[i]
        l0, l1, l2 = local[i, 0], local[i, 1], local[i, 2]
        n0, n1, n2 = local_n[i, 0], local_n[i, 1], local_n[i, 2]
        for r in range(3):
            P[i, r] = G[j, r, 0] * l0 + G[j, r, 1] * l1 + G[j, r, 2] * l2 + G[j, r, 3]
            N[i, r] = G[j, r, 0] * n0 + G[j, r, 1] * n1 + G[j, r, 2] * n2


@njit(cache=True, nogil=True)
def model_to_data_mean(theta, hand, samples, sil, tolerance_mm, tolerance_px, cap_mm):
    """The mean over the samples of :func:`tracker.correspond.model_to_data_mm` (the model→data part
    of :func:`tracker.init.score`) at θ, the samples posed here: the same per-sample costs, summed in
    order (numpy's mean sums pairwise: equal to ~1e-15 relative). ``samples``:
    :class:`~tracker._kernel_arrays.SampleArrays`, ``sil``: :class:`~tracker._kernel_arrays.SilhouetteArrays`."""
    if samples.nodes.shape[0] == 0:
        return np.nan
    G, wa, wo = new_frames(hand)
    hand_frames(theta, hand, G, wa, wo)
    return _model_to_data_at(G, samples, sil, tolerance_mm, tolerance_px, cap_mm)


@njit(cache=True)
def pose_samples_entry(theta, hand, samples, P, N):
    """:func:`pose_samples` with its named tuples given as plain tuples (:func:`tracker._kernel_arrays.plain`)."""
    pose_samples(theta, HandArrays(*hand), SampleArrays(*samples), P, N)


@njit(cache=True, nogil=True)
def model_to_data_mean_entry(theta, hand, samples, sil, tolerance_mm, tolerance_px, cap_mm):
    """:func:`model_to_data_mean` with its named tuples given as plain tuples."""
    return model_to_data_mean(theta, HandArrays(*hand), SampleArrays(*samples), SilhouetteArrays(*sil),
                              tolerance_mm, tolerance_px, cap_mm)


@njit(cache=True, inline="always")
def _model_to_data_at(G, samples, sil, tolerance_mm, tolerance_px, cap_mm):
    """:func:`model_to_data_mean` with the samples' node frames ``G`` given."""
    nodes, local = samples.nodes, samples.local
    fx, fy, cx, cy, dist, depth, v0, u0 = sil.fx, sil.fy, sil.cx, sil.cy, sil.dist, sil.depth, sil.v0, sil.u0
    n = nodes.shape[0]
    if n == 0:
        return np.nan
    h, w = dist.shape
    H, W = depth.shape
    total = 0.0
    for i in range(n):
        j = nodes[i]
        l0, l1, l2 = local[i, 0], local[i, 1], local[i, 2]
        x = G[j, 0, 0] * l0 + G[j, 0, 1] * l1 + G[j, 0, 2] * l2 + G[j, 0, 3]
        y = G[j, 1, 0] * l0 + G[j, 1, 1] * l1 + G[j, 1, 2] * l2 + G[j, 1, 3]
        z = G[j, 2, 0] * l0 + G[j, 2, 1] * l1 + G[j, 2, 2] * l2 + G[j, 2, 3]
        if not z > MIN_DEPTH_M:
            total += cap_mm
            continue
        u = int(np.rint(fx * x / z + cx))
        v = int(np.rint(fy * y / z + cy))
        uu = min(max(u - u0, 0), w - 1)
        vv = min(max(v - v0, 0), h - 1)
        d_px = dist[vv, uu] + np.hypot(float(u - u0 - uu), float(v - v0 - vv))
        if d_px > 0:
            cost = max(d_px - tolerance_px, 0.0) * z / fx * MM
        elif u >= 0 and u < W and v >= 0 and v < H:
            zo = depth[v, u]
            cost = max((zo - z) * MM - tolerance_mm, 0.0) if np.isfinite(zo) else 0.0
        else:
            cost = 0.0
        total += min(cost, cap_mm)
    return total / n


