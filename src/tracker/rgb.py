"""Colour keypoints as a start: 2-D hand keypoints from MediaPipe Hands on the colour frame registered
to the depth, lifted to 3-D with the depth and fitted by :func:`handmodel.solver.fit_keypoints`; the
result seeds the single-frame search (:func:`tracker.init.fit_single_frame` ``extra``), which the
depth ICP then refines.

MediaPipe is the optional extra ``[rgb]`` (``mediapipe==0.10.21``, the last release whose wheel ships
the hand models; later releases need a ``.task`` file, given as ``model_path``). Only
:class:`MediaPipeHands` needs it; lifting and the keypoint fit are plain array functions.

MediaPipe's 21 landmarks come in the order of the hand model's keypoints (wrist, then each finger
from its base to its tip, thumb to little finger), so no re-ordering is needed.

>>> import numpy as np
>>> from tracker.io.cameras import Camera
>>> cam = Camera(width=8, height=6, fx=10.0, fy=10.0, cx=4.0, cy=3.0)
>>> depth = np.full((6, 8), 0.5); depth[3, 4] = np.nan
>>> lift_keypoints(np.array([[4.0, 3.0]]), depth, cam, surface_mm=0.0).round(3).tolist()
[[0.0, 0.0, 0.5]]
"""
from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from handmodel.solver import fit_keypoints

from .io.cameras import as_camera
from .errors import TrackerError

INSTALL = "pip install 'synergistic-hand-tracking[rgb]'"
N_KEYPOINTS = 21


def mediapipe_available() -> bool:
    """Whether the ``[rgb]`` extra (mediapipe) is installed, without importing it."""
    return importlib.util.find_spec("mediapipe") is not None


def require_mediapipe(what: str = "--rgb-seed"):
    """Raise :class:`TrackerError` naming the install command when mediapipe is missing."""
    if not mediapipe_available():
        raise TrackerError(what, f"colour keypoints need MediaPipe: {INSTALL}")


