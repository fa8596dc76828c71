"""Subject calibration from the trial itself (or a static trial): hand scale, bone lengths, marker offsets.

The paper scaled its model by hand; here:

1. **Bone lengths** where the protocol makes them observable (markers at the joint centres at both ends
   of a bone, e.g. ART's joint-centre export): median distance over frames ÷ the model's bone.
2. **Hand scale** for skin-marker protocols: the scale that minimises the median marker-IK residual
   over a sample of frames (golden-section search); markers' explicit offsets and dorsal heights
   scale with the hand.
3. **Marker offsets** flagged ``calibrate_offset`` (e.g. a glove's): alternate marker IK on the sample
   frames and the median offset of each marker in its node's frame.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import MarkerSetError


@dataclass
class Calibration:
    """The subject's hand: ``scale`` of the whole hand, per-bone factors (node → factor) on top,
    calibrated marker offsets (label → metres in the node frame), and the fit it gave."""

    scale: float = 1.0
    bone_scales: dict = field(default_factory=dict)
    joint_positions: dict = field(default_factory=dict)
    joint_rotations: dict = field(default_factory=dict)
    offsets: dict = field(default_factory=dict)
    frames_used: int = 0
    median_residual_mm: float = float("nan")
    method: str = "none"
    source: str = ""

    def model(self, hand):
        """The calibrated hand model."""
        m = hand.scaled(self.scale, self.bone_scales)
        if self.joint_positions:
            m = m.with_joint_positions(self.joint_positions)
        if self.joint_rotations:
            m = m.with_rest_rotations(self.joint_rotations)
        return m

    def to_dict(self) -> dict:
        d = asdict(self)
        d["offsets"] = {k: [float(x) for x in v] for k, v in self.offsets.items()}
        d["bone_scales"] = {k: float(v) for k, v in self.bone_scales.items()}
        d["joint_positions"] = {k: [float(x) for x in v] for k, v in self.joint_positions.items()}
        d["joint_rotations"] = {k: np.asarray(v, float).tolist() for k, v in self.joint_rotations.items()}
        return d

    @classmethod
    def from_dict(cls, d) -> "Calibration":
        return cls(**{k: d[k] for k in cls.__dataclass_fields__ if k in d})


def sample_frames(points, count):
    """Up to ``count`` frames spread over the trial, preferring frames with every marker present."""
    present = ~np.isnan(points[..., 0])
    full = np.flatnonzero(present.all(1))
    pool = full if len(full) >= min(count, 20) else np.flatnonzero(present.sum(1) >= 3)
    if len(pool) == 0:
        return pool
    take = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    return np.unique(pool[take])


def _joint_centre_bones(hand, markerset, nodes, local, targets):
    """Bone factors from markers sitting at the joint centres at both ends of a bone."""
    at_centre = {int(n): i for i, (n, l) in enumerate(zip(nodes, local)) if not np.any(l)}
    out = {}
    for child, i in at_centre.items():
        par = int(hand.parents[child])
        if par < 0 or par not in at_centre:
            continue
        d = np.linalg.norm(targets[:, i] - targets[:, at_centre[par]], axis=1)
        d = d[np.isfinite(d)]
        model = np.linalg.norm(hand.rest[child, :3, 3])
        if len(d) and model > 0:
            out[hand.node_names[child]] = float(np.median(d) / model)
    return out


def _orient_finger_bases(hand, nodes, local, palm, residual, cal):
    """Rest rotation of each finger base that best explains its finger's joint centres (the plane
    the finger flexes in differs between people and tracking systems): a small rotation, 3 numbers
    per finger, fitted by Nelder–Mead on the finger's marker residual after IK."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    rots = {}
    for i in palm:
        base = int(nodes[i])
        chain = [k for k, n in enumerate(nodes) if _descends(hand, int(n), base)]
        if len(chain) < 3:
            continue
        name = hand.node_names[base]
        R0 = hand.scaled(1.0, cal.bone_scales).rest[base, :3, :3]
        sel = slice(None, None, 3)

        def cost(r):
            R = Rotation.from_rotvec(r).as_matrix() @ R0
            return residual(1.0, cal.bone_scales, None, cal.joint_positions, {**rots, name: R}, sel, chain)[0]

        res = minimize(cost, np.zeros(3), method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-3, "maxfev": 120, "initial_simplex": 0.15 * np.vstack([np.zeros(3), np.eye(3)])})
        # only a clear improvement re-orients the base: where the model already explains the finger,
        # a rotated base would fit as well and merely change what the angles mean
        if res.fun < 0.8 * cost(np.zeros(3)) - 0.1:
            rots[name] = Rotation.from_rotvec(res.x).as_matrix() @ R0
    return rots


def _descends(hand, node, base):
    while node >= 0:
        if node == base:
            return True
        node = int(hand.parents[node])
    return False


