"""Training data for the hand-part detector (:mod:`tracker.detector`): labelled depth crops drawn by
our renderer with domain randomisation.

Each scene (:func:`draw_scene`, from a :class:`DataRecipe` and a seed) picks

- a posture from our posture data — the fingerfist postures (htrack), samples of the shipped
  synergy bundle (its Gaussian in PC space, within its PC limits), the West–Hogan CyberGlove
  reach-to-grasp angles (mapped column by column onto our DoF and clipped to the limits: an
  approximate conversion, good enough to draw plausible grasping hands), the lab's named postures
  (fist, grasp, pinch, spread, open and counting hands, jittered) or uniform random angles within
  the hand's limits;
- an orientation uniform over the whole sphere (palm, back, side or fingers to the camera; only a
  forearm pointing at the camera with the hand behind it is drawn again);
- a hand 0.7–1.7 × the model (log-uniform) with finger lengths ±10 %, left or right;
- a forearm (bare or sleeved), a torso, a table, a box or cylinder near the hand (often in front
  of fingers);
- a sensor: Kinect v1, SR305 or D4xx intrinsics (focal ±5 %) with its noise model
  (:mod:`tracker.sim.noise`), extra random dropouts and flying pixels, or no noise;
- a distance of 0.3–1.5 m, the hand anywhere in the central 70 % of the image.

The frame is rendered through a camera cropped to a window around the hand (the same pixels as
the full frame's, cheaper): a :class:`Crop` holds the noisy depth, per-pixel part labels (the
hand pixels' nearest keypoint among those of their own bone, :data:`tracker.detector.PART_NAMES`;
:data:`tracker.detector.OTHER` on clutter; −1 where nothing), the 21 keypoints (pixels and depth)
and the crop's intrinsics. :func:`save_crops` / :func:`load_crops` keep a set as one ``.npz``.
"""
from __future__ import annotations

import io
import json
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from handmodel import HandModel
from handmodel.fileio import atomic_write_bytes, load_npz
from handmodel.rigid import euler_to_matrix, matrix_to_euler

from .. import TRACKING_HAND
from ..io.cameras import Camera, preset
from ..detector import OTHER
from ..errors import TrackerError
from .hands import FINGERS, HandShape
from .motions import FACING, FIST, POSTURES, fingerfist_path, hand_centre, read_schroeder26
from .noise import NoiseModel
from .clutter import Clutter
from .render import DepthRenderer

#: Sensors: camera intrinsics and the noise preset drawn with them. D4xx: a D435's depth stream at
#: 640×480 (fx ≈ 383 px; the exact value differs by unit).
SENSORS = {
    "kinect1": (preset("kinect1"), "kinect1"),
    "sr305": (preset("sr305"), "sr305"),
    "d4xx": (Camera(640, 480, 383.0, 383.0, 320.0, 240.0, 0.001, "uint16", "d4xx"), "d4xx"),
}
WEST_HOGAN_FILE = "west_hogan_cyberglove/X_R2G_bySubject.mat"
# West–Hogan columns (T Rot, T MCP, T IP, T ABD, then MCP, PIP, DIP, ABD per finger) → our
# posture order (per finger: 1_abd, 1_flex, 2_flex, 3_flex); their flexion is negative towards the
# palm as ours. The thumb's rotation stands in for its first flexion.
_WH_COLUMNS = (3, 0, 1, 2, 7, 4, 5, 6, 11, 8, 9, 10, 15, 12, 13, 14, 19, 16, 17, 18)


def shared_data() -> Path:
    """``../shared/data`` beside the checkout (where fingerfist and West–Hogan live)."""
    return fingerfist_path().parents[1]


