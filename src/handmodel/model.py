"""The kinematic hand model: loading, validation, mirroring and batched forward kinematics.

A model is a tree of joints with rest transforms (metres) and a table of degrees of freedom (DoF)
in parameter-vector order. The local matrix of a joint is ``rest . E(d1) . E(d2) ...`` where the
``E`` are elementary rotations/translations of the joint's DoFs in the order the joint lists them
(for the default hand: ``rest . Rx(flex) . Rz(abd)`` as in the original code). The root joint carries
the global pose ``T . Rx . Ry . Rz``.

Examples
--------
>>> import numpy as np
>>> hand = HandModel.load()
>>> hand.n_dofs, len(hand.keypoint_names)
(26, 21)
>>> hand.keypoints(np.zeros(26)).shape
(21, 3)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from . import kinematics
from .errors import HandModelError
from .geometry import Capsules, build_mesh

ROTATION, TRANSLATION = 0, 1


@dataclass(frozen=True, eq=False)
class Segment:
    """A rigid surface primitive riding on one joint, along the joint's local +y axis."""

    joint: int
    shape: str  # "capsule" (round cone) or "slab" (rounded trapezoid)
    length: float
    radius: tuple[float, float]  # capsule: radii at base/far end; slab: half-widths
    half_thickness: float = 0.0


