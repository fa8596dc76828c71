"""Marker sets: which marker rides where on the hand model, and matching them to a trial's labels.

A marker set (``models/markersets/<name>.yaml``, schema ``data_schema/marker-set.schema.json``) lists
each marker's label (with aliases; matching ignores case and subject prefixes such as ``Name:``),
the node it rides on and its offset in that node's frame, or a named landmark (joint centre,
fingertip, a point along a bone with a dorsal offset, a dorsal point above a joint), a weight, and
whether it is optional or its offset is to be calibrated.

Examples
--------
>>> ms = load_markerset("hand16")
>>> len(ms.markers), ms.markers[0].label
(16, 'WRR')
>>> labels = ["Sub:" + m.label for m in load_markerset("hand19").markers]
>>> ms, hand, report = choose_markerset(labels, shipped_markersets())
>>> ms.name, hand, report["matched"], report["total"]
('hand19', None, 19, 19)
"""
from __future__ import annotations

import fnmatch
import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .errors import MarkerSetError


@dataclass(frozen=True)
class Marker:
    label: str
    aliases: tuple = ()
    joint: str | None = None
    offset: tuple | None = None
    landmark: dict | None = None
    weight: float = 1.0
    optional: bool = False
    calibrate_offset: bool = False
    offset_sd: float | None = None

    def names(self) -> list:
        return [self.label, *self.aliases]


@dataclass(frozen=True)
class MarkerSet:
    name: str
    markers: tuple
    path: str = ""
    description: str = ""
    hand: str = "either"
    sides: dict = field(default_factory=dict)
    ignore: tuple = ()
    hand_model: str = "default"

    def for_hand(self, hand: str) -> "MarkerSet":
        """Labels with ``{side}`` replaced for ``hand`` ('left'/'right')."""
        if hand not in ("left", "right"):
            raise MarkerSetError(self.path or self.name, f"hand must be 'left' or 'right', got {hand!r}")
        if self.hand not in ("either", hand):
            raise MarkerSetError(self.path or self.name, f"marker set {self.name!r} is for the {self.hand} hand")
        code = self.sides.get(hand, "")
        sub = lambda s: s.replace("{side}", code)  # noqa: E731
        ms = tuple(replace(m, label=sub(m.label), aliases=tuple(sub(a) for a in m.aliases)) for m in self.markers)
        return replace(self, markers=ms, ignore=tuple(sub(g) for g in self.ignore))

    def attachments(self, hand_model, right: bool = False, offsets: dict | None = None, scale: float = 1.0):
        """Node index and local offset (metres, in ``hand_model``'s node frames) of every marker.

        ``offsets`` (label → offset) overrides, e.g. from a calibration. Explicit offsets and the
        dorsal/segment landmarks are defined for the left default hand and mirrored (x → −x) for a
        right hand; explicit offsets and dorsal distances are multiplied by ``scale`` (the subject's
        hand size relative to the default), bone fractions follow the model's bone lengths.
        """
        nodes, local = [], []
        for m in self.markers:
            if offsets and m.label in offsets:
                j = _joint_of(m)
                nodes.append(_node(hand_model, j, self))
                local.append(np.asarray(offsets[m.label], float))
                continue
            if m.landmark is None:
                j = _node(hand_model, m.joint, self)
                off = np.array(m.offset, float) * scale
                if right:
                    off[0] = -off[0]
            else:
                lm = m.landmark
                j = _node(hand_model, lm["joint"], self)
                off = np.zeros(3)
                kind = lm["type"]
                if kind == "fingertip":
                    kids = [k for k in range(hand_model.n_nodes) if hand_model.parents[k] == j]
                    if kids:
                        raise MarkerSetError(self.path or self.name,
                                             f"marker {m.label}: fingertip landmark needs an end joint, {lm['joint']!r} has children")
                elif kind == "segment":
                    kids = [k for k in range(hand_model.n_nodes) if hand_model.parents[k] == j]
                    if len(kids) != 1:
                        raise MarkerSetError(self.path or self.name,
                                             f"marker {m.label}: segment landmark needs a joint with one child, {lm['joint']!r} has {len(kids)}")
                    off = lm.get("along", 0.5) * hand_model.rest[kids[0], :3, 3].copy()
                    off[2] += lm.get("dorsal", 0.0) * scale
                elif kind == "dorsal":
                    off[2] = lm.get("distance", 0.0) * scale
            nodes.append(j)
            local.append(off)
        return np.asarray(nodes, np.int64), np.asarray(local, float).reshape(-1, 3)

    def check_model(self, hand_model) -> None:
        """Raise :class:`MarkerSetError` naming the marker if a node it rides on is not in
        ``hand_model`` or a landmark does not fit the node (a fingertip that has children, a
        segment landmark on a joint without exactly one child)."""
        self.attachments(hand_model)

    def match(self, labels, where=None):
        """Column of each marker in ``labels`` (−1 for a missing optional marker), and the unused labels.

        Raises :class:`MarkerSetError` listing the missing required markers and the labels present.
        """
        norm = [_norm(l) for l in labels]
        idx, missing = [], []
        for m in self.markers:
            found = -1
            for cand in m.names():
                c = _norm(cand)
                if c in norm:
                    found = norm.index(c)
                    break
            if found < 0 and not m.optional:
                missing.append(m.label)
            idx.append(found)
        if missing:
            raise MarkerSetError(where or self.name,
                                 f"marker set {self.name!r}: missing marker(s) {', '.join(missing)}; "
                                 f"the file has {', '.join(labels) if labels else 'no markers'}")
        used = set(i for i in idx if i >= 0)
        extra = [l for i, l in enumerate(labels) if i not in used
                 and not any(fnmatch.fnmatch(_norm(l), _norm(g)) for g in self.ignore)]
        return np.asarray(idx, np.int64), extra


