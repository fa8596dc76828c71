"""The hand-model file (``hand-model.schema.json``, YAML): its one reader and writer, behind
:meth:`handmodel.model.HandModel.load`, ``from_dict``, ``to_dict`` and ``save``."""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from .chain import ROTATION, TRANSLATION
from .chain import read_only as _ro
from .errors import HandModelError
from .fileio import atomic_path, load_yaml, plain_values, resolve_model_file, schema_errors, sha256_file

if TYPE_CHECKING:
    from .model import HandModel

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
         "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0), "-z": (0.0, 0.0, -1.0)}


def read_hand(name_or_path, *, right: bool | None = None) -> HandModel:
    """Read a hand file by name (``models/hands/<name>.yaml``) or path, as the hand ``right`` (True: right,
    False: left, None: the file's own handedness — the shipped models are left); behind :meth:`HandModel.load`.

    A right hand is the mirror image of the left one for the same θ (x → −x in the hand frame);
    the global pose is not mirrored. A hand file is mirrored when the other hand is asked for:
    one calibrated on a user's right hand serves their left hand as its mirror image.
    """
    p = resolve_model_file("hands", name_or_path, HandModelError, "hand model")
    doc = load_yaml(p, HandModelError)
    model = hand_from_doc(doc, p)
    # the model's identity is the hash of its file (what bundles and outputs record)
    model = dataclasses.replace(model, sha256=sha256_file(p))
    if right is not None and right != (model.handedness == "right"):
        model = model.mirrored()
    return model


def write_hand(hand: HandModel, path, *, overwrite: bool = False, name: str | None = None,
               description: str | None = None, provenance: dict | None = None) -> Path:
    """Write ``hand`` as a YAML hand-model file (:meth:`HandModel.to_dict`) that :meth:`HandModel.load`
    reads back (behind :meth:`HandModel.save`).

    The file is written under a temporary name, read back and rebuilt, and only a model identical
    to ``hand`` (same kinematics, geometry, limits and handedness) is renamed into place; an
    existing ``path`` is refused (``FileExistsError``) unless ``overwrite``. ``provenance`` (a
    mapping of plain values) says where the model came from: :func:`tracker.scale.calibrated_hand`
    puts the calibration's record and the base model's name and SHA-256 there. Returns ``path``.
    """
    path = Path(path)
    doc = hand.to_dict(name=name, description=description, provenance=provenance)
    text = "# Hand model written by handmodel.HandModel.save; see provenance.\n" + yaml.safe_dump(
        doc, sort_keys=False, default_flow_style=None, allow_unicode=True, width=120)

    def same(tmp: Path) -> None:
        back = hand_from_doc(load_yaml(tmp, HandModelError), path)
        problem = _difference(hand, back)
        if problem:
            raise HandModelError(path, f"the written model differs from the one in memory ({problem})")

    with atomic_path(path, overwrite=overwrite, suffix=".yaml", verify=same) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _validate_schema(doc, path: Path) -> None:
    problem = schema_errors(doc, "hand-model")
    if problem:
        raise HandModelError(path, problem)


def hand_from_doc(doc, where) -> HandModel:
    """Parse and validate a model document (see :meth:`HandModel.from_dict`)."""
    from .model import HandModel, Segment  # here: model.py imports this module

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
        return hand_from_doc({**doc, "joints": joints}, where)

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


def hand_to_doc(hand: HandModel, name, description, provenance) -> dict:
    """``hand`` as a hand-model document (``hand-model.schema.json``) that :func:`hand_from_doc` turns
    back into the same model (behind :meth:`HandModel.to_dict`): every rest transform, DoF axis and
    limit, segment and the handedness as they are in memory (a scaled or mirrored model is written out,
    not referred to). ``name``, ``description`` and ``provenance`` replace the model's own when given.
    Floats go out as Python floats, which YAML writes with their shortest exact repr, so the file reads
    back bit for bit.

    Examples
    --------
    >>> from handmodel import HandModel
    >>> hand = HandModel.load().scaled(1.2).mirrored()
    >>> back = HandModel.from_dict(hand_to_doc(hand, None, None, None))
    >>> back.handedness, bool(np.array_equal(back.keypoints(np.zeros(26)), hand.keypoints(np.zeros(26))))
    ('right', True)
    """
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
           "provenance": plain_values(hand.provenance if provenance is None else provenance),
           "units": "m", "handedness": hand.handedness, "n_dofs": hand.n_dofs, "joints": joints, "dofs": dofs,
           "segments": segments}
    if hand.mesh_settings:
        doc["mesh"] = plain_values(hand.mesh_settings)
    return doc


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
