"""Pipeline stage ``correspond``: model–data pairs for ICP.

Data→model: closest points on the capsule model (compiled) or on dense LBS surface samples of the
mesh (KD-tree), restricted to model surface facing the camera, rejected beyond a distance or when the
data normal disagrees with the model's. Model→data: silhouette pairs that pull model parts projecting
outside the hand silhouette back onto it.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.spatial import cKDTree

from handmodel._geometry_kernels import closest_points_facing
from handmodel.geometry import surface_samples

from ._kernel_arrays import SampleArrays, SilhouetteArrays
from ._silhouette_kernels import feature_transform, silhouette_pairs_kernel
from .errors import TrackerError
from .segment.ops import bounds
from .settings_base import SettingsGroup


@dataclass(frozen=True)
class CorrespondSettings(SettingsGroup):
    """How data→model pairs are found and rejected.

    ``model``: the surface, ``"capsules"`` (the paper's) or ``"mesh"``; ``reject_mm``: pairs this far
    apart or farther are dropped (the paper's 50 mm); ``facing_only``: only model surface facing the
    camera is a candidate; ``normal_agreement``: with data normals, pairs whose normals' cosine is below
    this are dropped (−1 = off, the paper's).
    """

    model: str = "capsules"
    reject_mm: float = 50.0
    facing_only: bool = True
    normal_agreement: float = 0.5

    @classmethod
    def paper(cls):
        """Pairs rejected at 50 mm, no normal test."""
        return cls(reject_mm=50.0, normal_agreement=-1.0)

    def check(self):
        if self.model not in SURFACES:
            raise TrackerError("settings", f"model must be one of {', '.join(SURFACES)}, got {self.model!r}")
        if not self.reject_mm > 0:
            raise TrackerError("settings", f"reject_mm must be positive, got {self.reject_mm!r}")


@dataclass
class Correspondences:
    """For each data point: the model point, its node, the model normal, the distance (m) and
    whether the pair is used (front-facing candidate found and distance below the rejection);
    ``points``: the data points themselves (None where a producer did not keep them), so that a
    score can measure them against the model in other ways (:func:`data_to_model_mm`)."""

    model: np.ndarray
    nodes: np.ndarray
    normals: np.ndarray
    distance: np.ndarray
    valid: np.ndarray
    points: np.ndarray | None = None

    @property
    def used(self) -> int:
        return int(self.valid.sum())

    @property
    def rejected_share(self) -> float:
        """The share of the points without a valid pair (1 when there are none)."""
        return 1.0 - float(self.valid.mean()) if len(self.valid) else 1.0

    def fit_error_mm(self) -> float:
        return float(np.mean(self.distance[self.valid]) * 1000.0) if self.valid.any() else float("inf")


class CapsuleModel:
    """Closest points on the tapered capsules (round cones) and palm slab of the hand model."""

    name = "capsules"

    def __init__(self, hand):
        self.hand = hand
        self.caps = hand.capsules

    def __call__(self, theta, points, *, reject=0.05, facing_only=True, camera_centre=(0.0, 0.0, 0.0), frames=None):
        G = self.hand.node_frames(theta) if frames is None else frames
        pts = np.ascontiguousarray(points, dtype=np.float64)
        P = len(pts)
        mp = np.zeros((P, 3))
        mn = np.zeros((P, 3))
        seg = np.empty(P, np.int64)
        d = np.empty(P)
        closest_points_facing(G, *self.caps.kernel_args(), pts, np.asarray(camera_centre, float), bool(facing_only),
                              mp, mn, seg, d)
        valid = (seg >= 0) & (d < reject)
        nodes = np.where(seg >= 0, self.caps.node[np.maximum(seg, 0)], 0)
        return Correspondences(mp, nodes, mn, d, valid, pts)


class MeshModel:
    """Closest of dense area-uniform samples of the LBS-posed mesh (KD-tree rebuilt per call).

    Each sample rides on the node with its largest skinning weight for the Jacobian."""

    name = "mesh"

    def __init__(self, hand, n_samples=8000, seed=0):
        self.hand = hand
        self.mesh = hand.mesh()
        pts, w, faces = self.mesh.sample(n_samples, seed)
        self.rest_pts = pts
        self.weights = w
        self.faces = faces
        self.node = np.argmax(w, axis=1)
        self._G0inv = np.linalg.inv(hand.node_frames(np.zeros(hand.n_dofs)))

    def __call__(self, theta, points, *, reject=0.05, facing_only=True, camera_centre=(0.0, 0.0, 0.0), frames=None):
        B = (self.hand.node_frames(theta) if frames is None else frames) @ self._G0inv
        Bw = np.einsum("vn,nij->vij", self.weights, B[:, :3, :])
        S = np.einsum("vij,vj->vi", Bw[:, :, :3], self.rest_pts) + Bw[:, :, 3]
        V = self.mesh.pose(theta)
        tri = V[self.mesh.faces[self.faces]]
        N = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
        if facing_only:
            keep = np.einsum("ij,ij->i", S - np.asarray(camera_centre), N) < 0
        else:
            keep = np.ones(len(S), bool)
        idx_keep = np.flatnonzero(keep)
        P = len(points)
        if idx_keep.size == 0:
            return Correspondences(np.zeros((P, 3)), np.zeros(P, np.int64), np.zeros((P, 3)), np.full(P, np.inf),
                                   np.zeros(P, bool), np.asarray(points, float))
        tree = cKDTree(S[idx_keep])
        d, k = tree.query(points)
        j = idx_keep[k]
        return Correspondences(S[j], self.node[j], N[j], d, d < reject, np.asarray(points, float))


SURFACES = {"capsules": CapsuleModel, "mesh": MeshModel}


class Matcher:
    """Data→model correspondences of one hand under one :class:`CorrespondSettings`; built once,
    called every ICP iteration as ``matcher(theta, points, normals=None)``."""

    def __init__(self, hand, settings: CorrespondSettings | None = None):
        self.settings = settings = settings or CorrespondSettings()
        settings.check()
        self.surface = SURFACES[settings.model](hand)

    def __call__(self, theta, points, normals=None) -> Correspondences:
        st = self.settings
        corr = self.surface(theta, points, reject=st.reject_mm / 1000.0, facing_only=st.facing_only)
        if normals is not None and st.normal_agreement > -1:
            # a data point on a surface facing another way than the model's is a wrong pair
            cos = np.einsum("ij,ij->i", normals, corr.normals)
            corr.valid &= ~(cos < st.normal_agreement)  # NaN (unknown normal) keeps the pair
        return corr


# a data point farther than this from the model is simply unexplained: farther is no worse (an arm
# stub, a speck of body the segmentation kept), and one outlier must not outweigh the fit
DATA_CAP_MM = 30.0


def data_to_model_mm(matcher: Matcher, theta, points, *, cap_mm=DATA_CAP_MM, frames=None) -> np.ndarray:
    """Per data point, its distance (mm) to the nearest model surface on any side, capped at
    ``cap_mm``: how well the hand at ``theta`` explains each point, for scoring a fit (the data→model
    half of :func:`tracker.init.score`).

    Unlike the pairs ICP uses, neither the side facing the camera nor the data normals decide here:
    both exist to keep ICP from pulling on the wrong surface, and on real sensors (SR305, Kinect)
    the normals of a concave palm, a thenar bulge or a finger's rim disagree with the model's on
    10–20 % of the points of a right fit, which a score counting every rejected pair as a far miss
    (the earlier 100 mm each) takes for a wrong hand. A real finger the model leaves uncovered
    (a thumb folded into the palm of a hand turned over) still costs its distance, up to the cap.
    ``frames``: the hand's node frames at ``theta`` when the caller has them (a search scores
    hundreds of fits)."""
    pts = np.asarray(points, float)
    if len(pts) == 0:
        return np.zeros(0)
    c = matcher.surface(theta, pts, reject=np.inf, facing_only=False, frames=frames)
    return np.minimum(np.where(np.isfinite(c.distance), c.distance * 1000.0, cap_mm), cap_mm)


def local_offsets(hand, theta, nodes, world):
    """Offsets of world points in their nodes' frames at θ (so the solver can move them with the model)."""
    G = hand.node_frames(theta)[np.asarray(nodes, np.int64)]
    return np.einsum("pji,pj->pi", G[:, :3, :3], np.asarray(world, float) - G[:, :3, 3])


class ModelSamples:
    """Points on the capsule model stored in their nodes' frames, posed cheaply by the node frames
    (for the model→data silhouette term)."""

    def __init__(self, hand, spacing=0.004):
        theta0 = np.zeros(hand.n_dofs)
        P, S, N = surface_samples(hand, theta0, spacing=spacing)
        G0 = hand.node_frames(theta0)
        nodes = np.array([hand.segments[s].joint for s in S], np.int64)
        R = G0[nodes, :3, :3]
        self.hand = hand
        self.nodes = nodes
        self.local = np.einsum("pji,pj->pi", R, P - G0[nodes, :3, 3])
        self.local_n = np.einsum("pji,pj->pi", R, N)

    def pose(self, theta):
        G = self.hand.node_frames(theta)[self.nodes]
        P = np.einsum("pij,pj->pi", G[:, :3, :3], self.local) + G[:, :3, 3]
        N = np.einsum("pij,pj->pi", G[:, :3, :3], self.local_n)
        return P, N


class Silhouette:
    """The hand silhouette of one frame with its distance transform (on the bounding box of the mask
    plus a margin; computed once, when first used: the paper's method fits without it)."""

    def __init__(self, mask, depth, camera, margin=48):
        self.mask = np.asarray(mask, bool)
        self.depth = depth
        self.camera = camera
        flat = self.mask.reshape(-1)
        self.empty = not flat[flat.argmax()]  # argmax stops at the first set pixel
        if self.empty:
            return
        (r0, r1), (c0, c1) = bounds(self.mask)
        self.v0 = max(r0 - margin, 0)
        self.u0 = max(c0 - margin, 0)
        v1 = min(r1 + margin + 1, self.mask.shape[0])
        u1 = min(c1 + margin + 1, self.mask.shape[1])
        # the window as it is now: the transform is made later, of what this frame's mask was
        self._sub = self.mask[self.v0:v1, self.u0:u1].copy()

    @cached_property
    def _transform(self):
        sub = self._sub
        h, w = sub.shape
        dist, iv, iu = np.empty((h, w)), np.empty((h, w), np.int32), np.empty((h, w), np.int32)
        # scipy's distance_transform_edt(~sub, return_indices=True) compiled
        feature_transform(sub, dist, iv, iu)
        return dist, iv, iu

    @property
    def dist(self):
        """Distance (px) of each window pixel to the nearest silhouette pixel, ``(h, w)``."""
        return self._transform[0]

    @property
    def iv(self):
        """Row of that nearest silhouette pixel (window coordinates)."""
        return self._transform[1]

    @property
    def iu(self):
        """Column of that nearest silhouette pixel (window coordinates)."""
        return self._transform[2]


#: a model sample projecting this far (px) outside the silhouette gets a silhouette pair: the
#: silhouette's edge is known to a pixel or so
SILHOUETTE_TOLERANCE_PX = 1.5


def silhouette_pairs(samples, theta, sil, tolerance_px=SILHOUETTE_TOLERANCE_PX):
    """Model→data pairs for front-facing model points that project outside the hand silhouette
    (by more than ``tolerance_px``): each is pulled to the 3-D point of the nearest silhouette pixel
    (a 3-D version of htrack's 2-D silhouette term). Returns (nodes, local offsets, targets)."""
    empty = np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    if sil.empty:
        return empty
    G = samples.hand.node_frames(theta)
    n = len(samples.nodes)
    nodes, local, tgt = np.empty(n, np.int64), np.empty((n, 3)), np.empty((n, 3))
    k = silhouette_pairs_kernel(G, SampleArrays.of(samples), SilhouetteArrays.of(sil), float(tolerance_px), nodes,
                                local, tgt)
    return nodes[:k], local[:k], tgt[:k]


# the model→data cost's settings (its compiled means, tracker.icp.model_to_data_mean and the start
# search's score, take the same)
M2D_TOLERANCE_MM, M2D_TOLERANCE_PX, M2D_CAP_MM = 6.0, 1.0, 30.0


def model_to_data_mm(samples, theta, sil, *, tolerance_mm=M2D_TOLERANCE_MM, tolerance_px=M2D_TOLERANCE_PX,
                     cap_mm=M2D_CAP_MM) -> np.ndarray:
    """Per model sample, how far (mm) it is from anywhere the camera allows it to be: a sample
    projecting outside the hand silhouette costs its distance to the silhouette beyond ``tolerance_px``
    (pixels × depth / f; the silhouette's edge is only known to a pixel, which is 2–3 % of a small
    hand's finger length, so without it small hands come out small),
    one inside costs how far it lies in front of the observed surface beyond ``tolerance_mm`` (free
    space: the camera saw past that point, so nothing can be there); behind the surface is free
    (self-occlusion). Capped at ``cap_mm`` so one stray finger does not outweigh the rest. Every
    sample counts, hidden ones included: an upside-down or mirrored hand puts whole parts where the
    camera saw background, which the data→model term alone cannot see."""
    P, _ = samples.pose(theta)
    out = np.full(len(P), cap_mm)
    if sil.empty:
        return out
    cam = sil.camera
    z = P[:, 2]
    front = z > 1e-3
    zs = np.where(front, z, 1.0)
    u = np.rint(cam.fx * P[:, 0] / zs + cam.cx).astype(np.int64)
    v = np.rint(cam.fy * P[:, 1] / zs + cam.cy).astype(np.int64)
    h, w = sil.dist.shape
    uu = np.clip(u - sil.u0, 0, w - 1)
    vv = np.clip(v - sil.v0, 0, h - 1)
    d_px = sil.dist[vv, uu] + np.hypot(u - sil.u0 - uu, v - sil.v0 - vv)
    outside = d_px > 0
    cost = np.where(outside, np.maximum(d_px - tolerance_px, 0.0) * zs / cam.fx * 1000.0, 0.0)
    H, W = sil.depth.shape
    inside = front & ~outside & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    zo = sil.depth[np.clip(v, 0, H - 1), np.clip(u, 0, W - 1)]
    with np.errstate(invalid="ignore"):
        ahead = np.where(inside & np.isfinite(zo), (zo - z) * 1000.0 - tolerance_mm, 0.0)
    cost = np.where(inside, np.maximum(ahead, 0.0), cost)
    out[front] = np.minimum(cost[front], cap_mm)
    return out
