"""Hands of other sizes and proportions than the tracking model, and the file that records them.

Real hands are not the model's size (the default model measures 129 mm from wrist to middle tip; a
large adult hand 216 mm). :class:`HandShape` describes the *rendered* hand relative to a base model:
a global scale (every bone and radius, :meth:`handmodel.HandModel.scaled`) and one length factor per
finger applied to the bones of its ray (thumb: metacarpal and both phalanges; fingers: the three
phalanges, the palm stays as it is). θ keeps its meaning on the resized hand (same joints, same
angles), so the truth of a synthetic recording stays θ; only keypoints in millimetres need the
rendered hand, which :func:`write_hand_truth` stores beside ``truth.csv`` as ``truth_hand.yaml``
and :func:`truth_hand` rebuilds.

Examples
--------
>>> from handmodel import HandModel
>>> base = HandModel.load()
>>> shape = HandShape(1.3, fingers={"index": 1.1})
>>> big = shape.apply(base)
>>> round(wrist_to_middle_tip_mm(big) / wrist_to_middle_tip_mm(base), 3)
1.3
>>> shape.finger_scales()["index"], shape.finger_scales()["pinky"]
(1.1, 1.0)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from handmodel import HandModel
from handmodel.fileio import atomic_write_text, load_yaml

from ..errors import RecordingError, TrackerError

FINGERS = ("thumb", "index", "middle", "ring", "pinky")
#: The sidecar of a synthetic recording that describes the rendered hand.
TRUTH_HAND_FILE = "truth_hand.yaml"
_FORMAT = "synthetic-hand-truth/1"
SCALE_RANGE = (0.5, 2.0)  # sanity bounds; the experiments use 0.8–1.5
FINGER_RANGE = (0.7, 1.3)


def wrist_to_middle_tip_mm(hand: HandModel) -> float:
    """Length of the flat hand from the wrist to the middle fingertip (mm): the usual hand length."""
    k = hand.keypoints(np.zeros(hand.n_dofs))
    return float(np.linalg.norm(k[hand.node_index("middle_tip")] - k[hand.node_index("wrist")]) * 1000)


@dataclass(frozen=True)
class HandShape:
    """A resized hand: global ``scale`` and per-finger length factors ``fingers`` (name → factor,
    missing fingers 1).

    Parameters
    ----------
    scale : float
        Every bone and capsule radius × ``scale`` (0.5–2).
    fingers : dict
        Finger name (:data:`FINGERS`) → length factor of its ray (0.7–1.3; ±10 % is the usual spread).
    """

    scale: float = 1.0
    fingers: dict = field(default_factory=dict)

    def __post_init__(self):
        if not (np.isfinite(self.scale) and SCALE_RANGE[0] <= self.scale <= SCALE_RANGE[1]):
            raise TrackerError("hand scale", f"must be in {SCALE_RANGE[0]}–{SCALE_RANGE[1]}, got {self.scale}")
        for name, f in self.fingers.items():
            if name not in FINGERS:
                raise TrackerError("finger scale", f"unknown finger {name!r} ({', '.join(FINGERS)})")
            if not (np.isfinite(f) and FINGER_RANGE[0] <= f <= FINGER_RANGE[1]):
                raise TrackerError("finger scale", f"{name} must be in {FINGER_RANGE[0]}–{FINGER_RANGE[1]}, got {f}")
        # every finger spelled out: equal shapes compare equal however they were given
        object.__setattr__(self, "fingers", {f: float(self.fingers.get(f, 1.0)) for f in FINGERS})

    def __hash__(self):
        return hash((self.scale, tuple(sorted(self.fingers.items()))))

    @classmethod
    def parse(cls, scale: float = 1.0, fingers: str | None = None) -> "HandShape":
        """From command-line text: ``fingers`` is one factor for all (``"1.1"``), five in
        :data:`FINGERS` order (``"1,1.1,1,0.95,0.9"``) or ``name=factor`` pairs (``"index=1.1,pinky=0.9"``).

        >>> HandShape.parse(1.2, "index=1.1,pinky=0.9").finger_scales()["pinky"]
        0.9
        """
        out = {}
        items = [p.strip() for p in (fingers or "").split(",") if p.strip()]
        try:
            if items and all("=" in p for p in items):
                for p in items:
                    k, v = p.split("=", 1)
                    out[k.strip().lower()] = float(v)
            elif len(items) == 1:
                out = dict.fromkeys(FINGERS, float(items[0]))
            elif len(items) == len(FINGERS):
                out = dict(zip(FINGERS, map(float, items)))
            elif items:
                out = None
        except ValueError:  # float() of a word
            raise TrackerError("--finger-scale", f"not numbers: {fingers!r}") from None
        if out is None:
            raise TrackerError("--finger-scale", f"give 1 or 5 factors or name=factor pairs, got {fingers!r}")
        return cls(float(scale), out)

    def finger_scales(self) -> dict:
        """Every finger's factor (1 where not given)."""
        return {f: float(self.fingers.get(f, 1.0)) for f in FINGERS}

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and all(v == 1.0 for v in self.finger_scales().values())

    def bone_scales(self) -> dict:
        """Node name → factor of the bone ending there (:meth:`HandModel.scaled`'s ``bone_scales``)."""
        out = {}
        for f, s in self.finger_scales().items():
            if s != 1.0:
                out.update({f"{f}2": s, f"{f}3": s, f"{f}_tip": s})
        return out

    def apply(self, hand: HandModel) -> HandModel:
        """The resized copy of ``hand`` (``hand`` itself when nothing changes)."""
        return hand if self.is_identity else hand.scaled(self.scale, self.bone_scales())

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "finger_scales": self.finger_scales()}


