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

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml

from . import kinematics
from .errors import HandModelError
from .fileio import atomic_path, load_yaml, resolve_model_file, schema_errors, sha256_file
from .geometry import Capsules, build_mesh

ROTATION, TRANSLATION = 0, 1
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
         "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0), "-z": (0.0, 0.0, -1.0)}
_MIRROR = np.diag([-1.0, 1.0, 1.0])


def _validate_schema(doc, path: Path) -> None:
    problem = schema_errors(doc, "hand-model")
    if problem:
        raise HandModelError(path, problem)


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
        p = resolve_model_file("hands", name_or_path, HandModelError, "hand model")
        doc = load_yaml(p, HandModelError)
        model = cls.from_dict(doc, where=p)
        # the model's identity is the hash of its file (what bundles and outputs record)
        model = dataclasses.replace(model, sha256=sha256_file(p))
        if right is not None and right != (model.handedness == "right"):
            model = model.mirrored()
        return model

    @classmethod
    def from_dict(cls, doc, *, where: str | Path = "<dict>") -> "HandModel":
        """Build and validate a model from its parsed YAML document."""
        return _from_doc(doc, where)

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
        return _to_doc(self, name, description, provenance)

    def save(self, path: str | Path, *, overwrite: bool = False, name: str | None = None,
             description: str | None = None, provenance: dict | None = None) -> Path:
        """Write the model as a YAML hand-model file (:meth:`to_dict`) that :meth:`load` reads back.

        The file is written under a temporary name, read back and rebuilt, and only a model identical
        to this one (same kinematics, geometry, limits and handedness) is renamed into place; an
        existing ``path`` is refused (``FileExistsError``) unless ``overwrite``. ``provenance`` (a
        mapping of plain values) says where the model came from: :func:`tracker.scale.calibrated_hand`
        puts the calibration's record and the base model's name and SHA-256 there. Returns ``path``.
        """
        path = Path(path)
        doc = self.to_dict(name=name, description=description, provenance=provenance)
        text = "# Hand model written by handmodel.HandModel.save; see provenance.\n" + yaml.safe_dump(
            doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=120)

        def same(tmp: Path) -> None:
            back = _from_doc(load_yaml(tmp, HandModelError), path)
            problem = _difference(self, back)
            if problem:
                raise HandModelError(path, f"the written model differs from the one in memory ({problem})")

        with atomic_path(path, overwrite=overwrite, suffix=".yaml", verify=same) as tmp:
            tmp.write_text(text, encoding="utf-8")
        return path

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
        return _mirrored(self)

    def scaled(self, scale: float = 1.0, bone_scales: dict | None = None) -> "HandModel":
        """A resized copy: every bone and radius × ``scale``, then the bones ending at the nodes in
        ``bone_scales`` (node name → factor) × their factor. Capsule lengths follow their bones."""
        return _scaled(self, scale, bone_scales)

    def with_joint_positions(self, positions: dict) -> "HandModel":
        """A copy with the rest positions (in the parent's frame, metres) of some joints replaced,
        e.g. the finger bases on the palm measured from a subject."""
        rest = self.rest.copy()
        for name, v in positions.items():
            v = np.asarray(v, float)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise HandModelError(self.path, f"joint position of {name!r} must be 3 finite numbers")
            rest[self.node_index(name), :3, 3] = v
        key = json.dumps({"base": self.sha256, "positions": {k: list(map(float, v)) for k, v in positions.items()}},
                         sort_keys=True).encode()
        return dataclasses.replace(self, rest=_ro(rest), sha256=hashlib.sha256(key).hexdigest())

    def with_rest_rotations(self, rotations: dict) -> "HandModel":
        """A copy with the rest rotations of some joints replaced (3×3 proper rotations)."""
        rest = self.rest.copy()
        for name, R in rotations.items():
            R = np.asarray(R, float)
            if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
                raise HandModelError(self.path, f"rest rotation of {name!r} is not a proper rotation")
            rest[self.node_index(name), :3, :3] = R
        key = json.dumps({"base": self.sha256, "rotations": {k: np.asarray(v).round(12).tolist()
                                                             for k, v in rotations.items()}}, sort_keys=True).encode()
        return dataclasses.replace(self, rest=_ro(rest), sha256=hashlib.sha256(key).hexdigest())

    def with_limits(self, limits) -> "HandModel":
        """A copy with other default limits ``(n_dofs, 2)``."""
        lim = np.asarray(limits, float)
        if lim.shape != (self.n_dofs, 2) or np.any(lim[:, 0] >= lim[:, 1]):
            raise HandModelError(self.path, f"limits must be ({self.n_dofs}, 2) with lower < upper")
        return dataclasses.replace(self, limits=_ro(lim.copy()))

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


