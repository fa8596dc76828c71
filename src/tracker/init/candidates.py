"""The starts of the single-frame search: global placements from the cloud's principal axes
(:func:`placements`), synergy postures (:func:`posture_candidates`, the coarse :func:`posture_grid`),
the best few that differ in orientation (:func:`diverse`), finger shapes for the finger-wise restarts
(:func:`finger_shapes`, :func:`finger_variants`, :func:`finger_pair_variants`), and the thinned cloud
that ranks them (:func:`thin`)."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from handmodel.geometry import surface_samples
from handmodel.rigid import euler_to_matrix, matrix_to_euler

from .scoring import FitContext


def _palm_side(hand, posture):
    """θ at ``posture`` (pose zero), the model's surface samples and normals there, and the samples of
    its palm-side half (what a camera in front of the palm sees)."""
    base = np.zeros(hand.n_dofs)
    base[~hand.pose_mask] = posture
    S, _, N = surface_samples(hand, base, spacing=0.004)
    return base, S, N, S[N[:, 2] < 0]


def placements(hand, points, posture) -> list[np.ndarray]:
    """Candidate global poses from the cloud: the model's palm-side surface centroid on the data
    centroid, its principal axes on the data's (the four sign choices, each rolled about the main
    axis by 0, ±45 and ±90°: a curled hand's main axis need not be the fingers')."""
    base, S, N, ms = _palm_side(hand, posture)
    # the palm-side half gives the axes only: each placement is centred by the half that faces the
    # camera in it, the palm or the back
    mc = ms.mean(0)
    dc = points.mean(0)
    _, _, Vm = np.linalg.svd(ms - mc, full_matrices=False)
    _, _, Vd = np.linalg.svd(points - dc, full_matrices=False)
    A = np.stack([Vm[0], np.cross(Vm[2], Vm[0]), Vm[2]], 1)
    out = []
    for s1 in (1, -1):
        for s3 in (1, -1):
            d1, d3 = s1 * Vd[0], s3 * Vd[2]
            B = np.stack([d1, np.cross(d3, d1), d3], 1)
            for roll in (0.0, 45.0, -45.0, 90.0, -90.0):
                R = Rotation.from_rotvec(np.radians(roll) * d1).as_matrix() @ B @ A.T
                th = base.copy()
                th[3:6] = matrix_to_euler(R)
                RS = S @ R.T
                seen = RS[(N @ R.T)[:, 2] < 0]
                th[:3] = dc - (seen.mean(0) if len(seen) else R @ mc)
                out.append(th)
    return out


def posture_candidates(synergies, k, n_posture) -> list[np.ndarray]:
    """Start postures: the synergy mean and ±1.5σ along PC1, ±1.2σ along PC2 and PC3 (the first
    ``k`` PCs); zeros without synergies."""
    if synergies is None:
        return [np.zeros(n_posture)]
    out = [synergies.mean_.copy()]
    for pc, amp in ((0, 1.5), (1, 1.2), (2, 1.2))[:k]:
        for sgn in (1, -1):
            coef = np.zeros(pc + 1)
            coef[pc] = sgn * amp
            out.append(synergies.posture(coef))
    return out


def posture_grid(synergies) -> list[np.ndarray]:
    """The coarse search space: PC1 at −2…+2σ, PC2 and PC3 at −1, 0, +1σ, inside the PC limits."""
    return [synergies.posture(np.array([a1, a2, a3]), clip=True)
            for a1 in (-2.0, -1.0, 0.0, 1.0, 2.0) for a2 in (-1.0, 0.0, 1.0) for a3 in (-1.0, 0.0, 1.0)]


def diverse(scored, k, min_deg=60.0) -> list[np.ndarray]:
    """The best ``k`` of ``(score, θ)`` sorted by score whose global rotations differ pairwise by at
    least ``min_deg`` (a palm-facing and a back-facing placement both go on when the cloud alone cannot
    tell them apart), filled up with the next best if fewer are that different."""
    picked, Rs = [], []
    for _, th in scored:
        R = euler_to_matrix(th[3:6])
        if all(math.degrees(math.acos(float(np.clip((np.trace(R @ Q.T) - 1) / 2, -1, 1)))) >= min_deg for Q in Rs):
            picked.append(th)
            Rs.append(R)
            if len(picked) == k:
                return picked
    rest = [th for _, th in scored if not any(th is p for p in picked)]
    return picked + rest[: k - len(picked)]


# finger shapes for finger-wise restarts: flexion (°) of the first, second and third flexion joint
# (MCP, PIP, DIP; for the thumb CMC, MCP, IP): straight, evenly curled, PIP-led curl (a finger flexed
# alone, as in fingerfist), MCP-led bend, hook
FINGER_SHAPES_DEG = ((5.0, 5.0, 5.0), (-25.0, -25.0, -25.0), (-55.0, -55.0, -55.0), (-85.0, -85.0, -85.0),
                     (-45.0, -100.0, -10.0), (-80.0, -20.0, -10.0), (0.0, -90.0, -60.0))


# the shapes (rows of FINGER_SHAPES_DEG) the pair restarts combine: straight, evenly curled and
# fully curled, MCP-led bend and hook (25 combinations a pair instead of 49; half the pairs' cost)
PAIR_SHAPES = (0, 1, 3, 5, 6)


def finger_shapes(hand, limits) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per finger (thumb … pinky): the θ indices of its flexion joints and FINGER_SHAPES_DEG as values
    for them, inside ``limits`` — one row per shape."""
    names = list(hand.dof_names)
    lo, hi = limits[:, 0], limits[:, 1]
    out = []
    for f in ("thumb", "index", "middle", "ring", "pinky"):
        fi = np.array([i for i, n in enumerate(names) if n.startswith(f) and "flex" in n], np.int64)
        if fi.size:
            vals = np.radians([np.resize(shape, fi.size) for shape in FINGER_SHAPES_DEG])
            out.append((fi, np.clip(vals, lo[fi], hi[fi])))
    return out


