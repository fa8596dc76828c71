"""Hand keypoints from one depth frame: a per-pixel hand-part forest (inference only).

Each pixel is classified into one of 21 hand parts (the pixels nearest each keypoint of the model
hand, :data:`PART_NAMES`) or "other" (arm, body, table, objects) by a random decision forest on
depth-difference features (Shotton et al. 2011; Keskin et al. 2012 for hands). The feature of
pixel ``x`` with offsets ``u``, ``v`` (metres at 1 m) is

    f(x) = d(x + A·u·f/d(x)) − d(x + A·v·f/d(x)),

``f`` the focal lengths: the offsets shrink with depth, so a feature reads the same part of a hand
at any distance and through any camera. A probe off the image or on a pixel without depth reads
:data:`~tracker._detector_kernels.BACKGROUND_M` (the compiled probe, feature and mean shift:
:mod:`tracker._detector_kernels`). ``A`` (:func:`offset_map`) mirrors the offsets for a right hand
(one forest serves both) and turns them with the hand in the image plane: two layers (after Keskin's
multi-layered forests), a first forest whose pixels vote the hand's turn (:data:`ROLL_BINS` bins),
then the parts forest reading offsets turned by it (or by a turn the caller knows, e.g. from the
previous frame's fit) — a hand seen at any turn reads as one with its fingers up. A part's keypoint is the densest mode (mean shift) of its
pixels' 3-D points, weighted by probability × depth² (each pixel's area), pushed along the ray
by a per-keypoint depth learned on the training data (the joint lies inside the finger, the
pixels on its skin).

The forest is trained by :mod:`tracker.sim.train_detector` (scikit-learn) and shipped as flat
arrays in a sealed ``.npz`` under ``models/detectors/`` (no pickles; the manifest carries the
training command, data recipe, seed, metrics and the hashes of itself and the arrays). This
module never imports :mod:`tracker.sim`.

Examples
--------
>>> det = load_detector()
>>> det.n_trees, det.n_classes
(3, 22)
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numba as nb
import numpy as np

from handmodel import fileio
from handmodel.fileio import atomic_write_bytes, load_npz, manifest_sha256, models_dir

from ._detector_kernels import feature, mean_shift
from .io.cameras import as_camera
from .errors import TrackerError

#: The 21 parts: one per keypoint of the hand model (``HandModel.keypoint_names`` order).
PART_NAMES = ("wrist", "thumb1", "thumb2", "thumb3", "thumb_tip", "index1", "index2", "index3", "index_tip",
              "middle1", "middle2", "middle3", "middle_tip", "ring1", "ring2", "ring3", "ring_tip",
              "pinky1", "pinky2", "pinky3", "pinky_tip")
N_PARTS = len(PART_NAMES)
#: Class index of every pixel that is not the hand (arm, sleeve, body, table, object, flying pixels).
OTHER = N_PARTS
N_CLASSES = N_PARTS + 1
FORMAT = "hand-part-forest/1"
DETECTOR_NAME = "hand-parts"
#: The in-image turn of the hand is voted in this many bins of 360°/ROLL_BINS (the first layer).
ROLL_BINS = 8
#: A forest's arrays (:func:`forest_arrays`); a file holds the roll forest's under ``roll_`` and the parts'.
FOREST_ARRAYS = ("offsets", "thresholds", "left", "right", "leaf", "roots", "leaf_values")
#: The arrays of a detector file, in the order they are hashed.
ARRAY_NAMES = (*(f"roll_{n}" for n in FOREST_ARRAYS), *FOREST_ARRAYS, "keypoint_push_m")
MAX_FILE_BYTES = 200 * 1024 * 1024


# ----------------------------------------------------------------------------- features, the forest walk
def offset_map(mirror: float = 1.0, roll: float = 0.0) -> np.ndarray:
    """``(2, 2)``: offsets of the hand's canonical frame (a left hand, fingers up) into the image: a
    right hand mirrored (x negated), a hand turned by ``roll`` radians in the image turned with it.

    >>> offset_map(-1.0).tolist()
    [[-1.0, 0.0], [0.0, 1.0]]
    """
    c, s = np.cos(roll), np.sin(roll)
    return np.array([[c, -s], [s, c]]) @ np.diag([float(mirror), 1.0])


@nb.njit(cache=True)
def feature_matrix(depth, rows, cols, fx, fy, A, offsets):
    """``(N, F)`` float32 features of the pixels ``rows, cols`` for every offset pair of ``offsets``
    ``(F, 4)`` (ux, uy, vx, vy metres at 1 m) mapped by ``A`` (:func:`offset_map`); the training matrix."""
    n, F = rows.shape[0], offsets.shape[0]
    out = np.empty((n, F), np.float32)
    for i in range(n):
        d0 = depth[rows[i], cols[i]]
        for j in range(F):
            out[i, j] = feature(depth, rows[i], cols[i], d0, fx, fy, A, offsets[j, 0], offsets[j, 1],
                                offsets[j, 2], offsets[j, 3])
    return out


@nb.njit(cache=True)
def forest_proba(depth, rows, cols, fx, fy, A, offsets, thresholds, left, right, leaf, roots, leaf_values):
    """Class probabilities ``(N, C)`` of the pixels: every tree walked with each node's feature
    computed on demand (the same float32 value and ``<=`` test as scikit-learn's), leaf
    distributions averaged."""
    n, C, T = rows.shape[0], leaf_values.shape[1], roots.shape[0]
    out = np.zeros((n, C), np.float32)
    for i in range(n):
        r, c = rows[i], cols[i]
        d0 = depth[r, c]
        for t in range(T):
            k = roots[t]
            while left[k] >= 0:
                f = feature(depth, r, c, d0, fx, fy, A, offsets[k, 0], offsets[k, 1], offsets[k, 2],
                            offsets[k, 3])
                k = left[k] if np.float64(f) <= thresholds[k] else right[k]
            lv = leaf[k]
            for j in range(C):
                out[i, j] += leaf_values[lv, j]
        for j in range(C):
            out[i, j] /= T
    return out


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class Detection:
    """The detector's answer for one frame (keypoints in :data:`PART_NAMES` order).

    Attributes
    ----------
    keypoints_px : (21, 2) float
        (u, v) pixels; NaN where the part was not found.
    keypoints_depth_m : (21,) float
        z of each keypoint (the part's surface pushed to the joint), NaN where not found.
    keypoints_xyz : (21, 3) float
        Camera frame, metres; NaN where not found.
    confidence : (21,) float
        0–1: the mean part probability of the pixels at the mode × how many they are; 0 where not found.
    hand_score : float
        Mean probability of "some hand part" over the pixels classified (0: no hand there).
    pixels : int
        Pixels classified.
    region : (H, W) bool or None
        The part of the mask the keypoints were found in, where the detector narrowed it (the keypoint
        CNN's re-crop, :func:`tracker.keypoint_cnn.detect`); None: the whole mask it was given.
    """

    keypoints_px: np.ndarray
    keypoints_depth_m: np.ndarray
    keypoints_xyz: np.ndarray
    confidence: np.ndarray
    hand_score: float
    pixels: int
    region: np.ndarray | None = None

    @property
    def found(self) -> np.ndarray:
        """Keypoints with a position."""
        return np.isfinite(self.keypoints_xyz).all(axis=1)


# ----------------------------------------------------------------------------- the model
@dataclass(frozen=True, eq=False)
class HandPartForest:
    """A trained hand-part forest as flat arrays (see :func:`forest_arrays`) with its manifest.

    Parameters
    ----------
    arrays : dict
        :data:`ARRAY_NAMES` → arrays.
    manifest : dict
        Training command, data recipe, seed, metrics, hashes.
    path : Path or None
        The file it was read from.
    """

    arrays: dict
    manifest: dict
    path: Path | None = None

    @property
    def n_trees(self) -> int:
        return int(len(self.arrays["roots"]))

    @property
    def n_classes(self) -> int:
        return int(self.arrays["leaf_values"].shape[1])

    @property
    def bandwidth_m(self) -> float:
        return float(self.manifest.get("bandwidth_m", 0.012))

    def proba(self, depth, rows, cols, fx, fy, mirror=1.0, roll=0.0, *, layer: str = "") -> np.ndarray:
        """Class probabilities of pixels ``rows, cols`` of ``depth`` (float32 metres): of the parts
        ``(N, 22)`` with the offsets turned by ``roll``, or with ``layer="roll_"`` of the roll bins
        ``(N, ROLL_BINS + 1)``, the last "not the hand"."""
        a = {n: self.arrays[layer + n] for n in FOREST_ARRAYS}
        return forest_proba(np.ascontiguousarray(depth, np.float32), np.ascontiguousarray(rows, np.int64),
                            np.ascontiguousarray(cols, np.int64), float(fx), float(fy), offset_map(mirror, roll),
                            a["offsets"], a["thresholds"], a["left"], a["right"], a["leaf"], a["roots"],
                            a["leaf_values"])

    def roll(self, depth, rows, cols, fx, fy, mirror=1.0) -> float:
        """The hand's turn in the image (radians, 0 = fingers up) voted by the pixels: the circular
        mean of the roll bins' centres weighted by their probabilities."""
        p = self.proba(depth, rows, cols, fx, fy, mirror, layer="roll_")[:, :ROLL_BINS].sum(axis=0)
        centres = np.arange(ROLL_BINS) * (2 * np.pi / ROLL_BINS)
        return float(mirror) * float(np.arctan2(p @ np.sin(centres), p @ np.cos(centres)))


def forest_arrays(estimators, offsets, n_classes: int = N_CLASSES) -> dict:
    """The flat arrays (:data:`FOREST_ARRAYS`) of fitted scikit-learn decision trees (a
    ``RandomForestClassifier``'s ``estimators_``, trained on the columns of ``offsets`` (F, 4) and
    on classes 0…n_classes−1).

    Every node carries its feature's offsets, its threshold and its children (−1 at leaves);
    ``leaf`` points leaves into ``leaf_values`` (L, 22), the normalised class distributions."""
    off, thr, lft, rgt, leaf, roots, values = [], [], [], [], [], [], []
    base, n_leaves = 0, 0
    for est in estimators:
        t = est.tree_
        classes = np.asarray(est.classes_, int)
        is_leaf = t.children_left < 0
        roots.append(base)
        f = np.where(is_leaf, 0, t.feature)
        off.append(np.where(is_leaf[:, None], 0.0, np.asarray(offsets, np.float64)[f]))
        thr.append(np.where(is_leaf, 0.0, t.threshold))
        lft.append(np.where(is_leaf, -1, t.children_left + base))
        rgt.append(np.where(is_leaf, -1, t.children_right + base))
        idx = np.cumsum(is_leaf) - 1 + n_leaves
        leaf.append(np.where(is_leaf, idx, -1))
        v = np.zeros((int(is_leaf.sum()), n_classes))
        raw = t.value[is_leaf, 0, :]
        v[:, classes] = raw / np.maximum(raw.sum(axis=1, keepdims=True), 1e-300)
        values.append(v)
        base += t.node_count
        n_leaves += int(is_leaf.sum())
    return {"offsets": np.concatenate(off).astype(np.float64), "thresholds": np.concatenate(thr).astype(np.float64),
            "left": np.concatenate(lft).astype(np.int64), "right": np.concatenate(rgt).astype(np.int64),
            "leaf": np.concatenate(leaf).astype(np.int64), "roots": np.asarray(roots, np.int64),
            "leaf_values": np.concatenate(values).astype(np.float32)}


# ----------------------------------------------------------------------------- file: write, read, seal
def arrays_sha256(arrays: dict) -> str:
    """The detector arrays' seal: :func:`handmodel.fileio.arrays_sha256` over :data:`ARRAY_NAMES`."""
    return fileio.arrays_sha256(arrays, ARRAY_NAMES)


def save_detector(path, arrays: dict, manifest: dict, *, overwrite: bool = False) -> Path:
    """Write a sealed detector file (compressed ``.npz``: the arrays and the manifest as JSON),
    verified by reading it back before it takes its name."""
    import io

    missing = [n for n in ARRAY_NAMES if n not in arrays]
    if missing:
        raise TrackerError(str(path), f"detector arrays missing: {', '.join(missing)}")
    m = dict(manifest, format=FORMAT, arrays_sha256=arrays_sha256(arrays))
    m["manifest_sha256"] = manifest_sha256(m)
    buf = io.BytesIO()
    np.savez_compressed(buf, **{n: np.asarray(arrays[n]) for n in ARRAY_NAMES},
                        manifest=np.array(json.dumps(m, indent=1, sort_keys=True)))
    try:
        out = atomic_write_bytes(path, buf.getvalue(), overwrite=overwrite)
    except FileExistsError:
        raise TrackerError(str(path), "exists (give another output folder)") from None
    except OSError as exc:
        raise TrackerError(str(path), f"cannot write ({exc.strerror or exc})") from None
    read_detector(out)
    return out


def read_detector(path) -> HandPartForest:
    """Read and verify a detector file: the manifest's seal, the arrays' hash, shapes and indices."""
    path = Path(path)
    if not path.is_file():
        raise TrackerError(str(path), "no such detector file")
    with load_npz(path, TrackerError, max_bytes=MAX_FILE_BYTES, what="detector .npz") as z:
        missing = [n for n in (*ARRAY_NAMES, "manifest") if n not in z.files]
        if missing:
            raise TrackerError(str(path), f"not a detector file: missing array(s) {', '.join(missing)}")
        arrays = {n: z[n] for n in ARRAY_NAMES}
        raw = z["manifest"]
    if raw.ndim != 0 or raw.dtype.kind != "U":
        raise TrackerError(str(path), "manifest must be a 0-d unicode array (JSON)")
    try:
        manifest = json.loads(str(raw[()]))
    except json.JSONDecodeError as exc:
        raise TrackerError(str(path), f"manifest is not JSON ({exc.msg})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
        raise TrackerError(str(path), f"not a {FORMAT} file")
    if manifest.get("manifest_sha256") != manifest_sha256(manifest):
        raise TrackerError(str(path), "manifest does not match its manifest_sha256 (manifest edited?)")
    if manifest.get("arrays_sha256") != arrays_sha256(arrays):
        raise TrackerError(str(path), "arrays do not match the manifest's arrays_sha256 (file modified?)")
    _check_arrays(arrays, path)
    return HandPartForest(arrays, manifest, path)


def _check_arrays(a: dict, path: Path) -> None:
    """Shapes, dtypes and indices each traversal relies on."""
    if a["keypoint_push_m"].dtype != np.float64 or a["keypoint_push_m"].shape != (N_PARTS,):
        raise TrackerError(str(path), "array keypoint_push_m malformed")
    _check_forest({n: a[f"roll_{n}"] for n in FOREST_ARRAYS}, ROLL_BINS + 1, path)
    _check_forest({n: a[n] for n in FOREST_ARRAYS}, N_CLASSES, path)


def _check_forest(a: dict, n_classes: int, path: Path) -> None:
    """A forest's shapes, dtypes and indices (a sealed file was made by us, but a wrong index would
    read out of bounds in compiled code)."""
    n = len(a["thresholds"])
    want = {"offsets": (np.float64, (n, 4)), "thresholds": (np.float64, (n,)), "left": (np.int64, (n,)),
            "right": (np.int64, (n,)), "leaf": (np.int64, (n,))}
    for name, (dt, shape) in want.items():
        if a[name].dtype != dt or a[name].shape != shape:
            raise TrackerError(str(path), f"array {name}: {a[name].dtype}{a[name].shape}, expected {np.dtype(dt)}{shape}")
    lv, roots = a["leaf_values"], a["roots"]
    if lv.dtype != np.float32 or lv.ndim != 2 or lv.shape[1] != n_classes or roots.dtype != np.int64 or roots.ndim != 1:
        raise TrackerError(str(path), "leaf_values or roots malformed")
    inner = a["left"] >= 0
    kids = np.concatenate([a["left"][inner], a["right"][inner]])
    if (len(roots) == 0 or np.any((roots < 0) | (roots >= n)) or np.any(kids >= n) or np.any(a["right"][inner] < 0)
            or np.any(a["leaf"][~inner] < 0) or np.any(a["leaf"][~inner] >= len(lv))):
        raise TrackerError(str(path), "node indices out of range")
    if np.any(kids <= np.concatenate([np.flatnonzero(inner)] * 2)):
        raise TrackerError(str(path), "a child precedes its parent (the walk could loop)")


def newest_shipped(name: str, suffix: str, what: str = "detector") -> Path:
    """The newest version of the model file ``<name>-<version><suffix>`` under ``models/detectors/``
    (versions compared number by number: 1.10.0 after 1.9.0)."""
    folder = models_dir() / "detectors"
    found = sorted(folder.glob(f"{name}-*{suffix}"), key=lambda q: [int(x) if x.isdigit() else x
                                                                    for x in q.stem[len(name) + 1:].split(".")])
    if not found:
        raise TrackerError(str(folder), f"no {what} {name!r} shipped")
    return found[-1]


def detector_path(name: str = DETECTOR_NAME) -> Path:
    """The shipped detector file of that name (the newest version under ``models/detectors/``) or a path."""
    p = Path(name)
    return p if p.suffix == ".npz" else newest_shipped(name, ".npz")


@lru_cache(maxsize=8)
def _read_cached(path: str, mtime: float, reader):
    return reader(path)


def read_once(path: Path, reader, what: str):
    """``reader(path)``, once per process and version of the file (its modification time)."""
    try:
        return _read_cached(str(path.resolve()), path.stat().st_mtime, reader)
    except FileNotFoundError:
        raise TrackerError(str(path), f"no such {what}") from None


def load_detector(name_or_path: str = DETECTOR_NAME) -> HandPartForest:
    """The detector by name (shipped, newest version) or ``.npz`` path, read once per process."""
    return read_once(detector_path(str(name_or_path)), read_detector, "detector file")


# ----------------------------------------------------------------------------- detection
def checked_frame(depth_m, camera, hand: str):
    """``(camera, depth as float32)`` for a detector, after the checks every detector makes: the hand
    is "left" or "right", the depth an image of the camera's size."""
    if hand not in ("left", "right"):
        raise TrackerError("hand", f"must be 'left' or 'right', got {hand!r}")
    cam = as_camera(camera)
    d = np.asarray(depth_m, np.float32)
    if d.ndim != 2 or d.shape != (int(cam.height), int(cam.width)):
        raise TrackerError("depth", f"shape {d.shape} does not match the camera's {int(cam.height)}×{int(cam.width)}")
    return cam, d


def candidate_pixels(depth, mask=None, *, stride: int = 2, depth_range=(0.15, 2.0)):
    """``(rows, cols)`` to classify: the mask's pixels with depth, or without a mask every valid
    pixel in ``depth_range``, on a ``stride`` grid."""
    d = np.asarray(depth)
    ok = np.isfinite(d) & (d > depth_range[0]) & (d < depth_range[1])
    if mask is not None:
        m = np.asarray(mask, bool)
        if m.shape != d.shape:
            raise TrackerError("mask", f"shape {m.shape} differs from the depth's {d.shape}")
        ok &= m
    grid = np.zeros_like(ok)
    grid[::stride, ::stride] = True
    rows, cols = np.nonzero(ok & grid)
    return rows.astype(np.int64), cols.astype(np.int64)


def parts_to_keypoints(points, proba, push_m, *, bandwidth_m=0.012, min_prob=0.2, seeds: int = 6,
                       iterations: int = 12):
    """Keypoints ``(21, 3)`` and confidences ``(21,)`` from classified pixels' 3-D points ``(N, 3)``
    and their class probabilities ``(N, 22)``: per part the densest mean-shift mode of the points
    whose probability reaches ``min_prob``, weighted by probability × depth², moved ``push_m[k]``
    along its ray (NaN and 0 where no pixel reaches it)."""
    P = np.asarray(points, float)
    kp = np.full((N_PARTS, 3), np.nan)
    conf = np.zeros(N_PARTS)
    for k in range(N_PARTS):
        p = proba[:, k]
        sel = p >= min_prob
        if sel.sum() < 3:
            continue
        Q, w = P[sel], p[sel] * P[sel, 2] ** 2
        order = np.argsort(-w)[:seeds]
        mode, _ = mean_shift(np.ascontiguousarray(Q), np.ascontiguousarray(w), np.ascontiguousarray(Q[order]),
                             float(bandwidth_m), iterations)
        near = np.sum((Q - mode) ** 2, axis=1) <= bandwidth_m ** 2
        if not near.any():
            continue
        kp[k] = mode * (1.0 + push_m[k] / mode[2])  # along the ray through the mode
        conf[k] = float(np.mean(p[sel][near]) * (1.0 - np.exp(-near.sum() / 8.0)))
    return kp, conf


def roll_bin(roll) -> np.ndarray:
    """The roll bin (0…ROLL_BINS−1) of angles in radians."""
    return np.rint(np.asarray(roll) / (2 * np.pi / ROLL_BINS)).astype(np.int64) % ROLL_BINS


def detect(depth_m, camera, mask=None, hand: str = "left", *, detector: HandPartForest | None = None,
           stride: int = 2, min_prob: float = 0.2, roll: float | None = None) -> Detection:
    """The hand's 21 keypoints in one depth frame.

    Parameters
    ----------
    depth_m : (H, W) float
        Depth in metres, NaN or 0 where none.
    camera : a camera (``tracker.io.cameras``) or preset name
    mask : (H, W) bool or None
        Pixels that may be the hand (the segmentation's); None: every pixel with depth in 0.15–2 m.
        The features read the whole frame either way.
    hand : "left" or "right"
    detector : the forest (default: the shipped one)
    stride : classify every ``stride``-th pixel in each direction
    min_prob : a pixel joins its part's mode from this probability
    roll : the hand's turn in the image (radians, 0 = wrist to fingers pointing up; e.g. from the
        previous frame's fit); None: voted by the pixels (the first layer)

    Returns
    -------
    Detection
    """
    cam, d = checked_frame(depth_m, camera, hand)
    det = detector or load_detector()
    d = np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan)).astype(np.float32)
    rows, cols = candidate_pixels(d, mask, stride=stride)
    nan = np.full(N_PARTS, np.nan)
    if len(rows) == 0:
        return Detection(np.full((N_PARTS, 2), np.nan), nan, np.full((N_PARTS, 3), np.nan), np.zeros(N_PARTS), 0.0, 0)
    mirror = -1.0 if hand == "right" else 1.0
    if roll is None:
        roll = det.roll(d, rows, cols, cam.fx, cam.fy, mirror)
    proba = det.proba(d, rows, cols, cam.fx, cam.fy, mirror, roll)
    z = d[rows, cols].astype(float)
    P = np.stack([(cols - cam.cx) * z / cam.fx, (rows - cam.cy) * z / cam.fy, z], axis=1)
    kp, conf = parts_to_keypoints(P, proba, det.arrays["keypoint_push_m"], bandwidth_m=det.bandwidth_m,
                                  min_prob=min_prob)
    with np.errstate(invalid="ignore"):
        uv = np.stack([cam.fx * kp[:, 0] / kp[:, 2] + cam.cx, cam.fy * kp[:, 1] / kp[:, 2] + cam.cy], axis=1)
    return Detection(uv, kp[:, 2].copy(), kp, conf, float(1.0 - proba[:, OTHER].mean()), int(len(rows)))