# ------------------------------------------------------------------ builders behind the class's methods
def _from_doc(doc, where) -> HandModel:
    """Parse and validate a model document (see :meth:`HandModel.from_dict`)."""
    where = Path(where) if not isinstance(where, Path) else where
    if not isinstance(doc, dict):
        raise HandModelError(where, "top level must be a mapping")
    if not {"joints", "dofs", "segments"} & set(doc):
        # another of our YAML files (a recording, a subject calibration, truth_hand.yaml) given as a hand
        raise HandModelError(where, "not a hand-model file (no joints, dofs or segments; a hand file is written "
                                    "by tracker calibrate or HandModel.save)")
    _validate_schema(doc, where)
    joints = doc["joints"]
    names = [j["name"] for j in joints]
    seen = set()
    for i, n in enumerate(names):
        if n in seen:
            raise HandModelError(where, f"field joints/{i}/name: duplicate joint {n!r}")
        seen.add(n)
    index = {n: i for i, n in enumerate(names)}
    roots = [j["name"] for j in joints if j["parent"] is None]
    if len(roots) != 1:
        raise HandModelError(where, f"field joints: exactly one root joint (parent: null) is required, found {roots}")
    if joints[0]["parent"] is not None:
        raise HandModelError(where, "field joints/0/parent: the root joint must come first")
    parents = np.full(len(joints), -1, dtype=np.int64)
    for i, j in enumerate(joints):
        par = j["parent"]
        if par is None:
            continue
        if par not in index:
            raise HandModelError(where, f"field joints/{i}/parent: unknown joint {par!r} (missing joint?)")
        parents[i] = index[par]
    # cycles: walking up from every joint must reach the root within n steps
    for i in range(len(joints)):
        k, steps = i, 0
        while parents[k] >= 0:
            k = parents[k]
            steps += 1
            if steps > len(joints):
                raise HandModelError(where, f"field joints/{i}/parent: cyclic parents involving {names[i]!r}")
    # parents first, so one pass down the list computes the forward kinematics
    order = _topological_order(parents)
    if list(order) != list(range(len(joints))):
        joints = [joints[i] for i in order]
        return _from_doc({**doc, "joints": joints}, where)

    rest = np.zeros((len(joints), 4, 4))
    for i, j in enumerate(joints):
        R = np.asarray(j["rest"]["rotation"], float)
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
            raise HandModelError(where, f"field joints/{i}/rest/rotation: not a proper rotation matrix")
        rest[i, :3, :3] = R
        rest[i, :3, 3] = j["rest"]["translation"]
        rest[i, 3, 3] = 1.0

    dofs = doc["dofs"]
    dof_names = [d["name"] for d in dofs]
    if len(set(dof_names)) != len(dof_names):
        raise HandModelError(where, "field dofs: duplicate DoF names")
    dindex = {n: i for i, n in enumerate(dof_names)}
    types = np.array([ROTATION if d["type"] == "rotation" else TRANSLATION for d in dofs], dtype=np.int64)
    axes = np.zeros((len(dofs), 3))
    limits = np.zeros((len(dofs), 2))
    for i, d in enumerate(dofs):
        a = _AXES[d["axis"]] if isinstance(d["axis"], str) else d["axis"]
        a = np.asarray(a, float)
        nrm = np.linalg.norm(a)
        if nrm < 1e-9:
            raise HandModelError(where, f"field dofs/{i}/axis: zero axis")
        axes[i] = a / nrm
        lo, hi = d["limits"]
        if not lo < hi:
            raise HandModelError(where, f"field dofs/{i}/limits: lower limit {lo} is not below upper {hi}")
        limits[i] = (lo, hi)
    ptr = [0]
    idx = []
    used = {}
    for i, j in enumerate(joints):
        for dn in j["dofs"]:
            if dn not in dindex:
                raise HandModelError(where, f"field joints/{i}/dofs: unknown DoF {dn!r}")
            if dn in used:
                raise HandModelError(where, f"field joints/{i}/dofs: DoF {dn!r} already used by joint {used[dn]!r}")
            used[dn] = j["name"]
            idx.append(dindex[dn])
        ptr.append(len(idx))
    unused = [n for n in dof_names if n not in used]
    if unused:
        raise HandModelError(where, f"field dofs: DoFs not attached to any joint: {unused}")
    n_expected = doc.get("n_dofs")
    if n_expected is not None and n_expected != len(dofs):
        raise HandModelError(where, f"field dofs: {len(dofs)} DoFs, expected {n_expected}")

    segs = []
    for i, s in enumerate(doc["segments"]):
        if s["joint"] not in index:
            raise HandModelError(where, f"field segments/{i}/joint: unknown joint {s['joint']!r}")
        if s["shape"] == "capsule":
            segs.append(Segment(index[s["joint"]], "capsule", float(s["length"]), tuple(map(float, s["radius"]))))
        else:
            segs.append(Segment(index[s["joint"]], "slab", float(s["length"]),
                                tuple(map(float, s["half_width"])), float(s["half_thickness"])))
    canon = json.dumps(doc, sort_keys=True, default=str).encode()
    return HandModel(
        name=doc["name"], path=str(where), sha256=hashlib.sha256(canon).hexdigest(),
        handedness=doc["handedness"], node_names=names, parents=_ro(parents), rest=_ro(rest),
        dof_names=dof_names, dof_types=_ro(types), dof_axes=_ro(axes), limits=_ro(limits),
        dof_ptr=_ro(np.asarray(ptr, np.int64)), dof_idx=_ro(np.asarray(idx, np.int64)),
        segments=tuple(segs), mesh_settings=dict(doc.get("mesh") or {}), description=doc.get("description", ""),
        provenance=dict(doc.get("provenance") or {}),
    )