def write_hand_truth(folder, shape: HandShape, base: HandModel) -> Path:
    """Write ``truth_hand.yaml`` into a recording folder: the base model, the shape and the resulting
    hand length, so evaluation can rebuild the rendered hand (:func:`truth_hand`)."""
    hand = shape.apply(base)
    doc = {"format": _FORMAT, "model": base.name, "model_sha256": base.sha256, "handedness": base.handedness,
           **shape.to_dict(), "rendered_wrist_to_middle_tip_mm": round(wrist_to_middle_tip_mm(hand), 3),
           "model_wrist_to_middle_tip_mm": round(wrist_to_middle_tip_mm(base), 3)}
    return atomic_write_text(Path(folder) / TRUTH_HAND_FILE, yaml.safe_dump(doc, sort_keys=False), overwrite=False)


def read_hand_truth(folder) -> tuple[HandShape, dict] | None:
    """The :class:`HandShape` and the raw document of a recording's ``truth_hand.yaml`` (None if absent).

    Raises
    ------
    RecordingError
        Naming the file: unreadable, another format, bad factors.
    """
    path = Path(folder) / TRUTH_HAND_FILE
    if not path.is_file():
        return None
    doc = load_yaml(path, RecordingError)
    if not isinstance(doc, dict) or doc.get("format") != _FORMAT:
        raise RecordingError(path, f"not a {_FORMAT} file")
    try:
        fingers = {str(k): float(v) for k, v in (doc.get("finger_scales") or {}).items()}
        shape = HandShape(float(doc["scale"]), fingers)
    except TrackerError as exc:  # before ValueError, which it is
        raise RecordingError(path, str(exc)) from None
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(path, f"bad scale or finger_scales ({exc})") from None
    return shape, doc


def truth_hand(folder, base: HandModel | None = None) -> HandModel | None:
    """The hand a synthetic recording was rendered with (``base`` resized by its ``truth_hand.yaml``;
    ``base`` defaults to the model named there), or None when the recording has no such file.

    Raises
    ------
    RecordingError
        When ``base`` is given and is not the model the file names (its SHA-256 differs).
    """
    got = read_hand_truth(folder)
    if got is None:
        return None
    shape, doc = got
    if base is None:
        base = HandModel.load(doc.get("model", "default"), right=doc.get("handedness") == "right")
    if doc.get("model_sha256") and base.sha256 != doc["model_sha256"]:
        raise RecordingError(Path(folder) / TRUTH_HAND_FILE,
                             f"rendered from model {doc.get('model')} ({doc['model_sha256'][:12]}…), "
                             f"not {base.name} ({base.sha256[:12]}…)")
    return shape.apply(base)