@dataclass(frozen=True)
class DataRecipe:
    """How scenes are drawn (the training set's recipe, written into the detector's manifest).

    Parameters
    ----------
    hand_model : the base hand (the tracker's)
    size_range : hand size relative to the model (drawn log-uniform)
    finger_spread : finger length factors drawn uniform within 1 ± this
    distance_m : the hand centre's depth
    postures : source name → weight (``fingerfist``, ``bundle``, ``west_hogan``, ``named``, ``random``)
    sensors : sensor name → weight (:data:`SENSORS` and ``none``: the Kinect v1 camera without noise)
    p_right, p_forearm, p_sleeve, p_torso, p_table, p_object : probabilities of each scene element
    p_extra_noise : probability of extra random dropouts (≤ 4 %) and flying pixels
    window_m : half the crop's side at the hand (metres per unit of hand size) plus ``margin_m``
    orientations : ``sphere`` (uniform over all rotations) or ``user`` (palm, back or side to the
        camera, turned in the image plane by up to ``roll_deg`` from fingers-up and tilted by up to
        ``tilt_deg`` about the camera's x and y axes: how a user shows a hand to a camera)
    """

    hand_model: str = TRACKING_HAND
    size_range: tuple = (0.7, 1.7)
    finger_spread: float = 0.10
    distance_m: tuple = (0.3, 1.5)
    postures: dict = field(default_factory=lambda: {"fingerfist": 0.3, "bundle": 0.2, "west_hogan": 0.15,
                                                    "named": 0.2, "random": 0.15})
    sensors: dict = field(default_factory=lambda: {"kinect1": 0.3, "sr305": 0.35, "d4xx": 0.25, "none": 0.1})
    p_right: float = 0.5
    p_forearm: float = 0.9
    p_sleeve: float = 0.35
    p_torso: float = 0.35
    p_table: float = 0.3
    p_object: float = 0.3
    p_extra_noise: float = 0.3
    orientations: str = "sphere"
    roll_deg: float = 90.0
    tilt_deg: float = 50.0
    window_m: float = 0.12
    margin_m: float = 0.06

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True, eq=False)
class Crop:
    """One labelled depth crop.

    Attributes
    ----------
    depth : (h, w) float32, metres, NaN where the sensor gives nothing
    parts : (h, w) int8: 0–20 hand part, 21 other surface, −1 nothing (from the noise-free render)
    camera : (4,) fx, fy, cx, cy of the crop
    keypoints_uv : (21, 2) keypoint pixels in the crop
    keypoints_z : (21,) keypoint depths (metres)
    mirror : +1 left hand, −1 right (the detector's feature sign)
    meta : dict (posture source, sensor, size, clutter, distance)
    """

    @property
    def roll(self) -> float:
        """The hand's turn in the image (radians): 0 with the wrist → middle finger base pointing up."""
        return hand_roll(self.keypoints_uv)

    depth: np.ndarray
    parts: np.ndarray
    camera: np.ndarray
    keypoints_uv: np.ndarray
    keypoints_z: np.ndarray
    mirror: float
    meta: dict


def hand_roll(keypoints_uv) -> float:
    """The image angle of the wrist → middle finger base direction, 0 = up (−v), positive clockwise
    on screen (towards +u): the turn :func:`tracker.detector.offset_map` undoes."""
    e = np.asarray(keypoints_uv, float)[9] - np.asarray(keypoints_uv, float)[0]
    return float(np.arctan2(e[0], -e[1]))


# ----------------------------------------------------------------------------- postures
@lru_cache(maxsize=1)
def _fingerfist() -> np.ndarray:
    p = fingerfist_path()
    if not p.is_file():
        raise TrackerError(str(p), "fingerfist postures not found (set TRACKER_FINGERFIST)")
    return read_schroeder26(p)


@lru_cache(maxsize=1)
def _west_hogan() -> np.ndarray:
    from scipy.io import loadmat

    p = shared_data() / WEST_HOGAN_FILE
    if not p.is_file():
        raise TrackerError(str(p), "West–Hogan CyberGlove data not found")
    X = loadmat(p)["X_R2G_bySubject"]  # (frames, 23, subjects)
    X = np.concatenate([X[:, :, s] for s in range(X.shape[2])])
    return X[:, _WH_COLUMNS]


