"""The kinematic hand model: its state and the methods users call, each a call into the module that owns
the behaviour (:mod:`.model_file` reading and writing, :mod:`.derived` mirrored/resized copies, :mod:`.chain`
forward kinematics and Jacobians, :mod:`.landmarks` the wrist crease and fingertip ends).

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

from . import chain, derived, landmarks, model_file
from .errors import HandModelError
from .geometry import Capsules, build_mesh


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
        """Load a model by name (``models/hands/<name>.yaml``) or path, as the hand ``right`` (True: right,
        False: left, None: the file's own — the shipped models are left; :func:`handmodel.model_file.read_hand`)."""
        return model_file.read_hand(name_or_path, right=right)

    @classmethod
    def from_dict(cls, doc, *, where: str | Path = "<dict>") -> "HandModel":
        """Build and validate a model from its parsed YAML document."""
        return model_file.hand_from_doc(doc, where)

    def to_dict(self, *, name: str | None = None, description: str | None = None,
                provenance: dict | None = None) -> dict:
        """The model as a hand-model document that :meth:`from_dict` turns back into the same model
        (:func:`handmodel.model_file.hand_to_doc`); ``name``, ``description`` and ``provenance`` replace its own."""
        return model_file.hand_to_doc(self, name, description, provenance)

    def save(self, path: str | Path, *, overwrite: bool = False, name: str | None = None,
             description: str | None = None, provenance: dict | None = None) -> Path:
        """Write the model as a YAML hand-model file (:meth:`to_dict`) that :meth:`load` reads back, verified
        before it takes its name; never over ``path`` unless ``overwrite`` (:func:`handmodel.model_file.write_hand`)."""
        return model_file.write_hand(self, path, overwrite=overwrite, name=name, description=description,
                                     provenance=provenance)

    @property
    def calibration(self) -> dict | None:
        """The calibration record of a hand file written from a calibrated hand (its provenance's
        ``calibration``: the recording, frames, size and finger factors, their spread), else None."""
        cal = self.provenance.get("calibration") if isinstance(self.provenance, dict) else None
        return cal if isinstance(cal, dict) else None

    def mirrored(self) -> "HandModel":
        """The mirror-image hand (left ↔ right) for the same θ (:func:`handmodel.derived.mirrored`)."""
        return derived.mirrored(self)

    def scaled(self, scale: float = 1.0, bone_scales: dict | None = None) -> "HandModel":
        """A copy resized by ``scale``, then the bones ending at the nodes in ``bone_scales`` by their factor."""
        return derived.scaled(self, scale, bone_scales)

    def with_joint_positions(self, positions: dict) -> "HandModel":
        """A copy with the rest positions (in the parent's frame, metres) of some joints replaced."""
        return derived.with_joint_positions(self, positions)

    def with_rest_rotations(self, rotations: dict) -> "HandModel":
        """A copy with the rest rotations of some joints replaced (3×3 proper rotations)."""
        return derived.with_rest_rotations(self, rotations)

    def with_limits(self, limits) -> "HandModel":
        """A copy with other default limits ``(n_dofs, 2)``."""
        return derived.with_limits(self, limits)

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
    def joint_indices(self) -> np.ndarray:
        return chain.read_only(np.flatnonzero(chain.has_child(self.parents)))

    @property
    def joint_names(self) -> list:
        return [self.node_names[i] for i in self.joint_indices]

    @cached_property
    def tip_indices(self) -> np.ndarray:
        """The keypoints without children (the fingertips, thumb first): ``[4, 8, 12, 16, 20]``."""
        return chain.read_only(np.flatnonzero(~chain.has_child(self.parents)))

    @cached_property
    def pose_mask(self) -> np.ndarray:
        """True for the DoFs of the root joint (the global pose)."""
        return chain.read_only(chain.root_dofs(self))

    @cached_property
    def dof_moves(self) -> np.ndarray:
        """``(n_dofs, n_nodes)`` bool: the nodes each DoF moves (:func:`handmodel.chain.dof_moves`)."""
        return chain.read_only(chain.dof_moves(self))

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
        return chain.segment_of_node(self)

    # ------------------------------------------------------------------ kinematics (handmodel.chain)
    def check_theta(self, theta) -> np.ndarray:
        """Return θ as a float64 array of shape (..., n_dofs), or raise :class:`HandModelError`."""
        return chain.check_theta(theta, self.n_dofs)

    def node_frames(self, theta) -> np.ndarray:
        """Global 4×4 frames of every node, ``(..., n_nodes, 4, 4)``."""
        return chain.node_frames(self, theta)

    def joint_frames(self, theta) -> np.ndarray:
        """Global frames of the joints that have children, ``(..., 16, 4, 4)`` for the default hand."""
        return self.node_frames(theta)[..., self.joint_indices, :, :]

    def keypoints(self, theta) -> np.ndarray:
        """Keypoint positions in metres, ``(..., 21, 3)``: wrist, then each finger base → tip."""
        return self.node_frames(theta)[..., :3, 3]

    def points(self, theta, nodes, local) -> np.ndarray:
        """World positions of points rigidly attached to nodes (``local`` in the node frames)."""
        return chain.points(self, theta, nodes, local)

    def jacobian(self, theta, nodes=None, local=None) -> np.ndarray:
        """Analytic Jacobian ∂p/∂θ (paper eq. 5) of attached points (the keypoints without ``nodes``),
        ``(..., P, 3, n_dofs)``: :func:`handmodel.chain.jacobian`."""
        return chain.jacobian(self, theta, nodes, local)

    def kernel_args(self):
        """The arrays the numba kernels take, in their order."""
        return (self.parents, self.rest, self.dof_ptr, self.dof_idx, self.dof_types, self.dof_axes)

    def zero(self) -> np.ndarray:
        """The zero parameter vector (flat hand at the origin)."""
        return np.zeros(self.n_dofs)

    # ------------------------------------------------------------------ surface landmarks (handmodel.landmarks)
    def wrist_crease(self, theta, frames=None) -> np.ndarray:
        """Where a wrist-crease label belongs, ``(..., 3)`` metres (:func:`handmodel.landmarks.wrist_crease`;
        ``frames``: the node frames at θ, when at hand)."""
        return landmarks.wrist_crease(self, theta, frames)

    def wrist_crease_local(self) -> tuple[int, np.ndarray]:
        """``(node, offset)``: :meth:`wrist_crease` as a point of the root node (its frame, metres)."""
        return landmarks.wrist_crease_local(self)

    def fingertip_ends(self, theta) -> np.ndarray:
        """Where each fingertip label belongs, ``(..., 5, 3)`` metres (:func:`handmodel.landmarks.fingertip_ends`)."""
        return landmarks.fingertip_ends(self, theta)

    # ------------------------------------------------------------------ geometry shortcuts
    @cached_property
    def capsules(self):
        return Capsules.from_model(self)

    def mesh(self):
        """The procedurally generated rest mesh with skinning weights (:class:`handmodel.geometry.SkinnedMesh`)."""
        return build_mesh(self)

    def __repr__(self) -> str:
        return f"HandModel({self.name!r}, {self.handedness}, {self.n_nodes} nodes, {self.n_dofs} DoF)"

