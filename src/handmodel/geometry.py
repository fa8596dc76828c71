"""Hand geometry: tapered capsules (round cones) and a rounded palm slab, their closest points and
surface samples, and a procedurally generated triangle mesh with linear-blend-skinning weights.

Segment ``s`` rides on node ``joint``: its axis starts at the joint origin and runs along local +y
for ``length``. A capsule is the convex hull of two spheres (radii ``radius[0]`` at the joint and
``radius[1]`` at the far end); a slab is a trapezoid in the local x–y plane (half-widths at both
ends minus the thickness) swept by a sphere of ``half_thickness``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
from scipy.spatial import ConvexHull

from . import libm
from ._geometry_kernels import closest_local_many, closest_points as _closest_points_kernel
from .errors import HandModelError
from .fileio import atomic_write_bytes


@dataclass(frozen=True, eq=False)
class Capsules:
    """Array form of a model's segments (kernel input)."""

    node: np.ndarray
    shape: np.ndarray
    length: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    thickness: np.ndarray

    @classmethod
    def from_model(cls, hand) -> "Capsules":
        segs = hand.segments
        return cls(
            node=np.array([s.joint for s in segs], np.int64),
            shape=np.array([0 if s.shape == "capsule" else 1 for s in segs], np.int64),
            length=np.array([s.length for s in segs]),
            r0=np.array([s.radius[0] for s in segs]),
            r1=np.array([s.radius[1] for s in segs]),
            thickness=np.array([s.half_thickness for s in segs]),
        )

    def kernel_args(self):
        return (self.node, self.shape, self.length, self.r0, self.r1, self.thickness)

    def __len__(self) -> int:
        return len(self.node)


def closest_points(hand, theta, points):
    """Closest points on the posed model surface.

    Returns
    -------
    closest : (P, 3) surface points (metres)
    segment : (P,) segment index
    normal : (P, 3) outward unit surface normals at ``closest``
    distance : (P,) signed distance of each point to the surface (negative inside)
    """
    G = hand.node_frames(theta)
    if G.ndim != 3:
        raise HandModelError("theta", "closest_points takes one parameter vector")
    pts = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3))
    P = len(pts)
    out_p = np.empty((P, 3))
    out_n = np.empty((P, 3))
    out_s = np.empty(P, np.int64)
    out_d = np.empty(P)
    _closest_points_kernel(G, *hand.capsules.kernel_args(), pts, out_p, out_n, out_s, out_d)
    return out_p, out_s, out_n, out_d


# ------------------------------------------------------------------------------ surface in local frames
def _revolve_profile(xs, rs, n_around):
    """Vertices/faces of a surface of revolution about local +y (profile: axial x, radius r).

    The first and last profile points must have r == 0 (poles)."""
    ang = np.linspace(0.0, 2 * np.pi, n_around, endpoint=False)
    x, r = np.asarray(xs, float)[1:-1, None], np.asarray(rs, float)[1:-1, None]
    nring = len(xs) - 2
    rings = np.stack([r * np.cos(ang), np.broadcast_to(x, (nring, n_around)), r * np.sin(ang)], 2)
    V = np.concatenate([[[0.0, xs[0], 0.0]], rings.reshape(-1, 3), [[0.0, xs[-1], 0.0]]])
    k = np.arange(n_around)
    k1 = (k + 1) % n_around
    first = 1
    # bottom pole (index 0) to first ring; orientation chosen so normals point outward
    a = first + n_around * np.arange(nring - 1)[:, None]
    b = a + n_around
    band = np.stack([np.stack([a + k, b + k, b + k1], 2), np.stack([a + k, b + k1, a + k1], 2)], 1)
    last = len(V) - 1
    a = first + (nring - 1) * n_around
    F = np.concatenate([np.stack([np.zeros(n_around, int), first + k, first + k1], 1), band.reshape(-1, 3),
                        np.stack([np.full(n_around, last), a + k1, a + k], 1)])
    return V, F


def _capsule_profile(L, ra, rb, cap_rings, per_m):
    d = ra - rb
    nx = float(np.clip(d / L, -0.999, 0.999))
    # the C library's (handmodel.libm): numpy's differs in the last bits by processor
    bt = math.atan2(math.sqrt(1 - nx * nx), nx)  # angle of the tangent normal from +axis
    a_ang = np.linspace(np.pi, bt, cap_rings + 1)
    b_ang = np.linspace(bt, 0.0, cap_rings + 1)
    ax, ar = ra * np.cos(a_ang), ra * np.sin(a_ang)
    bx, br = L + rb * np.cos(b_ang), rb * np.sin(b_ang)
    n_mid = max(int(np.ceil((bx[0] - ax[-1]) * per_m)), 1)
    t = np.linspace(0, 1, n_mid + 1)[1:-1]
    mx = ax[-1] + t * (bx[0] - ax[-1])
    mr = ar[-1] + t * (br[0] - ar[-1])
    xs = np.concatenate([ax, mx, bx[1:]])
    rs = np.concatenate([ar, mr, br[1:]])
    rs[0] = rs[-1] = 0.0
    return xs, rs


