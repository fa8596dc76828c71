"""Hand motions for synthetic recordings: θ trajectories ``(F, 26)`` in the camera frame.

A :class:`Motion` is the posture (20 finger angles) per frame plus a global pose that places the
hand in front of the camera (camera frame: x right, y down, z forward; metres, radians). Postures
come from joint-angle tables (CSV with DoF-name columns), from posture files in the schroeder26
format (``fingerfist.txt``; its unreliable columns 1–6 are replaced), or are procedural; the global
pose comes from the table itself or from a :class:`GlobalPath`. Named scenarios live in
:data:`SCENARIOS`.

Examples
--------
>>> m = make_motion("open-close", frames=10, fps=30)
>>> m.theta.shape, m.fps
((10, 26), 30.0)
>>> sorted(SCENARIOS)[:3]
['count', 'fast', 'fingerfist']
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from handmodel import HandModel
from handmodel.rigid import euler_to_matrix, matrix_to_euler
from synergy import postures as synergy_postures
from synergy.errors import SynergyError

from ..errors import TrackerError

N_POSE = 6

# 20-vectors in posture order (thumb, index, middle, ring, pinky: 1_abd 1_flex 2_flex 3_flex), radians.
# Flexion is negative toward the palm; abduction positive toward the pinky side (DESIGN.md).
OPEN = np.zeros(20)
FIST = np.array([0.25, -0.5, -0.4, -0.9,  0.1, -1.0, -1.5, -1.2,  0.0, -1.0, -1.5, -1.2,
                 -0.05, -1.05, -1.5, -1.1,  -0.15, -1.15, -1.3, -1.2])
GRASP = np.array([0.2, -0.35, -0.3, -0.4,  0.05, -0.9, -1.0, -0.5,  0.0, -0.95, -1.05, -0.5,
                  -0.05, -1.0, -1.0, -0.5,  -0.1, -1.05, -0.95, -0.5])
PINCH = np.array([0.25, -0.45, -0.35, -0.45,  0.1, -0.75, -0.75, -0.4,  0.0, -0.3, -0.3, -0.2,
                  0.0, -0.3, -0.3, -0.2,  0.0, -0.3, -0.3, -0.2])
SPREAD = np.array([-0.25, 0.0, 0.0, 0.0,  -0.3, 0.0, 0.0, 0.0,  0.0, 0.0, 0.0, 0.0,
                   0.2, 0.0, 0.0, 0.0,  0.3, 0.0, 0.0, 0.0])
POSTURES = {"open": OPEN, "fist": FIST, "grasp": GRASP, "pinch": PINCH, "spread": SPREAD}

# Rotation taking the hand frame (fingers +y, palm toward −z) to the camera frame with the fingers
# up in the image (−y_cam) and the given side toward the camera (−z_cam).
FACING = {
    "palm": np.diag([-1.0, -1.0, 1.0]),  # palm normal −z_hand → −z_cam
    "back": np.diag([1.0, -1.0, -1.0]),  # palm normal → +z_cam: the back of the hand faces the camera
    "side": np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]),  # thumb side (+x_hand) → −z_cam
}


def hand_centre(hand) -> np.ndarray:
    """Mean keypoint of the flat hand in the hand frame: the point a :class:`GlobalPath` moves."""
    return hand.keypoints(np.zeros(hand.n_dofs)).mean(axis=0)


# ----------------------------------------------------------------------------- global paths
@dataclass(frozen=True)
class GlobalPath:
    """Trajectory of the hand centre and the hand's orientation in the camera frame.

    Translation: ``centre + amplitude · sin(2π speed t / period + phase)`` per axis (metres).
    Orientation: ``R(t) = W(t) · Rx·Ry·Rz(tilt) · FACING[facing]`` where ``W`` rotates about the
    camera axes through the hand centre by ``wobble · sin(2π speed t / wobble_period)`` and
    ``spin`` adds a steady turn (degrees per second) about the camera y axis.

    The defaults keep the hand at 0.68–0.82 m, palm facing the camera, fingers up.
    """

    centre: tuple = (0.0, 0.0, 0.75)
    amplitude: tuple = (0.04, 0.03, 0.07)
    period_s: tuple = (7.0, 5.0, 9.0)
    phase: tuple = (0.0, 1.0, 2.0)
    facing: str = "palm"
    tilt_deg: tuple = (0.0, 0.0, 0.0)
    wobble_deg: tuple = (10.0, 10.0, 8.0)
    wobble_period_s: tuple = (6.0, 8.0, 10.0)
    spin_deg_s: float = 0.0
    speed: float = 1.0

    def __post_init__(self):
        if self.facing not in FACING:
            raise TrackerError("global path", f"facing must be one of {', '.join(FACING)}, got {self.facing!r}")

    def rotations(self, t) -> np.ndarray:
        """Hand orientations ``(F, 3, 3)`` at times ``t`` (seconds)."""
        t = np.asarray(t, float)
        w = np.radians(self.wobble_deg) * np.sin(
            2 * np.pi * self.speed * t[:, None] / np.asarray(self.wobble_period_s) + np.asarray(self.phase))
        W = euler_to_matrix(w)
        spin = np.radians(self.spin_deg_s) * self.speed * t
        c, s = np.cos(spin), np.sin(spin)
        S = np.zeros((len(t), 3, 3))
        S[:, 0, 0], S[:, 0, 2], S[:, 1, 1], S[:, 2, 0], S[:, 2, 2] = c, s, 1.0, -s, c
        R0 = euler_to_matrix(np.radians(self.tilt_deg)) @ FACING[self.facing]
        return W @ S @ R0

    def centres(self, t) -> np.ndarray:
        """Hand-centre positions ``(F, 3)`` at times ``t`` (seconds)."""
        t = np.asarray(t, float)[:, None]
        arg = 2 * np.pi * self.speed * t / np.asarray(self.period_s) + np.asarray(self.phase)
        return np.asarray(self.centre) + np.asarray(self.amplitude) * np.sin(arg)

    def pose(self, hand, frames: int, fps: float) -> np.ndarray:
        """Global pose columns ``(frames, 6)``: tx ty tz rx ry rz with R = Rx·Ry·Rz, angles unwrapped."""
        t = np.arange(frames) / float(fps)
        R = self.rotations(t)
        trans = self.centres(t) - R @ hand_centre(hand)
        return np.concatenate([trans, continuous_euler(R)], axis=1)


def continuous_euler(R) -> np.ndarray:
    """Angles ``(F, 3)`` with R = Rx·Ry·Rz that change continuously from frame to frame.

    Of the two solutions ``(a, b, c)`` and ``(a + π, π − b, c + π)`` (and their 2π shifts) each
    frame takes the one nearest the previous frame's, so a path through ``b = ±90°`` does not jump.
    """
    e = matrix_to_euler(np.asarray(R, float).reshape(-1, 3, 3))
    out = np.empty_like(e)
    prev = None
    for i, (a, b, c) in enumerate(e):
        cands = np.array([[a, b, c], [a + np.pi, np.pi - b, c + np.pi]])
        if prev is None:
            cands = (cands + np.pi) % (2 * np.pi) - np.pi
            out[i] = cands[0]
        else:
            cands = prev + (cands - prev + np.pi) % (2 * np.pi) - np.pi
            out[i] = cands[np.argmin(np.abs(cands - prev).sum(1))]
        prev = out[i]
    return out


STILL = GlobalPath(amplitude=(0.0, 0.0, 0.0), wobble_deg=(0.0, 0.0, 0.0))


# ----------------------------------------------------------------------------- motions
@dataclass(frozen=True, eq=False)
class Motion:
    """A θ trajectory: ``theta`` ``(F, 26)`` at ``fps`` frames per second (read-only)."""

    name: str
    theta: np.ndarray
    fps: float
    description: str = ""
    source: str | None = None

    def __post_init__(self):
        th = np.array(self.theta, dtype=np.float64)
        if th.ndim != 2 or th.shape[1] != N_POSE + 20 or th.shape[0] == 0:
            raise TrackerError(self.name, f"motion needs θ of shape (F>0, 26), got {th.shape}")
        if not np.isfinite(th).all():
            raise TrackerError(self.name, "motion θ holds NaN or infinity")
        if not self.fps > 0:
            raise TrackerError(self.name, f"fps must be positive, got {self.fps}")
        th.setflags(write=False)
        object.__setattr__(self, "theta", th)
        object.__setattr__(self, "fps", float(self.fps))

    @property
    def frames(self) -> int:
        return int(self.theta.shape[0])

    @property
    def duration_s(self) -> float:
        return self.frames / self.fps

    def head(self, frames: int | None) -> "Motion":
        """The first ``frames`` frames (all when ``None`` or more than there are)."""
        if frames is None or frames >= self.frames:
            return self
        if frames < 1:
            raise TrackerError(self.name, f"frames must be at least 1, got {frames}")
        return replace(self, theta=self.theta[:frames])

    def resample(self, fps: float) -> "Motion":
        """The same motion at another frame rate (linear interpolation of θ over time)."""
        if fps == self.fps:
            return self
        t_old = np.arange(self.frames) / self.fps
        n = max(int(np.floor(t_old[-1] * fps + 1e-9)) + 1, 1)
        t_new = np.arange(n) / float(fps)
        th = np.stack([np.interp(t_new, t_old, c) for c in self.theta.T], axis=1)
        return replace(self, theta=th, fps=float(fps))


def with_path(postures, hand, fps: float, path: GlobalPath | None = None) -> np.ndarray:
    """θ ``(F, 26)`` from postures ``(F, 20)`` and the global pose of ``path`` (default :class:`GlobalPath`)."""
    P = np.asarray(postures, float)
    path = GlobalPath() if path is None else path
    return np.concatenate([path.pose(hand, len(P), fps), P], axis=1)


def keyframes(postures, frames: int, fps: float, period_s: float, hold: float = 0.25) -> np.ndarray:
    """Cycle through key postures: smooth (cosine) transitions, each key held ``hold`` of its slot."""
    K = np.asarray(postures, float)
    t = np.arange(frames) / fps
    slot = period_s / len(K)
    pos = t / slot
    k = np.floor(pos).astype(int)
    frac = pos - k
    s = np.clip((frac - hold) / (1.0 - hold), 0.0, 1.0)
    s = 0.5 - 0.5 * np.cos(np.pi * s)
    a, b = K[k % len(K)], K[(k + 1) % len(K)]
    return a + s[:, None] * (b - a)


# ----------------------------------------------------------------------------- file input
def _posture_names(hand) -> list:
    return list(hand.posture_names)


def from_table(table, *, hand=None, fps: float = 30.0, path: GlobalPath | None = None,
               name: str | None = None, source: str | None = None) -> Motion:
    """A motion from a joint-angle table (DataFrame or CSV path; columns = DoF names, radians).

    With a ``time_s`` column the rows are resampled to ``fps`` by linear interpolation (gaps of
    dropped rows are bridged); without it each row is one frame. Rows with a missing posture angle
    are dropped. Pose columns (tx … rz) that are absent are filled from ``path``.
    """
    hand = hand or HandModel.load()
    where = source or name or "table"
    if not isinstance(table, pd.DataFrame):
        p = Path(table)
        where = source or str(p)
        if not p.is_file():
            raise TrackerError(p, "no such file")
        try:
            table = pd.read_csv(p, comment="#", skipinitialspace=True)
        except (ValueError, OSError, pd.errors.ParserError, UnicodeDecodeError) as exc:
            raise TrackerError(p, f"cannot read CSV ({exc})") from None
        name = name or p.stem
    names = _posture_names(hand)
    missing = [c for c in names if c not in table.columns]
    if missing:
        raise TrackerError(where, f"missing posture column(s): {', '.join(missing)}")
    pose_names = [n for n in hand.dof_names if n not in names]
    cols = names + [c for c in pose_names if c in table.columns] + (["time_s"] if "time_s" in table.columns else [])
    try:
        A = table.loc[:, cols].to_numpy(dtype=float)
    except (ValueError, TypeError) as exc:
        raise TrackerError(where, f"non-numeric values ({exc})") from None
    keep = np.isfinite(A[:, :len(names)]).all(axis=1)
    A = A[keep]
    if A.shape[0] == 0:
        raise TrackerError(where, "no complete posture rows")
    if "time_s" in cols:
        t = A[:, -1]
        if not (np.isfinite(t).all() and np.all(np.diff(t) > 0)):
            raise TrackerError(where, "time_s must be finite and strictly increasing")
        n = int(np.floor((t[-1] - t[0]) * fps + 1e-9)) + 1
        grid = t[0] + np.arange(n) / fps
        A = np.stack([np.interp(grid, t, c) for c in A[:, :-1].T], axis=1)
        cols = cols[:-1]
    F = A.shape[0]
    theta = with_path(A[:, :len(names)], hand, fps, path)
    for j, c in enumerate(cols[len(names):]):
        col = A[:, len(names) + j]
        if not np.isfinite(col).all():
            raise TrackerError(where, f"column {c} has missing values")
        theta[:, hand.dof_names.index(c)] = col
    return Motion(name or "table", theta[:F], fps, "joint-angle table", source=str(where))


def read_schroeder26(path) -> np.ndarray:
    """The 20 posture columns (7–26) of a schroeder26 posture file, ``(F, 20)`` radians
    (:func:`synergy.postures.read_schroeder26`, failing with a :class:`~tracker.errors.TrackerError`)."""
    try:
        return synergy_postures.read_schroeder26(path)
    except SynergyError as exc:
        raise TrackerError(exc.where, exc.reason) from None


def from_postures_file(file, *, hand=None, fps: float = 30.0, path: GlobalPath | None = None,
                       name: str | None = None) -> Motion:
    """Replay a schroeder26 posture file one row per frame; its columns 1–6 (unreliable global
    pose) are replaced by the global path ``path`` (default :class:`GlobalPath`)."""
    hand = hand or HandModel.load()
    P = read_schroeder26(file)
    return Motion(name or Path(file).stem, with_path(P, hand, fps, path), fps,
                  "posture file replay (schroeder26, cols 1-6 replaced)", source=str(file))


def fingerfist_path() -> Path:
    """Where ``fingerfist.txt`` is: ``$TRACKER_FINGERFIST`` or ``../shared/data/htrack_schroeder/``
    beside the checkout."""
    env = os.environ.get("TRACKER_FINGERFIST")
    if env:
        return Path(env)
    # parents: sim, tracker, src, the checkout, the folder beside it
    return Path(__file__).resolve().parents[4] / "shared" / "data" / "htrack_schroeder" / "fingerfist.txt"


# ----------------------------------------------------------------------------- scenarios
@dataclass(frozen=True)
class Scenario:
    """A named motion recipe: ``build(hand, frames, fps, seed) -> θ (frames, 26)``."""

    name: str
    description: str
    seconds: float
    build: Callable = field(repr=False)


SCENARIOS: dict[str, Scenario] = {}


def _scenario(name: str, description: str, seconds: float = 4.0):
    def deco(fn):
        SCENARIOS[name] = Scenario(name, description, seconds, fn)
        return fn

    return deco


@_scenario("still", "open hand, palm to the camera at 0.75 m, no motion")
def _still(hand, frames, fps, seed):
    return with_path(np.tile(OPEN, (frames, 1)), hand, fps, STILL)


@_scenario("open-close", "all fingers open and close into a fist every 2 s; palm to the camera, slow drift")
def _open_close(hand, frames, fps, seed):
    return with_path(keyframes([OPEN, FIST], frames, fps, 2.0), hand, fps)


@_scenario("count", "fingers flex one after another (thumb to pinky) and open again; palm to the camera", 5.0)
def _count(hand, frames, fps, seed):
    keys = [OPEN.copy()]
    for f in range(5):
        k = keys[-1].copy()
        k[4 * f:4 * f + 4] = FIST[4 * f:4 * f + 4]
        keys.append(k)
    keys += keys[-2:0:-1]
    return with_path(keyframes(keys, frames, fps, 5.0), hand, fps)


@_scenario("spread", "fingers spread and close (abduction) with a slight bend; palm to the camera")
def _spread(hand, frames, fps, seed):
    return with_path(keyframes([OPEN, SPREAD, OPEN, PINCH], frames, fps, 4.0), hand, fps)


@_scenario("grasp-back", "power grasp seen from the back of the hand: the dorsal side faces the camera "
                         "while the fingers curl away from it (self-occluded), as in the paper's occlusion test")
def _grasp_back(hand, frames, fps, seed):
    path = GlobalPath(facing="back", tilt_deg=(-15.0, 0.0, 0.0), wobble_deg=(6.0, 6.0, 5.0))
    return with_path(keyframes([OPEN, GRASP], frames, fps, 3.0, hold=0.3), hand, fps, path)


@_scenario("fist-palm", "a fist, palm to the camera, opening and closing again every 3 s; the first frame is "
                        "the fist (a tracker meets the hand closed, its size unknown)")
def _fist_palm(hand, frames, fps, seed):
    return with_path(keyframes([FIST, OPEN], frames, fps, 3.0, hold=0.3), hand, fps)


@_scenario("fist-side", "the fist-palm motion with the thumb side to the camera (fingers curl across the view)")
def _fist_side(hand, frames, fps, seed):
    path = GlobalPath(facing="side", wobble_deg=(8.0, 8.0, 6.0))
    return with_path(keyframes([FIST, OPEN], frames, fps, 3.0, hold=0.3), hand, fps, path)


@_scenario("pinch", "thumb and index close to a pinch (tips 28 mm apart) and open every 2.5 s, palm to the "
                    "camera turned 30° towards the thumb side")
def _pinch(hand, frames, fps, seed):
    path = GlobalPath(tilt_deg=(0.0, -30.0, 0.0))
    return with_path(keyframes([OPEN, PINCH], frames, fps, 2.5, hold=0.3), hand, fps, path)


@_scenario("rotate", "hand closing and opening while it turns from palm to back and back (0–180° about the "
                     "vertical in 6 s)", 6.0)
def _rotate(hand, frames, fps, seed):
    path = GlobalPath(tilt_deg=(0.0, 90.0, 0.0), wobble_deg=(5.0, 90.0, 5.0), wobble_period_s=(6.0, 6.0, 6.0),
                      phase=(0.0, -np.pi / 2, 0.0))
    return with_path(keyframes([OPEN, GRASP], frames, fps, 3.0), hand, fps, path)


@_scenario("fast", "fast motion: open/close at 1.5 Hz while the hand sweeps ±12 cm (peak ≈ 1.1 m/s) and "
                   "turns ±30° at ≈ 1.1 Hz")
def _fast(hand, frames, fps, seed):
    path = GlobalPath(amplitude=(0.12, 0.06, 0.06), period_s=(0.7, 0.9, 1.1), wobble_deg=(30.0, 30.0, 25.0),
                      wobble_period_s=(0.8, 0.9, 1.0))
    return with_path(keyframes([OPEN, FIST], frames, fps, 0.67), hand, fps, path)


@_scenario("random", "smooth random postures within the model's joint limits (new key every 0.5 s, seeded)", 6.0)
def _random(hand, frames, fps, seed):
    rng = np.random.default_rng(seed)
    lim = np.asarray(hand.limits)[N_POSE:]
    n_keys = max(int(np.ceil(frames / fps / 0.5)) + 1, 2)
    keys = rng.uniform(lim[:, 0] * 0.8, lim[:, 1] * 0.8, (n_keys, 20))
    keys[0] = OPEN
    return with_path(keyframes(keys, frames, fps, n_keys * 0.5, hold=0.1), hand, fps)


@_scenario("fingerfist", "replay of the real fingerfist.txt postures (6000 rows, one per frame; file pose "
                         "replaced by the default path)", 200.0)
def _fingerfist(hand, frames, fps, seed):
    p = fingerfist_path()
    if not p.is_file():
        raise TrackerError(p, "fingerfist.txt not found (set TRACKER_FINGERFIST or give the file as --motion)")
    P = read_schroeder26(p)[:frames]
    return with_path(P, hand, fps)


def make_motion(spec: str | os.PathLike, *, hand=None, frames: int | None = None, fps: float = 30.0,
                seed: int = 0, path: GlobalPath | None = None) -> Motion:
    """A motion by scenario name or from a file (``.csv`` angle table, ``.txt``/``.dat`` schroeder26).

    ``frames`` defaults to the scenario's length (files: all rows); files are cut to ``frames``.
    ``path`` replaces the global path of file input.
    """
    hand = hand or HandModel.load()
    if frames is not None and frames < 1:
        raise TrackerError("frames", f"must be at least 1, got {frames}")
    if not fps > 0:
        raise TrackerError("fps", f"must be positive, got {fps}")
    key = str(spec)
    if key in SCENARIOS:
        sc = SCENARIOS[key]
        n = frames if frames is not None else max(int(round(sc.seconds * fps)), 1)
        theta = sc.build(hand, n, float(fps), seed)
        src = str(fingerfist_path()) if key == "fingerfist" else None
        return Motion(key, theta, fps, sc.description, source=src)
    p = Path(spec)
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return from_table(p, hand=hand, fps=fps, path=path).head(frames)
    if suffix in (".txt", ".dat"):
        return from_postures_file(p, hand=hand, fps=fps, path=path).head(frames)
    if p.exists():
        raise TrackerError(p, "unknown motion file type (.csv angle table, .txt/.dat schroeder26)")
    raise TrackerError(spec, f"no such scenario or file (scenarios: {', '.join(sorted(SCENARIOS))})")