@lru_cache(maxsize=1)
def _bundle_arrays():
    from synergy.bundle import load_bundle

    m = load_bundle("fingerfist").model
    k = len(m.explained_variance_)  # the bundle's kept PCs
    return m.mean_, m.components_, np.sqrt(m.explained_variance_), m.pc_min_[:k], m.pc_max_[:k]


def draw_posture(source: str, rng, limits) -> np.ndarray:
    """A posture ``(20,)`` from one source (see the module docstring), within ``limits`` (20, 2)."""
    lo, hi = limits[:, 0], limits[:, 1]
    if source == "fingerfist":
        F = _fingerfist()
        p = F[rng.integers(len(F))]
    elif source == "bundle":
        mean, comps, sd, pmin, pmax = _bundle_arrays()
        a = np.clip(rng.normal(0.0, 1.0, len(sd)) * sd, pmin, pmax)
        p = mean + a @ comps
    elif source == "west_hogan":
        W = _west_hogan()
        p = W[rng.integers(len(W))]
    elif source == "named":
        kind = rng.integers(3)
        if kind == 0:
            p = list(POSTURES.values())[rng.integers(len(POSTURES))].copy()
        elif kind == 1:  # counting: some fingers in the fist, the others open
            p = np.where(np.repeat(rng.random(5) < 0.5, 4), FIST, 0.0)
        else:  # between two named postures
            a, b = rng.choice(len(POSTURES), 2, replace=False)
            t = rng.random()
            p = (1 - t) * list(POSTURES.values())[a] + t * list(POSTURES.values())[b]
        p = p + rng.normal(0.0, 0.08, 20)
    elif source == "random":
        p = rng.uniform(lo, hi)
    else:
        raise TrackerError("posture source", f"unknown {source!r}")
    return np.clip(p, lo, hi)


def random_rotation(rng) -> np.ndarray:
    """A rotation uniform over SO(3) (QR of a Gaussian matrix, signs fixed)."""
    Q, R = np.linalg.qr(rng.normal(size=(3, 3)))
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def draw_orientation(recipe: DataRecipe, rng) -> np.ndarray:
    """The hand's rotation into the camera frame by ``recipe.orientations``."""
    if recipe.orientations == "sphere":
        return random_rotation(rng)
    if recipe.orientations != "user":
        raise TrackerError("orientations", f"must be sphere or user, got {recipe.orientations!r}")
    facing = FACING[("palm", "back", "side")[rng.integers(3)]]
    if rng.random() < 0.5 and facing is FACING["side"]:
        facing = np.diag([-1.0, 1.0, -1.0]) @ facing  # the little finger's side
    a = np.radians([rng.uniform(-recipe.tilt_deg, recipe.tilt_deg), rng.uniform(-recipe.tilt_deg, recipe.tilt_deg),
                    rng.uniform(-recipe.roll_deg, recipe.roll_deg)])
    return euler_to_matrix(a) @ facing


def _pick(weights: dict, rng) -> str:
    names = list(weights)
    w = np.array([weights[n] for n in names], float)
    return names[rng.choice(len(names), p=w / w.sum())]


@lru_cache(maxsize=4)
def _base_hand(name: str, right: bool) -> HandModel:
    return HandModel.load(name, right=right)


# ----------------------------------------------------------------------------- scenes
def part_labels(hand: HandModel, theta, depth, labels, camera) -> np.ndarray:
    """Per-pixel parts of a noise-free render: each hand pixel's nearest keypoint among its own
    bone's two ends (the palm's: the wrist and the five finger bases); clutter :data:`OTHER`."""
    out = np.full(depth.shape, -1, np.int8)
    out[(labels < -1) & np.isfinite(depth)] = OTHER
    kp = hand.keypoints(theta)
    rows, cols = np.nonzero(labels >= 0)
    if len(rows) == 0:
        return out
    z = depth[rows, cols].astype(float)
    P = np.stack([(cols - camera.cx) * z / camera.fx, (rows - camera.cy) * z / camera.fy, z], axis=1)
    seg = labels[rows, cols]
    names = list(hand.keypoint_names)
    part = np.empty(len(rows), np.int8)
    for s, segment in enumerate(hand.segments):
        sel = seg == s
        if not sel.any():
            continue
        j = segment.joint
        cand = ([names.index(n) for n in ("wrist", "thumb1", "index1", "middle1", "ring1", "pinky1")] if j == 0
                else [j, j + 1])
        d = np.linalg.norm(P[sel, None, :] - kp[None, cand, :], axis=2)
        part[sel] = np.asarray(cand)[np.argmin(d, axis=1)]
    out[rows, cols] = part
    return out


