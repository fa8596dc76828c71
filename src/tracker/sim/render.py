"""Synthetic depth frames of the hand model: a compiled z-buffer renderer.

The LBS-posed hand mesh (θ's global pose places the hand in the camera frame: x right, y down,
z forward, metres) is rasterised through a pinhole camera by a numba kernel. Depth is the exact
z of the ray–triangle intersection (1/z is interpolated, not z), so it agrees with ray casting
(:mod:`tracker.sim.raycast`, the independent reference). Optional clutter (:class:`Clutter`: a
bare or sleeved forearm and upper arm, a torso behind the hand, a table plane, a box or cylinder beside the
hand), labels (hand segments ≥ 0, each clutter element its own negative label), a shaded colour
image, the incidence cosine and the infrared reflectance (which the sensor noise of
:mod:`tracker.sim.noise` uses) come from the same pass.

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

from ..io.cameras import as_camera
from ..errors import TrackerError
from ._kernels import lbs, plane_pass, raster, shade
from .clutter import CLUTTER_LABELS, Clutter
from .meshes import forearm_mesh, object_mesh, sleeve_mesh, superellipsoid, upper_arm_mesh

SKIN_RGB = (226, 178, 150)
SLEEVE_RGB = (48, 66, 128)
TABLE_RGB = (178, 172, 160)
TORSO_RGB = (96, 120, 104)
OBJECT_RGB = (200, 90, 60)
BACKGROUND_RGB = (36, 40, 48)
LIGHT_DIR = np.array([-0.3, -0.5, -1.0]) / np.linalg.norm([-0.3, -0.5, -1.0])  # toward the light (camera frame)
TABLE_FACE = -2  # face id of table pixels; hand faces are 0..T-1, clutter triangles follow

#: Label of every pixel that is not the hand (hand pixels carry their segment index ≥ 0).
BACKGROUND_LABEL = -1

# Materials: colour (RGB) and near-infrared reflectance (0–1, what an active depth sensor sees; the
# noise model drops pixels on dark surfaces). Skin reflects ≈ 0.5–0.6 of 850 nm light (Anderson &
# Parrish 1981, J Invest Dermatol 77:13); dark cloth far less — the values are round figures, not
# measurements, chosen so the sleeve counts as dark and everything else as bright.
MATERIALS = {  # name: (index, RGB, IR reflectance)
    "skin": (0, SKIN_RGB, 0.55), "sleeve": (1, SLEEVE_RGB, 0.08), "torso": (2, TORSO_RGB, 0.35),
    "table": (3, TABLE_RGB, 0.5), "object": (4, OBJECT_RGB, 0.6),
}
_MATERIALS = np.array([m[1] for m in sorted(MATERIALS.values())], float)
_REFLECTANCE = np.array([m[2] for m in sorted(MATERIALS.values())], np.float32)
_BACKGROUND = np.array(BACKGROUND_RGB, np.uint8)


# ----------------------------------------------------------------------------- rendered frames
@dataclass(frozen=True, eq=False)
class Rendered:
    """One rendered frame.

    Attributes
    ----------
    depth : (H, W) float32
        z in metres along the optical axis, NaN where no surface.
    labels : (H, W) int16 or None
        Hand segment index (``hand.segments`` order) on the hand, :data:`CLUTTER_LABELS` on clutter,
        −1 (:data:`BACKGROUND_LABEL`) where nothing.
    color : (H, W, 3) uint8 or None
        Shaded colour image registered to the depth image (skin hand and arm, blue sleeve, green
        torso, grey table, red object).
    face : (H, W) int32
        Visible triangle: hand faces 0…T−1 (``T = n_hand_faces``), clutter triangles T…, −2 table, −1 none.
    cos_incidence : (H, W) float32 or None
        |cos| of the angle between surface normal and pixel ray (NaN where no surface).
    reflectance : (H, W) float32 or None
        Near-infrared reflectance of the visible material (:data:`MATERIALS`), NaN where no surface.
    """

    depth: np.ndarray
    labels: np.ndarray | None
    color: np.ndarray | None
    face: np.ndarray
    cos_incidence: np.ndarray | None = None
    n_hand_faces: int = 0
    reflectance: np.ndarray | None = None

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
        self._meshes = {}

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
               incidence: bool = False, reflectance: bool = False) -> Rendered:
        """Render one frame at parameters ``theta`` (26,); see :func:`render`."""
        if isinstance(clutter, str):
            clutter = Clutter.parse(clutter)
        P = self.pose(theta)
        depth, lab, face = self.rasterize(P)
        c = self.camera
        verts, faces, mats = [P], [self._p.faces], [np.full(self.n_faces, MATERIALS["skin"][0], np.int64)]
        n_v, n_f = len(P), self.n_faces
        n_table = None
        if clutter is not None:
            centre = P.mean(axis=0)
            for V, F, label, material in self._clutter_meshes(clutter, theta, centre):
                raster(V, F, np.full(len(F), label, np.int16), n_f, float(c.fx), float(c.fy), float(c.cx),
                       float(c.cy), self.near, True, depth, lab, face)
                verts.append(V)
                faces.append(F + n_v)
                mats.append(np.full(len(F), material, np.int64))
                n_v += len(V)
                n_f += len(F)
            if clutter.table:
                n_table, dn = clutter.plane(centre)
                plane_pass(n_table, dn, float(c.fx), float(c.fy), float(c.cx), float(c.cy), clutter.max_depth_m,
                           depth, lab, np.int16(CLUTTER_LABELS["table"]), face, np.int32(TABLE_FACE))
        face_mat = np.concatenate(mats)
        cosi = col = refl = None
        if color or incidence:
            H, W = depth.shape
            col = np.empty((H, W, 3) if color else (0, 0, 3), np.uint8)
            cosi = np.empty((H, W) if incidence else (0, 0), np.float32)
            shade(np.ascontiguousarray(np.concatenate(verts)), np.ascontiguousarray(np.concatenate(faces)), face,
                  face_mat, MATERIALS["table"][0], np.zeros(3) if n_table is None else n_table, float(c.fx),
                  float(c.fy), float(c.cx), float(c.cy), LIGHT_DIR, _MATERIALS, _BACKGROUND, col, cosi)
            col = col if color else None
            cosi = cosi if incidence else None
        if reflectance:
            m = np.where(face >= 0, face_mat[np.maximum(face, 0)], MATERIALS["table"][0])
            refl = np.where(face == -1, np.float32(np.nan), _REFLECTANCE[m]).astype(np.float32)
        return Rendered(depth, lab if labels else None, col, face, cosi, self.n_faces, refl)

    def _clutter_meshes(self, clutter: Clutter, theta, centre):
        """The triangle clutter in the camera frame: ``(vertices, faces, label, material)`` per element."""
        out = []
        if clutter.forearm:
            G0 = self._p.hand.node_frames(theta)[0]
            pieces = [("forearm", "skin", forearm_mesh)] + ([("sleeve", "sleeve", sleeve_mesh)] if clutter.sleeve
                                                            else [])
            for name, material, build in pieces:
                V, F = self._mesh(name, clutter, build)
                out.append((np.ascontiguousarray(V @ G0[:3, :3].T + G0[:3, 3]), F, CLUTTER_LABELS[name],
                            MATERIALS[material][0]))
            if clutter.upper_arm:
                # built in camera axes about the elbow: only the elbow follows the wrist
                elbow = G0[:3, 3] - clutter.forearm_length_m * G0[:3, 1]
                V, F = self._mesh("upper_arm", clutter, upper_arm_mesh)
                label, material = ("sleeve", "sleeve") if clutter.sleeve else ("upper_arm", "skin")
                out.append((np.ascontiguousarray(V + elbow), F, CLUTTER_LABELS[label], MATERIALS[material][0]))
        if clutter.torso:
            V, F = self._mesh("torso", clutter, lambda c: superellipsoid(c.torso_size_m, c.torso_roundness))
            out.append((np.ascontiguousarray(V + clutter.torso_center(centre)), F, CLUTTER_LABELS["torso"],
                        MATERIALS["torso"][0]))
        if clutter.object is not None:
            V, F = self._mesh("object", clutter, object_mesh)
            out.append((np.ascontiguousarray(V + clutter.object_center(centre)), F, CLUTTER_LABELS["object"],
                        MATERIALS["object"][0]))
        return out

    def _mesh(self, name, clutter: Clutter, build):
        """A clutter mesh in its own frame, built once per shape."""
        key = (name, replace(clutter, torso_centre=None, table_point=None, table_normal=None, object_centre=None))
        if key not in self._meshes:
            self._meshes[key] = build(clutter)
        return self._meshes[key]


def render(hand_or_mesh, theta, camera, *, labels: bool = True, color: bool = False,
           clutter: Clutter | str | None = None, incidence: bool = False, reflectance: bool = False) -> Rendered:
    """Render the LBS-posed hand mesh at ``theta`` through ``camera``.

    Parameters
    ----------
    hand_or_mesh : HandModel or SkinnedMesh
        The mesh is built once per model and cached.
    theta : (26,) parameters; the global pose places the hand in the camera frame.
    camera : camera object with ``width height fx fy cx cy`` or a preset name (``tracker.io.cameras``).
    labels, color, incidence, reflectance : bool
        Also return the label image, a shaded colour image, the incidence cosine, the infrared reflectance.
    clutter : Clutter, a :meth:`Clutter.parse` spec ("forearm,table", "sleeve,torso=0.1,box", "upperarm,torso", …)
        or None

    Returns
    -------
    Rendered
    """
    return DepthRenderer(hand_or_mesh, camera).render(theta, labels=labels, color=color, clutter=clutter,
                                                      incidence=incidence, reflectance=reflectance)