def lift_keypoints(uv, depth, camera, *, window: int = 5, surface_mm: float = 8.0) -> np.ndarray:
    """3-D keypoints ``(K, 3)`` (camera frame, metres) from pixel keypoints ``uv (K, 2)``.

    Each keypoint's depth is the median of the valid depths (finite, > 0) in a ``window`` × ``window``
    box around it — the median because a keypoint on a finger's edge has background in its box;
    NaN rows where the box has no data or the keypoint is off the image. The depth camera sees
    the skin, the model's keypoints are joint centres: the point is moved ``surface_mm`` further
    along its ray (about a finger's radius).
    """
    cam = as_camera(camera)
    d = np.asarray(depth, float)
    uv = np.asarray(uv, float).reshape(-1, 2)
    H, W = d.shape
    h = max(int(window) // 2, 0)
    z = np.full(len(uv), np.nan)
    for k, (u, v) in enumerate(uv):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        x, y = round(float(u)), round(float(v))
        if not (0 <= x < W and 0 <= y < H):
            continue
        box = d[max(y - h, 0):y + h + 1, max(x - h, 0):x + h + 1]
        ok = box[np.isfinite(box) & (box > 0)]
        if ok.size:
            z[k] = np.median(ok)
    pts = cam.unproject(uv, z)
    if surface_mm:
        ray = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
        pts = pts + ray * (surface_mm / 1000.0)
    return pts


def seed_from_keypoints(hand, keypoints, *, subspace=None, min_keypoints: int = 8):
    """θ of ``hand`` fitted to 3-D keypoints ``(21, 3)`` (metres, NaN = missing), or None when fewer
    than ``min_keypoints`` are present (too few to place the hand and bend its fingers).

    Uses :func:`handmodel.solver.fit_keypoints` (a rigid placement, then Gauss-Newton on the keypoint
    residuals with restarts from flexed postures); ``subspace`` keeps the posture in the synergies."""
    kp = np.asarray(keypoints, float)
    if kp.shape != (hand.n_nodes, 3):
        raise TrackerError("keypoints", f"shape {kp.shape}: expected ({hand.n_nodes}, 3)")
    if int(np.isfinite(kp).all(-1).sum()) < min_keypoints:
        return None
    theta, _ = fit_keypoints(hand, kp, subspace=subspace)
    return theta if np.all(np.isfinite(theta)) else None


class MediaPipeHands:
    """2-D hand keypoints of one colour frame by MediaPipe Hands.

    Parameters
    ----------
    model_path : a MediaPipe ``hand_landmarker.task`` file, or None for the models shipped in the
        ``mediapipe==0.10.21`` wheel (the legacy ``solutions.hands`` graph)
    min_confidence : detection confidence below which a hand is not reported
    max_hands : hands looked for; the most confident is returned

    Calling it on an ``(H, W, 3)`` uint8 RGB image returns ``(21, 2)`` pixel coordinates (u, v) or
    None when no hand is found. ``detections_`` and ``frames_`` count found hands and frames seen.
    """

    def __init__(self, model_path=None, min_confidence: float = 0.3, max_hands: int = 2):
        self.model_path = model_path
        self.min_confidence = min_confidence
        self.max_hands = max_hands
        require_mediapipe()
        if model_path is not None and not Path(model_path).is_file():
            raise TrackerError(str(model_path), "MediaPipe hand landmarker .task file not found")
        self._impl = None
        self.detections_ = 0
        self.frames_ = 0

    def _open(self):
        import mediapipe as mp  # the [rgb] extra: imported only when colour keypoints are asked for

        if self.model_path is None:
            if not hasattr(mp, "solutions"):
                raise TrackerError("mediapipe", "this mediapipe release ships no hand models: give a .task file "
                                                f"or {INSTALL}")
            hands = mp.solutions.hands.Hands(static_image_mode=True, max_num_hands=self.max_hands,
                                             min_detection_confidence=self.min_confidence)

            def run(img):
                res = hands.process(img)
                if not res.multi_hand_landmarks:
                    return []
                scores = [h.classification[0].score for h in res.multi_handedness]
                return [(s, [(p.x, p.y) for p in lm.landmark]) for s, lm in zip(scores, res.multi_hand_landmarks)]
        else:
            from mediapipe.tasks.python import BaseOptions, vision

            opts = vision.HandLandmarkerOptions(base_options=BaseOptions(model_asset_path=str(self.model_path)),
                                                num_hands=self.max_hands,
                                                min_hand_detection_confidence=self.min_confidence)
            lm = vision.HandLandmarker.create_from_options(opts)

            def run(img):
                res = lm.detect(mp.Image(image_format=mp.ImageFormat.SRGB, data=img))
                return [(h[0].score, [(p.x, p.y) for p in pts]) for h, pts in zip(res.handedness, res.hand_landmarks)]
        return run

    def __call__(self, color):
        img = np.ascontiguousarray(np.asarray(color))
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise TrackerError("color", f"expected an (H, W, 3) uint8 RGB image, got {img.shape} {img.dtype}")
        if self._impl is None:
            self._impl = self._open()
        self.frames_ += 1
        found = self._impl(img)
        if not found:
            return None
        self.detections_ += 1
        _, pts = max(found, key=lambda f: f[0])
        H, W = img.shape[:2]
        # MediaPipe's landmarks are normalised to the image size
        return np.asarray(pts, float)[:N_KEYPOINTS] * [W, H]


class RgbSeed:
    """The colour start of one frame: detect (``detector``, by default :class:`MediaPipeHands`), lift
    with the frame's depth (:func:`lift_keypoints`), fit (:func:`seed_from_keypoints`).

    ``keypoints_`` holds the last lifted keypoints (None when nothing was detected)."""

    def __init__(self, detector=None, *, window: int = 5, surface_mm: float = 8.0, min_keypoints: int = 8):
        self.detector = detector if detector is not None else MediaPipeHands()
        self.window = window
        self.surface_mm = surface_mm
        self.min_keypoints = min_keypoints
        self.keypoints_ = None

    def __call__(self, hand, color, depth, camera, *, subspace=None):
        """θ seeding the start search of this frame, or None (no hand found, too little depth)."""
        self.keypoints_ = None
        if color is None or depth is None:
            return None
        uv = self.detector(color)
        if uv is None:
            return None
        self.keypoints_ = lift_keypoints(uv, depth, camera, window=self.window, surface_mm=self.surface_mm)
        return seed_from_keypoints(hand, self.keypoints_, subspace=subspace, min_keypoints=self.min_keypoints)