def draw_scene(recipe: DataRecipe, rng) -> Crop:
    """One labelled crop drawn by ``recipe`` with the generator ``rng``."""
    right = bool(rng.random() < recipe.p_right)
    base = _base_hand(recipe.hand_model, right)
    scale = float(np.exp(rng.uniform(*np.log(recipe.size_range))))
    fingers = {f: float(rng.uniform(1 - recipe.finger_spread, 1 + recipe.finger_spread)) for f in FINGERS}
    shape = HandShape(scale, fingers)
    hand = shape.apply(base)
    post = ~hand.pose_mask
    source = _pick(recipe.postures, rng)
    theta = np.zeros(hand.n_dofs)
    theta[post] = draw_posture(source, rng, hand.limits[post])
    while True:  # not a forearm pointing at the camera with the hand behind it
        R = draw_orientation(recipe, rng)
        if (R @ np.array([0.0, -1.0, 0.0]))[2] > -0.8:
            break
    sensor = _pick(recipe.sensors, rng)
    cam0, noise_name = SENSORS.get(sensor, SENSORS["kinect1"])
    k = float(rng.uniform(0.95, 1.05))
    z = float(rng.uniform(*recipe.distance_m))
    u = rng.uniform(0.15, 0.85) * cam0.width
    v = rng.uniform(0.15, 0.85) * cam0.height
    centre = np.array([(u - cam0.cx) * z / (cam0.fx * k), (v - cam0.cy) * z / (cam0.fy * k), z])
    theta[:3] = centre - R @ hand_centre(hand)
    theta[3:6] = matrix_to_euler(R)
    # the crop: a window around the hand, within the image
    half = (cam0.fx * k) * (recipe.window_m * scale + recipe.margin_m) / z
    x0, x1 = int(max(0, np.floor(u - half))), int(min(cam0.width, np.ceil(u + half)))
    y0, y1 = int(max(0, np.floor(v - half))), int(min(cam0.height, np.ceil(v + half)))
    cam = Camera(x1 - x0, y1 - y0, cam0.fx * k, cam0.fy * k, cam0.cx - x0, cam0.cy - y0, cam0.depth_scale_m,
                 cam0.depth_encoding, cam0.name)
    clutter = _draw_clutter(recipe, rng, scale)
    r = DepthRenderer(hand, cam).render(theta, labels=True, clutter=clutter, incidence=True, reflectance=True)
    parts = part_labels(hand, theta, r.depth, r.labels, cam)
    nm = NoiseModel.preset("none" if sensor == "none" else noise_name)
    if sensor != "none" and rng.random() < recipe.p_extra_noise:
        nm = nm.with_(random_drop_prob=float(rng.uniform(0, 0.04)),
                      flying_prob=float(min(1.0, nm.flying_prob + rng.uniform(0, 0.3))))
    depth = nm.apply(r.depth, cam, rng, r.cos_incidence, r.reflectance)
    kp = hand.keypoints(theta)
    uv = np.stack([cam.fx * kp[:, 0] / kp[:, 2] + cam.cx, cam.fy * kp[:, 1] / kp[:, 2] + cam.cy], axis=1)
    meta = {"posture": source, "sensor": sensor, "scale": round(scale, 4), "right": right,
            "clutter": clutter.describe() if clutter else "none", "distance_m": round(z, 4)}
    return Crop(depth.astype(np.float32), parts, np.array([cam.fx, cam.fy, cam.cx, cam.cy]), uv, kp[:, 2].copy(),
                -1.0 if right else 1.0, meta)