def finger_variants(theta, shapes, finger=None) -> list[np.ndarray]:
    """Copies of ``theta`` with one finger's flexion joints set to each of its ``shapes``, every
    finger in turn (or only ``finger``, an index into ``shapes``), the rest unchanged."""
    out = []
    for k, (fi, vals) in enumerate(shapes):
        if finger is None or finger == k:
            for v in vals:
                th = np.array(theta, float)
                th[fi] = v
                out.append(th)
    return out


def finger_pair_variants(ctx: FitContext, theta) -> list[tuple[int, np.ndarray]]:
    """The pair restarts: for every two neighbouring fingers among index … pinky (``(k, k+1)`` in
    ``ctx.finger_shapes``), copies of ``theta`` with both fingers set to every combination of their
    ``PAIR_SHAPES`` and both abductions back to the synergy mean's (zero without synergies), as
    ``(k, θ)``.
    A curled finger whose blob its neighbour took (the pinky spread onto the curled ring finger's
    place, the ring curled into the palm) comes back only when both move at once: either alone
    leaves the two on one place."""
    names = list(ctx.hand.dof_names)
    post = np.flatnonzero(~ctx.hand.pose_mask)
    rest = np.zeros(ctx.hand.n_dofs)
    if ctx.synergies is not None:
        rest[post] = ctx.synergies.mean_
    fingers = [names[fi[0]].split("1_")[0].rstrip("0123456789") for fi, _ in ctx.finger_shapes]
    order = ("index", "middle", "ring", "pinky")
    out = []
    for k in range(len(fingers) - 1):
        f, g = fingers[k], fingers[k + 1]
        if f not in order or g not in order or order.index(g) != order.index(f) + 1:
            continue
        (fa, va), (fb, vb) = ctx.finger_shapes[k], ctx.finger_shapes[k + 1]
        abd = [names.index(x + "1_abd") for x in (f, g) if x + "1_abd" in names]
        for u in va[list(PAIR_SHAPES)]:
            for v in vb[list(PAIR_SHAPES)]:
                th = np.array(theta, float)
                th[fa], th[fb] = u, v
                th[abd] = rest[abd]
                out.append((k, th))
    return out


def thin(points, n):
    """Every k-th point, about ``n`` of them: the cloud that ranks candidates."""
    return slice(None, None, max(1, len(points) // n))