def _slab_mesh(L, w0, w1, th, n):
    """A rounded slab (trapezoid ⊕ sphere) as the convex hull of dense surface samples."""
    pts = _slab_samples(L, w0, w1, th, n)
    hull = ConvexHull(pts)
    V = pts[hull.vertices]
    remap = -np.ones(len(pts), int)
    remap[hull.vertices] = np.arange(len(hull.vertices))
    F = remap[hull.simplices]
    # orient outward: the facet normal must point away from the centroid
    c = V.mean(0)
    tri = V[F]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", nrm, tri.mean(1) - c) < 0
    F[flip] = F[flip][:, ::-1]
    return V, F


def _slab_samples(L, w0, w1, th, n):
    """Points on the four corner spheres of a rounded slab; their convex hull is the slab
    (trapezoid ⊕ sphere) up to the sphere sampling error."""
    corners = np.array([[-(w0 - th), 0, 0], [w0 - th, 0, 0], [w1 - th, L, 0], [-(w1 - th), L, 0]], float)
    corners[:, 0] = np.sign(corners[:, 0]) * np.maximum(np.abs(corners[:, 0]), 0.0)
    return (corners[:, None, :] + th * fibonacci_sphere(n)[None]).reshape(-1, 3)


def fibonacci_sphere(n):
    """``n`` nearly uniform unit vectors (the same bits on every processor: :mod:`handmodel.libm`; the
    palm's mesh is their convex hull, which numpy's ``arccos`` changed by processor)."""
    i = np.arange(n) + 0.5
    phi = libm.acos(1 - 2 * i / n)
    ga = np.pi * (3 - np.sqrt(5)) * i
    return np.stack([np.cos(ga) * np.sin(phi), np.sin(ga) * np.sin(phi), np.cos(phi)], 1)


def segment_surface_mesh(seg, settings):
    """Vertices and faces of one segment's surface in its joint's local frame."""
    n_around = int(settings.get("ring_vertices", 20))
    cap = int(settings.get("cap_rings", 5))
    per_m = float(settings.get("axial_rings_per_cm", 3)) * 100.0
    if seg.shape == "capsule":
        xs, rs = _capsule_profile(seg.length, seg.radius[0], seg.radius[1], cap, per_m)
        return _revolve_profile(xs, rs, n_around)
    return _slab_mesh(seg.length, seg.radius[0], seg.radius[1], seg.half_thickness, 4 * n_around * cap)


@dataclass(frozen=True, eq=False)
class SkinnedMesh:
    """A rest-pose triangle mesh with linear-blend-skinning weights over the model's nodes.

    Attributes
    ----------
    vertices : (V, 3) rest-pose vertices in the hand's world frame at θ = 0 (metres)
    faces : (T, 3) int, counter-clockwise seen from outside
    weights : (V, n_nodes) skinning weights (rows sum to 1)
    segment : (V,) segment each vertex was generated on
    """

    hand: object
    vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    segment: np.ndarray

    def _blend_matrices(self, theta):
        G = self.hand.node_frames(theta)
        G0 = self.hand.node_frames(np.zeros(self.hand.n_dofs))
        return G @ np.linalg.inv(G0)

    def pose(self, theta) -> np.ndarray:
        """LBS-posed vertices ``(..., V, 3)``: v' = Σ_j w_j G_j(θ) G_j(0)⁻¹ v."""
        B = self._blend_matrices(theta)  # (..., N, 4, 4)
        Bw = np.einsum("vn,...nij->...vij", self.weights, B[..., :3, :])
        return np.einsum("...vij,vj->...vi", Bw[..., :3], self.vertices) + Bw[..., 3]

    def face_normals(self, vertices=None) -> np.ndarray:
        V = self.vertices if vertices is None else vertices
        tri = V[..., self.faces, :]
        n = np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :])
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)

    def to_trimesh(self, theta=None):
        import trimesh  # ~0.9 s to import, and only mesh export needs it: kept out of every model load

        V = self.vertices if theta is None else self.pose(theta)
        return trimesh.Trimesh(vertices=V, faces=self.faces, process=False)

    def export(self, path, theta=None) -> Path:
        """Write the (posed) mesh as GLB, PLY, OBJ or STL (by suffix), atomically."""
        path = Path(path)
        fmt = path.suffix.lstrip(".").lower()
        if fmt not in ("glb", "ply", "obj", "stl"):
            raise HandModelError(path, f"unsupported mesh format {fmt!r} (glb, ply, obj, stl)")
        data = self.to_trimesh(theta).export(file_type=fmt)
        if isinstance(data, str):
            data = data.encode()
        return atomic_write_bytes(path, data)

    def sample(self, count: int, seed: int = 0):
        """Area-uniform surface samples: (points (count,3) at rest, weights (count, n_nodes), faces)."""
        rng = np.random.default_rng(seed)
        tri = self.vertices[self.faces]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        f = rng.choice(len(self.faces), size=count, p=area / area.sum())
        u, v = rng.random(count), rng.random(count)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        bary = np.stack([1 - u - v, u, v], 1)
        idx = self.faces[f]
        pts = np.einsum("pk,pkj->pj", bary, self.vertices[idx])
        w = np.einsum("pk,pkn->pn", bary, self.weights[idx])
        return pts, w, f