@dataclass(frozen=True, eq=False)
class HandModel:
    """A kinematic hand model. Use :meth:`load`; arrays are read-only.

    Attributes
    ----------
    node_names : list of str
        All joints including end points (fingertips), parents first; these are the keypoints.
    joint_names : list of str
        The joints that have children (16 for the default hand): :meth:`joint_frames` order.
    dof_names : list of str
        Parameter-vector order (26 for the default hand: pose, then thumb…pinky).
    limits : ndarray (n_dofs, 2)
        Default limits in radians/metres, ±inf where unlimited.
    """

    name: str
    path: str
    sha256: str
    handedness: str
    node_names: list
    parents: np.ndarray
    rest: np.ndarray
    dof_names: list
    dof_types: np.ndarray
    dof_axes: np.ndarray
    limits: np.ndarray
    dof_ptr: np.ndarray
    dof_idx: np.ndarray
    segments: tuple
    mesh_settings: dict = field(default_factory=dict)
    description: str = ""
    provenance: dict = field(default_factory=dict)

    # ------------------------------------------------------------------ loading
    @classmethod
    def load(cls, name_or_path: str | Path = "default", *, right: bool | None = None) -> "HandModel":
        """Load a model by name (``models/hands/<name>.yaml``) or path, as the hand ``right``
        (True: right, False: left, None: the file's own handedness — the shipped models are left).

        A right hand is the mirror image of the left one for the same θ (x → −x in the hand frame);
        the global pose is not mirrored. A hand file is mirrored when the other hand is asked for:
        one calibrated on a user's right hand serves their left hand as its mirror image.
        """
        from .model_file import read_hand

        return read_hand(name_or_path, right=right)

    @classmethod
    def from_dict(cls, doc, *, where: str | Path = "<dict>") -> "HandModel":
        """Build and validate a model from its parsed YAML document."""
        from .model_file import hand_from_doc

        return hand_from_doc(doc, where)

    def to_dict(self, *, name: str | None = None, description: str | None = None,
                provenance: dict | None = None) -> dict:
        """The model as a hand-model document (``hand-model.schema.json``) that :meth:`from_dict`
        turns back into the same model: every rest transform, DoF axis and limit, segment and the
        handedness as they are in memory (a scaled or mirrored model is written out, not referred
        to). ``name``, ``description`` and ``provenance`` replace the model's own.

        Examples
        --------
        >>> import numpy as np
        >>> hand = HandModel.load().scaled(1.2).mirrored()
        >>> back = HandModel.from_dict(hand.to_dict())
        >>> back.handedness, bool(np.array_equal(back.keypoints(np.zeros(26)), hand.keypoints(np.zeros(26))))
        ('right', True)
        """
        from .model_file import hand_to_doc

        return hand_to_doc(self, name, description, provenance)

    def save(self, path: str | Path, *, overwrite: bool = False, name: str | None = None,
             description: str | None = None, provenance: dict | None = None) -> Path:
        """Write the model as a YAML hand-model file (:meth:`to_dict`) that :meth:`load` reads back.

        The file is written under a temporary name, read back and rebuilt, and only a model identical
        to this one (same kinematics, geometry, limits and handedness) is renamed into place; an
        existing ``path`` is refused (``FileExistsError``) unless ``overwrite``. ``provenance`` (a
        mapping of plain values) says where the model came from: :func:`tracker.scale.calibrated_hand`
        puts the calibration's record and the base model's name and SHA-256 there. Returns ``path``.
        """
        from .model_file import write_hand

        return write_hand(self, path, overwrite=overwrite, name=name, description=description,
                          provenance=provenance)

    @property
    def calibration(self) -> dict | None:
        """The calibration record of a hand file written from a calibrated hand (its provenance's
        ``calibration``: the recording, frames, size and finger factors, their spread), else None."""
        cal = self.provenance.get("calibration") if isinstance(self.provenance, dict) else None
        return cal if isinstance(cal, dict) else None

    def mirrored(self) -> "HandModel":
        """The mirror-image hand (left ↔ right) for the same parameter vector.

        Every joint below the root is conjugated by ``S = diag(-1, 1, 1)`` and each rotation axis
        ``a`` becomes ``-S a`` (so ``S R_a(q) S = R_{-Sa}(q)``); the root's global pose is unchanged.
        """
        from .derived import mirrored

        return mirrored(self)

    def scaled(self, scale: float = 1.0, bone_scales: dict | None = None) -> "HandModel":
        """A resized copy: every bone and radius × ``scale``, then the bones ending at the nodes in
        ``bone_scales`` (node name → factor) × their factor. Capsule lengths follow their bones."""
        from .derived import scaled

        return scaled(self, scale, bone_scales)

    def with_joint_positions(self, positions: dict) -> "HandModel":
        """A copy with the rest positions (in the parent's frame, metres) of some joints replaced,
        e.g. the finger bases on the palm measured from a subject."""
        from .derived import with_joint_positions

        return with_joint_positions(self, positions)

    def with_rest_rotations(self, rotations: dict) -> "HandModel":
        """A copy with the rest rotations of some joints replaced (3×3 proper rotations)."""
        from .derived import with_rest_rotations

        return with_rest_rotations(self, rotations)

    def with_limits(self, limits) -> "HandModel":
        """A copy with other default limits ``(n_dofs, 2)``."""
        from .derived import with_limits

        return with_limits(self, limits)

    # ------------------------------------------------------------------ names and masks
    @property
    def n_dofs(self) -> int:
        return len(self.dof_names)

    @property
    def n_nodes(self) -> int:
        return len(self.node_names)

    @property
    def keypoint_names(self) -> list:
        return list(self.node_names)

    @cached_property
    def _has_child(self) -> np.ndarray:
        """True for the nodes that are some node's parent (the joints; the others are the tips)."""
        has_child = np.zeros(self.n_nodes, bool)
        has_child[self.parents[self.parents >= 0]] = True
        return _ro(has_child)

    @cached_property
    def joint_indices(self) -> np.ndarray:
        return _ro(np.flatnonzero(self._has_child))

    @property
    def joint_names(self) -> list:
        return [self.node_names[i] for i in self.joint_indices]

    @cached_property
    def pose_mask(self) -> np.ndarray:
        """True for the DoFs of the root joint (the global pose)."""
        m = np.zeros(self.n_dofs, bool)
        m[self.dof_idx[self.dof_ptr[0]:self.dof_ptr[1]]] = True
        return _ro(m)

    @cached_property
    def dof_moves(self) -> np.ndarray:
        """``(n_dofs, n_nodes)`` bool: the nodes each DoF moves (the node it drives and every node below it).

        >>> hand = HandModel.load()
        >>> [hand.node_names[k] for k in np.flatnonzero(hand.dof_moves[hand.dof_index("index2_flex")])]
        ['index2', 'index3', 'index_tip']
        """
        n = self.n_nodes
        below = np.eye(n, dtype=bool)  # below[j, k]: node k is j or hangs from it
        for k in range(n):
            j = self.parents[k]
            while j >= 0:
                below[j, k] = True
                j = self.parents[j]
        out = np.zeros((self.n_dofs, n), bool)
        for k in range(n):
            out[self.dof_idx[self.dof_ptr[k]:self.dof_ptr[k + 1]]] = below[k]
        return _ro(out)

    @property
    def posture_names(self) -> list:
        return [n for n, p in zip(self.dof_names, self.pose_mask) if not p]

    def node_index(self, name: str) -> int:
        try:
            return self.node_names.index(name)
        except ValueError:
            raise HandModelError(self.path, f"no joint named {name!r}") from None

    def dof_index(self, name: str) -> int:
        try:
            return self.dof_names.index(name)
        except ValueError:
            raise HandModelError(self.path, f"no DoF named {name!r}") from None

    def segment_of_node(self) -> np.ndarray:
        """Segment index per node (-1 where the node has none)."""
        out = np.full(self.n_nodes, -1, np.int64)
        for i, s in enumerate(self.segments):
            out[s.joint] = i
        return out

    # ------------------------------------------------------------------ kinematics
    def check_theta(self, theta) -> np.ndarray:
        """Return θ as a float64 array of shape (..., n_dofs), or raise :class:`HandModelError`."""
        try:
            th = np.asarray(theta, dtype=np.float64)
        except (TypeError, ValueError):
            raise HandModelError("theta", "not a numeric array") from None
        if th.ndim == 0 or th.shape[-1] != self.n_dofs:
            raise HandModelError("theta", f"shape {th.shape}: the last axis must have {self.n_dofs} entries")
        if not np.isfinite(th).all():  # the method: check_theta runs thousands of times a search
            raise HandModelError("theta", "contains NaN or infinite values")
        return th

    def node_frames(self, theta) -> np.ndarray:
        """Global 4×4 frames of every node, ``(..., n_nodes, 4, 4)``."""
        th = self.check_theta(theta)
        flat = th.reshape(-1, self.n_dofs)
        G = kinematics.fk_batch(flat, self.parents, self.rest, self.dof_ptr, self.dof_idx, self.dof_types, self.dof_axes)
        return G.reshape(th.shape[:-1] + (self.n_nodes, 4, 4))

    def joint_frames(self, theta) -> np.ndarray:
        """Global frames of the joints that have children, ``(..., 16, 4, 4)`` for the default hand."""
        return self.node_frames(theta)[..., self.joint_indices, :, :]

    def keypoints(self, theta) -> np.ndarray:
        """Keypoint positions in metres, ``(..., 21, 3)``: wrist, then each finger base → tip."""
        return self.node_frames(theta)[..., :3, 3]

    def wrist_crease(self, theta) -> np.ndarray:
        """The middle of the model hand's edge towards the forearm, ``(..., 3)`` metres.

        Where a wrist-crease label (the middle of the skin crease, the hand's end in a hand mask)
        belongs on this model: the root segment's base, its rounded end past the wrist joint (the
        palm slab's half thickness, ~9 mm on the default hand), on the hand's axis. The wrist keypoint
        is the joint itself, the palm's origin.

        >>> hand = HandModel.load()
        >>> np.round(hand.wrist_crease(np.zeros(26)) * 1000, 2)  # the rest pose: fingers along +y
        array([ 0.  , -8.77,  0.  ])
        """
        root, local = self.wrist_crease_local()
        return self.points(theta, [root], [local])[..., 0, :]

    def wrist_crease_local(self) -> tuple[int, np.ndarray]:
        """``(node, offset)``: :meth:`wrist_crease` as a point of the root node (its frame, metres).

        >>> HandModel.load().wrist_crease_local()[0]
        0
        """
        root = int(np.flatnonzero(self.parents < 0)[0])
        seg = next((s for s in self.segments if s.joint == root), None)
        back = 0.0 if seg is None else (seg.half_thickness if seg.shape == "slab" else seg.radius[0])
        return root, np.array([0.0, -back, 0.0])

    def fingertip_ends(self, theta) -> np.ndarray:
        """Where each finger's surface ends, ``(..., 5, 3)`` metres, in :attr:`tip_indices` order.

        Where a fingertip label (the outermost point of the finger along its axis, on its centre line)
        belongs on this model: the last segment's rounded end, its end radius past the tip keypoint
        along the last bone (~5 mm on the default hand). The tip keypoint is the end of the bone, the
        centre of that rounded end.

        >>> hand = HandModel.load()
        >>> k, e = hand.keypoints(np.zeros(26)), hand.fingertip_ends(np.zeros(26))
        >>> np.round(np.linalg.norm(e - k[hand.tip_indices], axis=-1) * 1000, 2)  # each tip's end radius
        array([5.19, 5.19, 5.19, 5.19, 5.19])
        """
        k = self.keypoints(theta)
        tips = self.tip_indices
        base = self.parents[tips]
        radius = np.array([next(s.radius[1] for s in self.segments if s.joint == b) for b in base])
        bone = k[..., tips, :] - k[..., base, :]
        unit = bone / np.linalg.norm(bone, axis=-1, keepdims=True)
        return k[..., tips, :] + radius[:, None] * unit

    @cached_property
    def tip_indices(self) -> np.ndarray:
        """The keypoints without children (the fingertips, thumb first): ``[4, 8, 12, 16, 20]``."""
        return _ro(np.flatnonzero(~self._has_child))

    def points(self, theta, nodes, local) -> np.ndarray:
        """World positions of points rigidly attached to nodes (``local`` in the node frames)."""
        G = self.node_frames(theta)
        nodes = np.asarray(nodes, np.int64)
        local = np.asarray(local, float)
        Gs = G[..., nodes, :, :]
        return np.einsum("...pij,pj->...pi", Gs[..., :3, :3], local) + Gs[..., :3, 3]

    def jacobian(self, theta, nodes=None, local=None) -> np.ndarray:
        """Analytic Jacobian ∂p/∂θ (paper eq. 5) of attached points, ``(..., P, 3, n_dofs)``.

        Without ``nodes`` the points are the keypoints. A rotation column is ``a_w × (p − o)`` with
        ``a_w`` the DoF's axis in world coordinates and ``o`` its joint origin; a translation
        column is ``a_w``.
        """
        th = self.check_theta(theta)
        if nodes is None:
            nodes = np.arange(self.n_nodes)
            local = np.zeros((self.n_nodes, 3))
        nodes = np.asarray(nodes, np.int64)
        local = np.zeros((len(nodes), 3)) if local is None else np.asarray(local, float).reshape(len(nodes), 3)
        flat = th.reshape(-1, self.n_dofs)
        J = kinematics.jacobian_batch(flat, nodes, local, self.parents, self.rest, self.dof_ptr, self.dof_idx,
                                      self.dof_types, self.dof_axes)
        return J.reshape(th.shape[:-1] + (len(nodes), 3, self.n_dofs))

    def kernel_args(self):
        """The arrays the numba kernels take, in their order."""
        return (self.parents, self.rest, self.dof_ptr, self.dof_idx, self.dof_types, self.dof_axes)

    def zero(self) -> np.ndarray:
        """The zero parameter vector (flat hand at the origin)."""
        return np.zeros(self.n_dofs)

    # ------------------------------------------------------------------ geometry shortcuts
    @cached_property
    def capsules(self):
        return Capsules.from_model(self)

    def mesh(self):
        """The procedurally generated rest mesh with skinning weights (:class:`handmodel.geometry.SkinnedMesh`)."""
        return build_mesh(self)

    def __repr__(self) -> str:
        return f"HandModel({self.name!r}, {self.handedness}, {self.n_nodes} nodes, {self.n_dofs} DoF)"


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a
