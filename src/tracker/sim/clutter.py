"""The renderer's scene pieces besides the hand (:class:`Clutter`): a bare or sleeved forearm and its upper
arm, a torso behind the hand, a table plane, a box or cylinder beside it, and their pixel labels."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import TrackerError

#: One label per clutter element, all negative and distinct, so a test can tell what a pixel shows.
#: A sleeved upper arm shows cloth and carries the sleeve's label; a bare one its own.
CLUTTER_LABELS = {"forearm": -2, "sleeve": -3, "torso": -4, "table": -5, "object": -6, "upper_arm": -7}
_CLUTTER_PARTS = ("forearm", "sleeve", "torso", "table", "object", "upper_arm")


@dataclass(frozen=True)
class Clutter:
    """Non-hand geometry: a forearm (bare or sleeved) and its upper arm, a torso behind the hand, a table
    plane and a second object beside the hand.

    The forearm is a tapered elliptic tube in the wrist frame along −y (half-width along the hand's
    x, half-thickness along z, at the wrist and at the far end); it moves rigidly with the wrist.
    With ``sleeve`` a wider tube (``sleeve_scale`` × the forearm's half-axes + ``sleeve_ease_m``)
    covers it from ``sleeve_start_m`` behind the wrist to its far end: dark cloth (low infrared
    reflectance), blue in the colour image.

    With ``upper_arm`` (off by default; it needs the forearm) the arm goes on at the elbow — the forearm's
    far end, wrist frame ``(0, −forearm_length_m, 0)`` — into a tapered elliptic tube ``upper_arm_length_m``
    long, half-axes ``upper_arm_elbow_m`` at the elbow and ``upper_arm_shoulder_m`` at the shoulder (width in
    the image plane, thickness), along ``upper_arm_dir`` in the camera frame. The elbow moves with the wrist;
    the direction does not turn with it (the shoulder stays on the body). The default direction is a person
    facing the camera with the hand raised in front of the chest at 0.6–0.9 m, as in the realistic scenes:
    there the forearm hangs straight down in the image at the hand's depth, the elbow ~0.15–0.25 m in front
    of the body, and the upper arm runs from it back (away from the camera) and up to the shoulder, its far
    end 0.24 m deeper than the elbow, at the torso's front (``torso_gap_m`` 0.15 behind the hand). Up, not down
    in the image: a shoulder lies above its elbow unless the elbow is raised, and a level camera sees it so
    (down in the image would need a camera looking steeply up from below). Seen that way the upper arm lies
    mostly behind the forearm: it widens the arm near the elbow and joins it, in depth, to the body behind.
    With ``sleeve`` the upper arm is cloth (the sleeve's label, material and widening).

    The torso is a rounded box (superellipsoid with exponent ``torso_roundness``; half-extents
    ``torso_size_m`` along camera x, y, z) whose front surface lies ``torso_gap_m`` (0.03–0.30 m)
    behind the hand centre along the optical axis, offset by ``torso_offset_m`` in x and y (default:
    the hand in front of the upper chest).

    The table is an infinite plane through ``table_point`` with unit normal ``table_normal``
    (camera frame, pointing to the camera's side); when they are ``None`` the plane lies
    ``table_gap_m`` below/behind the hand centre, seen from ``table_view_deg`` above it
    (90°: a wall facing the camera).

    The object (``"box"`` or ``"cylinder"``, axis along camera y) stands with its centre at the hand
    centre + ``object_offset_m``; ``object_size_m`` is the box's half-extents, or the cylinder's
    (radius, half-height, —).

    Torso, table and object are placed from each frame's hand centre unless ``torso_centre`` /
    ``table_point`` / ``object_centre`` are given (:meth:`fixed` sets them once for a sequence).
    Pixels of clutter carry the labels of :data:`CLUTTER_LABELS`; :class:`tracker.sim.render.DepthRenderer` draws it.
    """

    forearm: bool = True
    forearm_length_m: float = 0.25
    forearm_wrist_m: tuple = (0.027, 0.02)
    forearm_far_m: tuple = (0.033, 0.028)
    sleeve: bool = False
    sleeve_start_m: float = 0.05
    sleeve_scale: float = 1.25
    sleeve_ease_m: float = 0.006
    torso: bool = False
    torso_gap_m: float = 0.15
    torso_size_m: tuple = (0.17, 0.28, 0.11)
    torso_offset_m: tuple = (0.0, 0.16)
    torso_roundness: float = 0.35
    torso_centre: tuple | None = None
    table: bool = False
    table_point: tuple | None = None
    table_normal: tuple | None = None
    table_view_deg: float = 45.0
    table_gap_m: float = 0.12
    object: str | None = None
    object_offset_m: tuple = (0.14, 0.03, 0.03)
    object_size_m: tuple = (0.035, 0.07, 0.035)
    object_centre: tuple | None = None
    max_depth_m: float = 4.0
    upper_arm: bool = False
    upper_arm_length_m: float = 0.30
    upper_arm_elbow_m: tuple = (0.045, 0.04)
    upper_arm_shoulder_m: tuple = (0.05, 0.045)
    upper_arm_dir: tuple = (0.0, -0.6, 0.8)

    def __post_init__(self):
        if not 0.03 <= self.torso_gap_m <= 0.30:
            raise TrackerError("clutter", f"torso gap must be 0.03–0.30 m behind the hand, got {self.torso_gap_m}")
        if self.object not in (None, "box", "cylinder"):
            raise TrackerError("clutter", f"object must be box or cylinder, got {self.object!r}")
        if self.sleeve and not self.forearm:
            raise TrackerError("clutter", "a sleeve needs the forearm")
        if not 0.0 <= self.sleeve_start_m < self.forearm_length_m:
            raise TrackerError("clutter", "sleeve_start_m must lie on the forearm")
        if self.upper_arm and not self.forearm:
            raise TrackerError("clutter", "an upper arm needs the forearm (its elbow is the forearm's far end)")
        if min(*self.torso_size_m, *self.object_size_m, self.forearm_length_m, self.sleeve_scale,
               self.upper_arm_length_m, *self.upper_arm_elbow_m, *self.upper_arm_shoulder_m) <= 0:
            raise TrackerError("clutter", "sizes must be positive")
        d = np.asarray(self.upper_arm_dir, float)
        if d.shape != (3,) or not np.isfinite(d).all() or np.linalg.norm(d) < 1e-9:
            raise TrackerError("clutter", f"upper_arm_dir must be a non-zero 3-vector, got {self.upper_arm_dir!r}")

    @classmethod
    def parse(cls, spec: str | None) -> "Clutter | None":
        """A comma-separated list of ``forearm``, ``sleeve`` (a sleeved forearm), ``upperarm`` (the forearm
        and its upper arm), ``torso`` or ``torso=GAP`` (metres behind the hand, 0.03–0.30), ``table``,
        ``object`` / ``box`` / ``cylinder`` (``object`` is a box); ``none`` or empty: no clutter. The text of
        :meth:`describe` parses too (``+`` joins parts, ``torso@GAPm``).

        >>> Clutter.parse("sleeve,torso=0.05").torso_gap_m, Clutter.parse("forearm,table").object
        (0.05, None)
        >>> c = Clutter.parse("upperarm,torso")
        >>> c.forearm, c.upper_arm, c.describe(), Clutter.parse(c.describe()) == c
        (True, True, 'forearm+upperarm,torso@0.15m', True)
        """
        kw = _spec_fields(spec)
        return None if kw is None else cls(**kw)

    @property
    def parts(self) -> tuple:
        """The clutter elements present, in :data:`CLUTTER_LABELS` order (``sleeve`` and ``upper_arm`` imply
        ``forearm``)."""
        on = {"forearm": self.forearm, "sleeve": self.sleeve, "torso": self.torso, "table": self.table,
              "object": self.object is not None, "upper_arm": self.upper_arm}
        return tuple(k for k in _CLUTTER_PARTS if on[k])

    def describe(self) -> str:
        """A short text for metadata, e.g. ``forearm+sleeve,torso@0.15m,box`` (``+upperarm`` after the forearm
        with the upper arm)."""
        out = []
        if self.forearm:
            out.append("forearm" + ("+sleeve" if self.sleeve else "") + ("+upperarm" if self.upper_arm else ""))
        if self.torso:
            out.append(f"torso@{self.torso_gap_m:g}m")
        if self.table:
            out.append("table")
        if self.object is not None:
            out.append(self.object)
        return ",".join(out) or "none"

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

    def torso_center(self, hand_centre) -> np.ndarray:
        """Centre of the torso (camera frame) for a hand centred at ``hand_centre``."""
        if self.torso_centre is not None:
            return np.asarray(self.torso_centre, float)
        c = np.asarray(hand_centre, float)
        return c + np.array([self.torso_offset_m[0], self.torso_offset_m[1], self.torso_gap_m + self.torso_size_m[2]])

    def object_center(self, hand_centre) -> np.ndarray:
        """Centre of the second object (camera frame) for a hand centred at ``hand_centre``."""
        if self.object_centre is not None:
            return np.asarray(self.object_centre, float)
        return np.asarray(hand_centre, float) + np.asarray(self.object_offset_m, float)

    def sized(self, scale: float) -> "Clutter":
        """A copy whose forearm (and sleeve, and upper arm) is ``scale`` × as long and as wide: the arm of a
        hand ``scale`` × the model's (a small hand on an adult's arm would be as wide at the wrist as
        across the palm, which no person's is). The upper arm's direction and the body stay.

        >>> c = Clutter().sized(0.8)
        >>> round(c.forearm_length_m, 3), tuple(round(v, 4) for v in c.forearm_wrist_m)
        (0.2, (0.0216, 0.016))
        """
        k = float(scale)
        if k == 1.0:
            return self
        return replace(self, forearm_length_m=k * self.forearm_length_m,
                       forearm_wrist_m=tuple(k * v for v in self.forearm_wrist_m),
                       forearm_far_m=tuple(k * v for v in self.forearm_far_m), sleeve_start_m=k * self.sleeve_start_m,
                       upper_arm_length_m=k * self.upper_arm_length_m,
                       upper_arm_elbow_m=tuple(k * v for v in self.upper_arm_elbow_m),
                       upper_arm_shoulder_m=tuple(k * v for v in self.upper_arm_shoulder_m))

    def fixed(self, hand_centre) -> "Clutter":
        """A copy whose table, torso and object no longer follow the hand (placed from ``hand_centre``)."""
        out = self
        if self.table and self.table_point is None:
            n, dn = self.plane(hand_centre)
            out = replace(out, table_point=tuple(n * dn), table_normal=tuple(n))
        if self.torso and self.torso_centre is None:
            out = replace(out, torso_centre=tuple(self.torso_center(hand_centre)))
        if self.object is not None and self.object_centre is None:
            out = replace(out, object_centre=tuple(self.object_center(hand_centre)))
        return out


def _spec_fields(spec) -> dict | None:
    """The :class:`Clutter` fields a :meth:`Clutter.parse` spec sets (None: no clutter)."""
    if spec is None:
        return None
    parts = [p.strip() for q in str(spec).lower().split(",") for p in q.split("+") if p.strip()]
    if not parts or parts == ["none"]:
        return None
    kw = {"forearm": False}
    for p in parts:
        name, _, value = p.partition("=")
        if not value and p.startswith("torso@") and p.endswith("m"):  # describe()'s form
            name, value = "torso", p[len("torso@"):-1]
        if value and name != "torso":
            raise TrackerError("clutter", f"{p!r}: only the torso takes a value (torso=GAP_M)")
        if name in ("forearm", "sleeve"):
            kw["forearm"] = True
            kw["sleeve"] = kw.get("sleeve", False) or name == "sleeve"
        elif name == "upperarm":
            kw["forearm"] = kw["upper_arm"] = True
        elif name == "torso":
            kw["torso"] = True
            if value:
                try:
                    kw["torso_gap_m"] = float(value)
                except ValueError:
                    raise TrackerError("clutter", f"{p!r}: the torso gap must be a number of metres") from None
        elif name == "table":
            kw["table"] = True
        elif name in ("object", "box", "cylinder"):
            kw["object"] = "cylinder" if name == "cylinder" else "box"
        else:
            raise TrackerError("clutter", f"unknown clutter {p!r} (forearm, sleeve, upperarm, torso[=gap], "
                                          "table, object, box, cylinder, none)")
    return kw