def build_mesh(hand) -> SkinnedMesh:
    """Generate the hand mesh from the segments; skin each vertex to its joint, blended with the
    parent joint over ``mesh.blend_length`` around the joint (smooth knuckles)."""
    st = hand.mesh_settings
    blend = float(st.get("blend_length", 0.006))
    G0 = hand.node_frames(np.zeros(hand.n_dofs))
    seg_of_node = hand.segment_of_node()
    Vs, Fs, Ws, Ss = [], [], [], []
    off = 0
    for s_i, seg in enumerate(hand.segments):
        V, F = segment_surface_mesh(seg, st)
        j = seg.joint
        W = np.zeros((len(V), hand.n_nodes))
        par = hand.parents[j]
        if seg.shape == "capsule" and par >= 0 and blend > 0 and seg_of_node[par] >= 0:
            s = np.clip((V[:, 1] + blend) / (2 * blend), 0.0, 1.0)
            s = s * s * (3 - 2 * s)  # smoothstep
            W[:, j] = s
            W[:, par] = 1 - s
        else:
            W[:, j] = 1.0
        Vw = V @ G0[j, :3, :3].T + G0[j, :3, 3]
        Vs.append(Vw)
        Fs.append(F + off)
        Ws.append(W)
        Ss.append(np.full(len(V), s_i))
        off += len(V)
    return SkinnedMesh(hand, np.concatenate(Vs), np.concatenate(Fs).astype(np.int64), np.concatenate(Ws),
                       np.concatenate(Ss))


def _segments_key(hand) -> tuple:
    """The hand's segments as a hashable shape: what :func:`_local_samples` depends on."""
    return tuple((seg.shape, float(seg.length), float(seg.radius[0]), float(seg.radius[1]),
                  float(seg.half_thickness), int(seg.joint)) for seg in hand.segments)


@lru_cache(maxsize=32)
def _local_samples(segments: tuple, spacing: float, seed: int) -> tuple:
    """Per segment ``(joint, points, normals)`` in its joint's frame (read-only arrays): area-uniform
    samples of its fine mesh snapped onto the exact primitive, drawn in segment order from one
    generator seeded by ``seed``."""
    rng = np.random.default_rng(seed)
    fine = {"ring_vertices": 48, "cap_rings": 12, "axial_rings_per_cm": 10}
    out = []
    for shape_name, length, r0, r1, half_thickness, joint in segments:
        seg = _SegmentShape(shape_name, length, (r0, r1), half_thickness)
        V, F = segment_surface_mesh(seg, fine)
        tri = V[F]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        count = max(int(round(area.sum() / spacing ** 2)), 1)
        f = rng.choice(len(F), size=count, p=area / area.sum())
        u, v = rng.random(count), rng.random(count)
        flip = u + v > 1
        u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
        pts = tri[f, 0] + u[:, None] * (tri[f, 1] - tri[f, 0]) + v[:, None] * (tri[f, 2] - tri[f, 0])
        nrm = np.empty_like(pts)
        closest_local_many(0 if shape_name == "capsule" else 1, length, r0, r1, half_thickness,
                           np.ascontiguousarray(pts), pts, nrm)
        pts.flags.writeable = nrm.flags.writeable = False
        out.append((joint, pts, nrm))
    return tuple(out)


class _SegmentShape(NamedTuple):
    """What :func:`segment_surface_mesh` reads of a segment."""

    shape: str
    length: float
    radius: tuple
    half_thickness: float


def surface_samples(hand, theta=None, spacing: float = 0.002, seed: int = 0):
    """Area-uniform points on the posed capsule surface, about one per ``spacing``², with their
    segment and outward normal. Samples are drawn on each segment's mesh and snapped onto the exact
    primitive, so they lie on the surface that :func:`closest_points` uses. The samples in each
    segment's frame are drawn once per hand shape, spacing and seed (:func:`_local_samples`) and posed
    at ``theta`` here: the same numbers as drawing them anew (a start search asks for them at several
    postures of one hand, each draw ~20 ms)."""
    theta = np.zeros(hand.n_dofs) if theta is None else theta
    G = hand.node_frames(theta)
    P, S, N = [], [], []
    for s_i, (joint, pts, nrm) in enumerate(_local_samples(_segments_key(hand), float(spacing), int(seed))):
        Gj = G[joint]
        P.append(pts @ Gj[:3, :3].T + Gj[:3, 3])
        N.append(nrm @ Gj[:3, :3].T)
        S.append(np.full(len(pts), s_i))
    return np.concatenate(P), np.concatenate(S), np.concatenate(N)