def _joint_of(m: Marker) -> str:
    return m.joint if m.landmark is None else m.landmark["joint"]


def _node(hand_model, name, ms):
    try:
        return hand_model.node_names.index(name)
    except ValueError:
        users = [m.label for m in ms.markers if _joint_of(m) == name]
        raise MarkerSetError(ms.path or ms.name, f"marker {', '.join(users) or '?'}: unknown joint {name!r} "
                                                 f"(hand model {hand_model.name!r} has "
                                                 f"{', '.join(hand_model.node_names)})") from None


def _norm(label: str) -> str:
    return str(label).split(":")[-1].strip().lower()


def _validate(doc, where):
    from handmodel.fileio import schema_errors

    problem = schema_errors(doc, "marker-set")
    if problem:
        raise MarkerSetError(where, problem)


def markerset_from_dict(doc, where="<dict>") -> MarkerSet:
    if not isinstance(doc, dict):
        raise MarkerSetError(where, "top level must be a mapping")
    _validate(doc, where)
    seen = set()
    ms = []
    for i, m in enumerate(doc["markers"]):
        for n in [m["label"], *m.get("aliases", [])]:
            if _norm(n) in seen:
                raise MarkerSetError(where, f"field markers/{i}: label or alias {n!r} used twice")
            seen.add(_norm(n))
        ms.append(Marker(label=m["label"], aliases=tuple(m.get("aliases", ())), joint=m.get("joint"),
                         offset=tuple(m["offset"]) if "offset" in m else None, landmark=m.get("landmark"),
                         weight=float(m.get("weight", 1.0)), optional=bool(m.get("optional", False)),
                         calibrate_offset=bool(m.get("calibrate_offset", False)),
                         offset_sd=float(m["offset_sd"]) if "offset_sd" in m else None))
    if "{side}" in json.dumps(doc["markers"]) and "sides" not in doc:
        raise MarkerSetError(where, "field sides: labels use {side} but no side codes are given")
    out = MarkerSet(name=doc["name"], markers=tuple(ms), path=str(where), description=doc.get("description", ""),
                    hand=doc.get("hand", "either"), sides=dict(doc.get("sides", {})), ignore=tuple(doc.get("ignore", ())),
                    hand_model=doc.get("hand_model", "default"))
    out.check_model(_hand_model(out.hand_model, where))
    return out


