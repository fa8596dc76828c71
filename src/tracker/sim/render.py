"""Synthetic depth frames of the hand model: a compiled z-buffer renderer.

The LBS-posed hand mesh (θ's global pose places the hand in the camera frame: x right, y down,
z forward, metres) is rasterised through a pinhole camera by a numba kernel. Depth is the exact
z of the ray–triangle intersection (1/z is interpolated, not z), so it agrees with ray casting
(:mod:`tracker.sim.raycast`, the independent reference). Optional clutter (:class:`Clutter`: a
forearm and a table plane), segment labels, a shaded colour image and the incidence cosine
(which the sensor noise of :mod:`tracker.sim.noise` uses) come from the same pass.

Pixel convention: pixel centres sit at integer coordinates; pixel ``(v, u)`` (row, column) samples
the ray ``((u − cx)/fx, (v − cy)/fy, 1)``, and a point projects to ``u = fx·x/z + cx``. Back-project
a depth image with the same rule (``x = (u − cx)·z/fx``, ``y = (v − cy)·z/fy``) to get points on the
surface.

Examples
--------
>>> from types import SimpleNamespace
>>> from handmodel import HandModel
>>> from tracker.sim.motions import make_motion
>>> cam = SimpleNamespace(width=160, height=120, fx=145.0, fy=145.0, cx=79.5, cy=59.5)
>>> r = render(HandModel.load(), make_motion("still", frames=1).theta[0], cam)
>>> r.depth.shape, r.depth.dtype, bool(0.6 < float(np.nanmin(r.depth)) < 0.9)
((120, 160), dtype('float32'), True)
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, replace

import numpy as np

from ..cameras import as_camera
from ..errors import TrackerError
from ._kernels import lbs, plane_pass, raster, shade

SKIN_RGB = (226, 178, 150)
SLEEVE_RGB = (48, 66, 128)
TABLE_RGB = (178, 172, 160)
BACKGROUND_RGB = (36, 40, 48)
LIGHT_DIR = np.array([-0.3, -0.5, -1.0]) / np.linalg.norm([-0.3, -0.5, -1.0])  # toward the light (camera frame)
TABLE_FACE = -2  # face id of table pixels; hand faces are 0..T-1, forearm faces follow
_MATERIALS = np.array([SKIN_RGB, SLEEVE_RGB, TABLE_RGB], float)
_BACKGROUND = np.array(BACKGROUND_RGB, np.uint8)


# ----------------------------------------------------------------------------- scene pieces
@dataclass(frozen=True)
class Clutter:
    """Non-hand geometry: a forearm continuing from the wrist and a table plane.

    The forearm is a tapered elliptic tube in the wrist frame along −y (half-width along the hand's
    x, half-thickness along z, at the wrist and at the far end); it moves rigidly with the wrist.
    The table is an infinite plane through ``table_point`` with unit normal ``table_normal``
    (camera frame, pointing to the camera's side); when they are ``None`` the plane lies
    ``table_gap_m`` below/behind the hand centre, seen from ``table_view_deg`` above it
    (90°: a wall facing the camera). Pixels of clutter get label −1.
    """

    forearm: bool = True
    forearm_length_m: float = 0.25
    forearm_wrist_m: tuple = (0.027, 0.02)
    forearm_far_m: tuple = (0.033, 0.028)
    table: bool = False
    table_point: tuple | None = None
    table_normal: tuple | None = None
    table_view_deg: float = 45.0
    table_gap_m: float = 0.12
    max_depth_m: float = 4.0

    @classmethod
    def parse(cls, spec: str | None) -> "Clutter | None":
        """``"none"``, ``"forearm"``, ``"table"`` or ``"forearm,table"``."""
        if spec is None:
            return None
        parts = {p.strip().lower() for p in str(spec).split(",") if p.strip()}
        if not parts or parts == {"none"}:
            return None
        bad = parts - {"forearm", "table"}
        if bad:
            raise TrackerError("clutter", f"unknown clutter {', '.join(sorted(bad))} (forearm, table, none)")
        return cls(forearm="forearm" in parts, table="table" in parts)

    def plane(self, hand_centre) -> tuple[np.ndarray, float]:
        """The table plane as ``(n, dn)`` with ``n·p = dn`` in the camera frame."""
        if self.table_normal is not None:
            n = np.asarray(self.table_normal, float)
            n = n / np.linalg.norm(n)
        else:
            a = np.radians(self.table_view_deg)
            n = np.array([0.0, -np.cos(a), -np.sin(a)])
        p0 = (np.asarray(self.table_point, float) if self.table_point is not None
              else np.asarray(hand_centre, float) - self.table_gap_m * n)
        return n, float(n @ p0)

    def fixed(self, hand_centre) -> "Clutter":
        """A copy whose table no longer follows the hand (placed from ``hand_centre``)."""
        if not self.table or self.table_point is not None:
            return self
        n, dn = self.plane(hand_centre)
        return replace(self, table_point=tuple(n * dn), table_normal=tuple(n))


def _forearm_mesh(c: Clutter, n_around: int = 24, n_rings: int = 8):
    """Closed tube in the wrist frame (vertices, faces with outward orientation)."""
    s = np.linspace(0.0, 1.0, n_rings)
    y = 0.004 - s * (c.forearm_length_m + 0.004)
    hw = c.forearm_wrist_m[0] + s * (c.forearm_far_m[0] - c.forearm_wrist_m[0])
    ht = c.forearm_wrist_m[1] + s * (c.forearm_far_m[1] - c.forearm_wrist_m[1])
    phi = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    ring = np.stack([hw[:, None] * np.cos(phi), np.broadcast_to(y[:, None], (n_rings, n_around)),
                     ht[:, None] * np.sin(phi)], -1).reshape(-1, 3)
    V = np.concatenate([ring, [[0.0, y[0], 0.0], [0.0, y[-1], 0.0]]])
    k = np.arange(n_around)
    k1 = (k + 1) % n_around
    F = []
    for i in range(n_rings - 1):
        a, b = i * n_around, (i + 1) * n_around
        F += [np.stack([a + k, a + k1, b + k], 1), np.stack([a + k1, b + k1, b + k], 1)]
    top, bot = len(V) - 2, len(V) - 1
    F.append(np.stack([np.full(n_around, top), a * 0 + k1, k], 1))
    last = (n_rings - 1) * n_around
    F.append(np.stack([np.full(n_around, bot), last + k, last + k1], 1))
    F = np.concatenate(F).astype(np.int64)
    tri = V[F]
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum()
    if vol < 0:  # make the normals point outward
        F = F[:, ::-1].copy()
    return np.ascontiguousarray(V), np.ascontiguousarray(F)


@dataclass(frozen=True, eq=False)
class Rendered:
    """One rendered frame.

    Attributes
    ----------
    depth : (H, W) float32
        z in metres along the optical axis, NaN where no surface.
    labels : (H, W) int16 or None
        Hand segment index (``hand.segments`` order), −1 elsewhere (background, clutter).
    color : (H, W, 3) uint8 or None
        Shaded colour image registered to the depth image (skin hand, blue sleeve, grey table).
    face : (H, W) int32
        Visible triangle: hand faces 0…T−1 (``T = n_hand_faces``), forearm faces T…, −2 table, −1 none.
    cos_incidence : (H, W) float32 or None
        |cos| of the angle between surface normal and pixel ray (NaN where no surface).
    """

    depth: np.ndarray
    labels: np.ndarray | None
    color: np.ndarray | None
    face: np.ndarray
    cos_incidence: np.ndarray | None = None
    n_hand_faces: int = 0

    @property
    def hand_mask(self) -> np.ndarray:
        """Pixels showing the hand."""
        return (self.face >= 0) & (self.face < self.n_hand_faces)


# ----------------------------------------------------------------------------- renderer
class _Prepared:
    """Per-mesh arrays for the kernels (cached on the mesh object)."""

    def __init__(self, mesh):
        self.mesh = mesh
        self.hand = mesh.hand
        self.rest = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        seg = np.asarray(mesh.segment)
        self.face_label = np.ascontiguousarray(seg[self.faces[:, 0]], dtype=np.int16)
        W = np.asarray(mesh.weights, float)
        K = max(int((W > 0).sum(1).max()), 1)
        idx = np.argsort(-W, axis=1)[:, :K]
        self.idx = np.ascontiguousarray(idx, dtype=np.int64)
        self.w = np.ascontiguousarray(np.take_along_axis(W, idx, 1))
        self.G0inv = np.linalg.inv(self.hand.node_frames(np.zeros(self.hand.n_dofs)))


_PREPARED: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()
_MESHES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _prepared(hand_or_mesh) -> _Prepared:
    if hasattr(hand_or_mesh, "faces") and hasattr(hand_or_mesh, "weights"):
        mesh = hand_or_mesh
    elif hasattr(hand_or_mesh, "mesh"):
        mesh = _MESHES.get(hand_or_mesh)
        if mesh is None:
            mesh = _MESHES[hand_or_mesh] = hand_or_mesh.mesh()
    else:
        raise TrackerError("render", "needs a HandModel or a SkinnedMesh")
    prep = _PREPARED.get(mesh)
    if prep is None:
        prep = _PREPARED[mesh] = _Prepared(mesh)
    return prep


class DepthRenderer:
    """Render the LBS-posed hand mesh through one camera; reuse it for many frames.

    Parameters
    ----------
    hand_or_mesh : HandModel or SkinnedMesh
    camera : camera object (``width height fx fy cx cy``) or preset name
    near : float
        Triangles with a vertex nearer than this (metres) are skipped.
    """

    def __init__(self, hand_or_mesh, camera, *, near: float = 0.05):
        self._p = _prepared(hand_or_mesh)
        self.camera = as_camera(camera)
        self.near = float(near)
        self._forearm = {}

    @property
    def hand(self):
        return self._p.hand

    @property
    def n_faces(self) -> int:
        return len(self._p.faces)

    def pose(self, theta) -> np.ndarray:
        """LBS-posed vertices ``(V, 3)`` in the camera frame (same as ``mesh.pose(theta)``)."""
        p = self._p
        G = p.hand.node_frames(theta)
        if G.ndim != 3:
            raise TrackerError("theta", "render takes one parameter vector of 26 values")
        B = np.ascontiguousarray((G @ p.G0inv)[:, :3, :])
        out = np.empty_like(p.rest)
        lbs(p.rest, p.idx, p.w, B, out)
        return out

    def rasterize(self, vertices, *, cull: bool = True):
        """Z-buffer posed vertices: ``(depth float32, labels int16, face int32)``."""
        c = self.camera
        H, W = int(c.height), int(c.width)
        depth = np.full((H, W), np.nan, np.float32)
        labels = np.full((H, W), -1, np.int16)
        face = np.full((H, W), -1, np.int32)
        raster(np.ascontiguousarray(vertices, dtype=np.float64), self._p.faces, self._p.face_label, 0,
               float(c.fx), float(c.fy), float(c.cx), float(c.cy), self.near, cull, depth, labels, face)
        return depth, labels, face

    def render(self, theta, *, labels: bool = True, color: bool = False, clutter: Clutter | str | None = None,
               incidence: bool = False) -> Rendered:
        """Render one frame at parameters ``theta`` (26,); see :func:`render`."""
        if isinstance(clutter, str):
            clutter = Clutter.parse(clutter)
        P = self.pose(theta)
        depth, lab, face = self.rasterize(P)
        c = self.camera
        verts, faces = P, self._p.faces
        if clutter is not None and clutter.forearm:
            G0 = self._p.hand.node_frames(theta)[0]
            Vf, Ff = self._forearm_mesh(clutter)
            Pf = np.ascontiguousarray(Vf @ G0[:3, :3].T + G0[:3, 3])
            raster(Pf, Ff, np.full(len(Ff), -1, np.int16), self.n_faces, float(c.fx), float(c.fy), float(c.cx),
                   float(c.cy), self.near, True, depth, lab, face)
            if color or incidence:
                verts = np.concatenate([P, Pf])
                faces = np.concatenate([faces, Ff + len(P)])
        n_table = None
        if clutter is not None and clutter.table:
            centre = P.mean(axis=0)
            n_table, dn = clutter.plane(centre)
            plane_pass(n_table, dn, float(c.fx), float(c.fy), float(c.cx), float(c.cy), clutter.max_depth_m,
                       depth, lab, np.int16(-1), face, np.int32(TABLE_FACE))
        cosi = col = None
        if color or incidence:
            H, W = depth.shape
            col = np.empty((H, W, 3) if color else (0, 0, 3), np.uint8)
            cosi = np.empty((H, W) if incidence else (0, 0), np.float32)
            shade(np.ascontiguousarray(verts), faces, face, self.n_faces,
                  np.zeros(3) if n_table is None else n_table, float(c.fx), float(c.fy), float(c.cx), float(c.cy),
                  LIGHT_DIR, _MATERIALS, _BACKGROUND, col, cosi)
            col = col if color else None
            cosi = cosi if incidence else None
        return Rendered(depth, lab if labels else None, col, face, cosi, self.n_faces)

    def _forearm_mesh(self, clutter: Clutter):
        key = (clutter.forearm_length_m, clutter.forearm_wrist_m, clutter.forearm_far_m)
        if key not in self._forearm:
            self._forearm[key] = _forearm_mesh(clutter)
        return self._forearm[key]


def render(hand_or_mesh, theta, camera, *, labels: bool = True, color: bool = False,
           clutter: Clutter | str | None = None, incidence: bool = False) -> Rendered:
    """Render the LBS-posed hand mesh at ``theta`` through ``camera``.

    Parameters
    ----------
    hand_or_mesh : HandModel or SkinnedMesh
        The mesh is built once per model and cached.
    theta : (26,) parameters; the global pose places the hand in the camera frame.
    camera : camera object with ``width height fx fy cx cy`` or a preset name (``tracker.cameras``).
    labels, color, incidence : bool
        Also return the segment-label image, a shaded colour image, the incidence cosine.
    clutter : Clutter, "forearm", "table", "forearm,table" or None

    Returns
    -------
    Rendered
    """
    return DepthRenderer(hand_or_mesh, camera).render(theta, labels=labels, color=color, clutter=clutter,
                                                      incidence=incidence)