def calibrate(data, markerset, hand, *, right=False, frames=150, offset_iterations=3, scale_range=(0.6, 1.6),
              settings=None, orient_bases=True) -> Calibration:
    """Estimate the subject's hand from a trial (``data``: marker data with ``labels``/``points``).

    Returns a :class:`Calibration`; ``Calibration.model(hand)`` is the calibrated model and its
    ``scale`` and ``offsets`` go to :meth:`MarkerSet.attachments`.
    """
    from handmodel.solver import SolverSettings, fit_points

    ms = markerset
    idx, _ = ms.match(list(data.labels), where=getattr(data, "path", None))
    pts = np.asarray(data.points, float)
    targets = np.where((idx >= 0)[None, :, None], pts[:, np.maximum(idx, 0)], np.nan)
    sel = sample_frames(targets, frames)
    if len(sel) == 0:
        raise MarkerSetError(getattr(data, "path", ms.name), "no frame with at least 3 markers to calibrate on")
    tg = targets[sel]
    settings = settings or SolverSettings(iterations=15, damping=0.1)
    nodes, local = ms.attachments(hand, right)
    weights = np.array([m.weight for m in ms.markers])
    bones = _joint_centre_bones(hand, ms, nodes, local, tg)
    cal = Calibration(source=str(getattr(data, "path", "")), frames_used=int(len(sel)))

    def residual(scale, bone_scales, offsets, positions=None, rotations=None, frames_sel=None, markers_sel=None):
        model = hand.scaled(scale, bone_scales)
        if positions:
            model = model.with_joint_positions(positions)
        if rotations:
            model = model.with_rest_rotations(rotations)
        n, l = ms.attachments(model, right, offsets, scale=scale)
        t = tg if frames_sel is None else tg[frames_sel]
        th, rep = fit_points(model, n, l, t, weights=weights, settings=settings, restarts=1)
        if markers_sel is None:
            return float(np.nanmedian(rep.rms_mm)), th, model, n, l
        e = np.linalg.norm(model.points(th, n[markers_sel], l[markers_sel]) - t[:, markers_sel], axis=-1)
        return float(np.nanmedian(np.sqrt(np.nanmean(e ** 2, axis=1))) * 1000.0), th, model, n, l

    if len(bones) >= len(nodes) - 1 and bones:
        # every bone measured: the model follows the data directly (joint-centre protocols); the
        # joints on the palm (finger bases) are then placed where the data has them in the hand frame
        cal.bone_scales = bones
        cal.method = "bone lengths from joint centres"
        palm = [i for i, n in enumerate(nodes) if hand.parents[n] == 0 and not np.any(local[i])]
        for _ in range(3):
            _, th, model, n, _ = residual(1.0, cal.bone_scales, None, cal.joint_positions)
            G0 = model.node_frames(th)[:, 0]
            pos = {}
            for i in palm:
                loc = np.einsum("sji,sj->si", G0[:, :3, :3], tg[:, i] - G0[:, :3, 3])
                ok = np.isfinite(loc).all(1)
                if ok.sum() >= 3:
                    pos[hand.node_names[nodes[i]]] = np.median(loc[ok], axis=0)
            cal.joint_positions = pos
            # the bone scale of a palm joint is now part of its position
            cal.bone_scales = {k: v for k, v in bones.items() if k not in pos}
        cal.method += " + finger bases on the palm"
        if orient_bases:
            cal.joint_rotations = _orient_finger_bases(hand, nodes, local, palm, residual, cal)
            cal.method += " + finger base orientations"
    else:
        lo, hi = scale_range
        g = (np.sqrt(5) - 1) / 2
        a, b = lo, hi
        c, d = b - g * (b - a), a + g * (b - a)
        fc, fd = residual(c, {}, None)[0], residual(d, {}, None)[0]
        for _ in range(14):
            if fc < fd:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = residual(c, {}, None)[0]
            else:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = residual(d, {}, None)[0]
        cal.scale = float((a + b) / 2)
        cal.method = "hand scale by marker-IK residual"
    flagged = [i for i, m in enumerate(ms.markers) if m.calibrate_offset and idx[i] >= 0]
    if flagged and offset_iterations:
        offsets = None
        for _ in range(offset_iterations):
            _, th, model, n, l = residual(cal.scale, cal.bone_scales, offsets, cal.joint_positions)
            G = model.node_frames(th)  # (S, N, 4, 4)
            offsets = dict(offsets or {})
            for i in flagged:
                Gi = G[:, n[i]]
                loc = np.einsum("sji,sj->si", Gi[:, :3, :3], tg[:, i] - Gi[:, :3, 3])
                ok = np.isfinite(loc).all(1)
                if ok.sum() >= 3:
                    offsets[ms.markers[i].label] = np.median(loc[ok], axis=0)
        cal.offsets = offsets
        cal.method += " + marker offsets"
    cal.median_residual_mm = residual(cal.scale, cal.bone_scales, cal.offsets or None, cal.joint_positions,
                                      cal.joint_rotations)[0]
    return cal