def _hand_model(name, where):
    """The hand model a marker set names (``hand_model:``), or a one-line error about it."""
    from handmodel import HandModel
    from handmodel.errors import HandModelError

    try:
        return HandModel.load(name)
    except HandModelError as err:
        raise MarkerSetError(where, f"field hand_model: {err}") from None


#: Environment variable: folders (``os.pathsep``-separated) of the user's own marker sets.
MARKERSETS_ENV = "SYNERGY_MARKERSETS"


def user_markerset_dirs(extra=()) -> list:
    """Folders searched for the user's own marker sets, in order: ``extra`` (e.g. ``--markersets
    DIR``), the folders in ``$SYNERGY_MARKERSETS``, then ``$XDG_CONFIG_HOME/synergy/markersets``
    (default ``~/.config/synergy/markersets``) when it exists. A folder named explicitly (``extra``
    or the variable) that does not exist is an error, not silently skipped.
    """
    dirs = [Path(d) for d in extra]
    dirs += [Path(d) for d in os.environ.get(MARKERSETS_ENV, "").split(os.pathsep) if d.strip()]
    for d in dirs:
        if not d.is_dir():
            raise MarkerSetError(d, "marker-set folder not found (from --markersets or $" + MARKERSETS_ENV + ")")
    config = Path(os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config") / "synergy" / "markersets"
    if config.is_dir():
        dirs.append(config)
    out = []
    for d in dirs:
        if d.resolve() not in [o.resolve() for o in out]:
            out.append(d)
    return out


def _user_files(dirs):
    return [p for d in dirs for p in sorted(d.iterdir()) if p.suffix in (".yaml", ".yml") and p.is_file()]


def load_markerset(name_or_path, user_dirs=None) -> MarkerSet:
    """Load a marker set by name (shipped, or a ``<name>.yaml`` in :func:`user_markerset_dirs`) or
    a marker-set YAML file by path; validates it."""
    from handmodel.fileio import load_yaml, models_dir, resolve_model_file

    name = str(name_or_path)
    if Path(name).suffix not in (".yaml", ".yml") and not (models_dir() / "markersets" / f"{name}.yaml").exists():
        dirs = user_markerset_dirs() if user_dirs is None else list(user_dirs)
        mine = [p for p in _user_files(dirs) if p.stem == name]
        if mine:
            return markerset_from_dict(load_yaml(mine[0], MarkerSetError), mine[0])
        if dirs:
            known = sorted({p.stem for p in (models_dir() / "markersets").glob("*.yaml")}
                           | {p.stem for p in _user_files(dirs)})
            raise MarkerSetError(name, f"no such marker set (known: {', '.join(known)}; searched the shipped "
                                       f"sets and {', '.join(str(d) for d in dirs)})")
    p = resolve_model_file("markersets", name_or_path, MarkerSetError, "marker set")
    return markerset_from_dict(load_yaml(p, MarkerSetError), p)


def shipped_markersets() -> list:
    """Every shipped marker set (``models/markersets/*.yaml``), loaded and validated, by name."""
    from handmodel.fileio import models_dir

    return [load_markerset(p) for p in sorted((models_dir() / "markersets").glob("*.yaml"))]


def available_markersets(extra_dirs=()) -> list:
    """The shipped marker sets, then the user's (every YAML in :func:`user_markerset_dirs`), for
    :func:`choose_markerset`. Every file must be a valid marker set; two sets of one name (a user
    set named like a shipped one, or in two folders) are an error naming both files, so the set a
    trial is converted with is never ambiguous."""
    sets = shipped_markersets()
    by_name = {m.name: m.path for m in sets}
    for p in _user_files(user_markerset_dirs(extra_dirs)):
        ms = load_markerset(p)
        if ms.name in by_name:
            raise MarkerSetError(p, f"marker set {ms.name!r} is also defined in {by_name[ms.name]}; rename one")
        by_name[ms.name] = ms.path
        sets.append(ms)
    return sets


def _hands_of(ms: MarkerSet) -> list:
    """Hands whose labels can differ: both for ``{side}`` labels, the set's own hand otherwise
    (None when the labels cannot tell the hands apart)."""
    if ms.sides and any("{side}" in n for m in ms.markers for n in m.names()):
        return [h for h in ("left", "right") if ms.hand in ("either", h)]
    return [None if ms.hand == "either" else ms.hand]


def score_markerset(ms: MarkerSet, labels, hand=None) -> dict:
    """How well a trial's ``labels`` fit ``ms`` (for ``hand`` when its labels carry a side):
    ``{name, hand, matched, total, missing, unused, full}``; ``full`` when no required marker is
    missing; ``unused`` counts the file's labels neither matched nor ignored."""
    sided = ms.for_hand(hand) if hand else ms
    norm = [_norm(x) for x in labels]
    found, missing = set(), []
    for m in sided.markers:
        hit = next((norm.index(_norm(c)) for c in m.names() if _norm(c) in norm), -1)
        if hit >= 0:
            found.add(hit)
        elif not m.optional:
            missing.append(m.label)
    unused = [x for i, x in enumerate(labels) if i not in found
              and not any(fnmatch.fnmatch(_norm(x), _norm(g)) for g in sided.ignore)]
    return {"name": ms.name, "hand": hand, "matched": len(found), "total": len(sided.markers),
            "missing": missing, "unused": len(unused), "full": not missing}


def choose_markerset(labels, markersets, *, hand=None, where=None):
    """The marker set (and hand) a trial's ``labels`` fit best.

    Every set of ``markersets`` is tried for each hand its ``{side}`` labels distinguish (only
    ``hand`` when given). Sets with all required markers present compete on the markers found,
    then on the fewest labels left unexplained; a tie goes to the earlier candidate (left before
    right). Returns ``(markerset, hand, report)``: ``hand`` is None when the labels cannot tell
    (side-less labels and no ``hand`` given); ``report`` is the winner's :func:`score_markerset`
    with ``others``, the other full matches (``name``/``hand``).

    Raises :class:`MarkerSetError` (``where``) when no set fits, naming the three closest with
    their match counts and first missing labels.
    """
    if hand not in (None, "left", "right"):
        raise MarkerSetError(where or "--hand", f"hand must be 'left' or 'right', got {hand!r}")
    scores = []
    for ms in markersets:
        for h in _hands_of(ms):
            if hand and h not in (None, hand):
                continue
            if hand and h is None and ms.hand not in ("either", hand):
                continue
            scores.append((ms, h if h is not None else hand, score_markerset(ms, labels, h)))
    full = [s for s in scores if s[2]["full"]]
    if not full:
        near = sorted(scores, key=lambda s: (-s[2]["matched"] / max(s[2]["total"], 1), -s[2]["matched"]))[:3]
        parts = [f"{r['name']}{' ' + r['hand'] if r['hand'] else ''} ({r['matched']} of {r['total']}; missing "
                 f"{', '.join(r['missing'][:4])}{', ...' if len(r['missing']) > 4 else ''})" for _, _, r in near]
        raise MarkerSetError(where or "trial", "no marker set fits its labels"
                             + (f"{' for the ' + hand + ' hand' if hand else ''}: closest " + "; ".join(parts)
                                if parts else "")
                             + "; give --markers NAME or a marker-set YAML")
    best = min(range(len(full)), key=lambda i: (-full[i][2]["matched"], full[i][2]["unused"], i))
    ms, h, report = full[best]
    report = {**report, "hand": h,
              "others": [{"name": s[0].name, "hand": s[1]} for i, s in enumerate(full) if i != best]}
    return ms, h, report