def _draw_clutter(recipe: DataRecipe, rng, scale: float) -> Clutter | None:
    forearm = bool(rng.random() < recipe.p_forearm)
    obj = None
    if rng.random() < recipe.p_object:
        obj = "box" if rng.random() < 0.5 else "cylinder"
    c = Clutter(forearm=forearm, sleeve=forearm and bool(rng.random() < recipe.p_sleeve),
                torso=bool(rng.random() < recipe.p_torso), torso_gap_m=float(rng.uniform(0.05, 0.30)),
                torso_offset_m=(float(rng.uniform(-0.1, 0.1)), float(rng.uniform(0.0, 0.2))),
                table=bool(rng.random() < recipe.p_table), table_view_deg=float(rng.uniform(15, 90)),
                table_gap_m=float(rng.uniform(0.04, 0.15)), object=obj,
                # beside, in front of (hiding fingers) or behind the hand
                object_offset_m=(float(rng.uniform(-0.09, 0.09)), float(rng.uniform(-0.06, 0.06)),
                                 float(rng.uniform(-0.08, 0.06))),
                object_size_m=(float(rng.uniform(0.015, 0.045)), float(rng.uniform(0.03, 0.08)),
                               float(rng.uniform(0.015, 0.045))))
    c = c.sized(scale)
    return c if c.parts else None


def draw_crops(recipe: DataRecipe, seed: int, n: int, progress=None) -> list:
    """``n`` crops; crop ``i`` is drawn from its own generator ``(seed, i)``, so any subset is reproducible."""
    out = []
    for i in range(n):
        out.append(draw_scene(recipe, np.random.default_rng([seed, i])))
        if progress is not None:
            progress(i + 1, n)
    return out


# ----------------------------------------------------------------------------- files
def save_crops(path, crops, recipe: DataRecipe, seed: int, *, overwrite: bool = False) -> Path:
    """Write crops as one ``.npz`` (ragged images concatenated; no pickles; the recipe and seed as JSON)."""
    shapes = np.array([c.depth.shape for c in crops], np.int64).reshape(-1, 2)
    buf = io.BytesIO()
    np.savez_compressed(
        buf, depth=np.concatenate([c.depth.ravel() for c in crops]),
        parts=np.concatenate([c.parts.ravel() for c in crops]), shapes=shapes,
        camera=np.array([c.camera for c in crops]), keypoints_uv=np.array([c.keypoints_uv for c in crops]),
        keypoints_z=np.array([c.keypoints_z for c in crops]), mirror=np.array([c.mirror for c in crops]),
        meta=np.array(json.dumps({"recipe": recipe.to_dict(), "seed": seed, "crops": [c.meta for c in crops]})))
    return atomic_write_bytes(path, buf.getvalue(), overwrite=overwrite)


def load_crops(path) -> list:
    """The crops of a :func:`save_crops` file."""
    with load_npz(path, TrackerError, what="crop set .npz") as z:
        need = ("depth", "parts", "shapes", "camera", "keypoints_uv", "keypoints_z", "mirror", "meta")
        missing = [n for n in need if n not in z.files]
        if missing:
            raise TrackerError(str(path), f"not a crop set: missing {', '.join(missing)}")
        shapes = z["shapes"]
        meta = json.loads(str(z["meta"][()]))
        sizes = shapes.prod(axis=1)
        if sizes.sum() != len(z["depth"]) or sizes.sum() != len(z["parts"]):
            raise TrackerError(str(path), "image sizes do not add up to the pixels stored")
        ends = np.cumsum(sizes)
        out = []
        for i, (h, w) in enumerate(shapes):
            a, b = ends[i] - sizes[i], ends[i]
            out.append(Crop(z["depth"][a:b].reshape(h, w), z["parts"][a:b].reshape(h, w), z["camera"][i],
                            z["keypoints_uv"][i], z["keypoints_z"][i], float(z["mirror"][i]), meta["crops"][i]))
    return out