def _to_doc(hand: HandModel, name, description, provenance) -> dict:
    """See :meth:`HandModel.to_dict`. Floats go out as Python floats, which YAML writes with their
    shortest exact repr, so the file reads back bit for bit."""
    named = {v: k for k, v in _AXES.items()}
    joints = []
    for k, n in enumerate(hand.node_names):
        dofs = [hand.dof_names[d] for d in hand.dof_idx[hand.dof_ptr[k]:hand.dof_ptr[k + 1]]]
        joints.append({"name": n, "parent": None if hand.parents[k] < 0 else hand.node_names[hand.parents[k]],
                       "rest": {"translation": hand.rest[k, :3, 3].tolist(), "rotation": hand.rest[k, :3, :3].tolist()},
                       "dofs": dofs})
    dofs = []
    for d, n in enumerate(hand.dof_names):
        axis = tuple(float(v) + 0.0 for v in hand.dof_axes[d])  # + 0.0: a mirrored -0.0 names its axis too
        dofs.append({"name": n, "type": "rotation" if hand.dof_types[d] == ROTATION else "translation",
                     "axis": named.get(axis, list(axis)), "limits": hand.limits[d].tolist()})
    segments = []
    for sg in hand.segments:
        seg = {"joint": hand.node_names[sg.joint], "shape": sg.shape, "length": float(sg.length)}
        if sg.shape == "capsule":
            seg["radius"] = [float(r) for r in sg.radius]
        else:
            seg.update(half_width=[float(r) for r in sg.radius], half_thickness=float(sg.half_thickness))
        segments.append(seg)
    doc = {"schema_version": 1, "name": name or hand.name,
           "description": hand.description if description is None else description,
           "provenance": _plain(hand.provenance if provenance is None else provenance),
           "units": "m", "handedness": hand.handedness, "n_dofs": hand.n_dofs, "joints": joints, "dofs": dofs,
           "segments": segments}
    if hand.mesh_settings:
        doc["mesh"] = _plain(hand.mesh_settings)
    return doc


def _plain(value):
    """``value`` with numpy scalars and arrays, tuples and paths turned into YAML's plain types."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def _difference(a: HandModel, b: HandModel) -> str | None:
    """What differs between two models' kinematics, geometry, limits and handedness, or None."""
    if a.handedness != b.handedness:
        return f"handedness {a.handedness} vs {b.handedness}"
    if a.node_names != b.node_names or a.dof_names != b.dof_names:
        return "joint or DoF names"
    for f in ("parents", "rest", "dof_types", "dof_axes", "limits", "dof_ptr", "dof_idx"):
        x, y = getattr(a, f), getattr(b, f)
        # an axis given as numbers is normalised again when read, which may move its last bit
        same = (np.allclose(x, y, rtol=0.0, atol=1e-15) if f == "dof_axes" and x.shape == y.shape
                else x.shape == y.shape and np.array_equal(x, y))
        if not same:
            return f"{f}"
    seg = [(s.joint, s.shape, s.length, s.radius, s.half_thickness) for s in a.segments]
    if seg != [(s.joint, s.shape, s.length, s.radius, s.half_thickness) for s in b.segments]:
        return "segments"
    if a.mesh_settings != b.mesh_settings:
        return "mesh settings"
    return None


def _mirrored(hand: HandModel) -> HandModel:
    """See :meth:`HandModel.mirrored`."""
    S = _MIRROR
    rest = hand.rest.copy()
    rest[1:, :3, :3] = S @ rest[1:, :3, :3] @ S
    rest[1:, :3, 3] = rest[1:, :3, 3] @ S
    axes = hand.dof_axes.copy()
    root_dofs = set(hand.dof_idx[hand.dof_ptr[0]:hand.dof_ptr[1]].tolist())
    for d in range(hand.n_dofs):
        if d in root_dofs:
            continue
        axes[d] = -(S @ axes[d]) if hand.dof_types[d] == ROTATION else S @ axes[d]
    side = "right" if hand.handedness == "left" else "left"
    return HandModel(
        name=hand.name, path=hand.path, sha256=hand.sha256, handedness=side, node_names=hand.node_names,
        parents=hand.parents, rest=_ro(rest), dof_names=hand.dof_names, dof_types=hand.dof_types,
        dof_axes=_ro(axes), limits=hand.limits, dof_ptr=hand.dof_ptr, dof_idx=hand.dof_idx,
        segments=hand.segments, mesh_settings=hand.mesh_settings, description=hand.description,
        provenance=hand.provenance,
    )


def _scaled(hand: HandModel, scale: float, bone_scales: dict | None) -> HandModel:
    """See :meth:`HandModel.scaled`."""
    if not np.isfinite(scale) or scale <= 0:
        raise HandModelError(hand.path, f"scale must be positive, got {scale}")
    rest = hand.rest.copy()
    rest[:, :3, 3] *= scale
    for name, f in (bone_scales or {}).items():
        if not np.isfinite(f) or f <= 0:
            raise HandModelError(hand.path, f"bone scale of {name!r} must be positive, got {f}")
        rest[hand.node_index(name), :3, 3] *= f
    segs = []
    for sg in hand.segments:
        f = scale
        kids = [k for k in range(hand.n_nodes) if hand.parents[k] == sg.joint]
        if sg.shape == "capsule" and len(kids) == 1 and abs(np.linalg.norm(hand.rest[kids[0], :3, 3]) - sg.length) < 1e-9:
            length = float(np.linalg.norm(rest[kids[0], :3, 3]))  # the capsule spans its bone
        else:
            length = sg.length * f
        segs.append(Segment(sg.joint, sg.shape, length, (sg.radius[0] * f, sg.radius[1] * f), sg.half_thickness * f))
    key = json.dumps({"base": hand.sha256, "scale": scale, "bones": bone_scales or {}}, sort_keys=True).encode()
    return HandModel(
        name=hand.name, path=hand.path, sha256=hashlib.sha256(key).hexdigest(), handedness=hand.handedness,
        node_names=hand.node_names, parents=hand.parents, rest=_ro(rest), dof_names=hand.dof_names,
        dof_types=hand.dof_types, dof_axes=hand.dof_axes, limits=hand.limits, dof_ptr=hand.dof_ptr,
        dof_idx=hand.dof_idx, segments=tuple(segs), mesh_settings=hand.mesh_settings, description=hand.description,
        provenance=hand.provenance,
    )


def _ro(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


def _topological_order(parents: np.ndarray) -> list:
    n = len(parents)
    children = [[] for _ in range(n)]
    root = int(np.flatnonzero(parents < 0)[0])
    for i, p in enumerate(parents):
        if p >= 0:
            children[p].append(i)
    out, stack = [], [root]
    while stack:
        k = stack.pop()
        out.append(k)
        stack.extend(reversed(children[k]))
    return out
