"""Hands from your own camera loop: one depth image in, one hand out.

:class:`HandTracker` is the tracker as a user's program meets it — a camera, the hand's side and a
synergy bundle in, then :meth:`HandTracker.step` once per depth image (metres, ``(H, W)``), each giving
a :class:`HandResult`. It runs the same path as ``tracker track`` (:func:`tracker.run.run_job`): the
frame is segmented in the predicted hand's window (:func:`tracker.observe.observe`), then fitted by
:class:`tracker.track.FrameTracker`, so a recording stepped through it gives the CSV's θ bit for bit.

>>> import numpy as np
>>> ht = HandTracker("sr305", hand="right")
>>> r = ht.step(np.zeros((ht.camera.height, ht.camera.width)))  # an empty frame: no hand
>>> r.status, r.found, r.keypoints.shape
('lost', False, (21, 3))
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from handmodel.model import HandModel
from synergy.bundle import load_bundle

from . import TRACKING_HAND
from .io.cameras import as_camera
from .errors import TrackerError
from .observe import observe
from .realtime import FrameBudget, predicted_theta
from .segment import Segmenter
from .run import settings_for_hand
from .track import FrameTracker
from .track import TrackerSettings

HANDS = ("left", "right")


@dataclass(frozen=True)
class HandResult:
    """One frame's hand.

    Attributes
    ----------
    status : ``"tracked"`` (followed from the last frame), ``"reinit"`` (found by a fresh search),
        ``"lost"`` (no hand: ``theta`` and ``keypoints`` are NaN) or, in real-time mode only,
        ``"predicted"`` (the frame came while the last one was still being fitted — a search — and got
        the latest fitted hand moved on by its last motion; ``points``, ``mask`` are then 0 and None)
    theta : (26,) the hand's parameters in :data:`handmodel.dofs.DOF_NAMES` order (metres, radians)
    keypoints : (21, 3) wrist then each finger base → tip, metres, camera frame (x right, y down, z forward)
    fit_mm : mean distance of the fitted points to the hand's surface, mm (NaN when lost)
    points : the points the frame's segmented hand gave; ms : the frame's time, segmentation included
    mask : (H, W) the pixels taken for the hand (None for an unusable frame)
    """

    status: str
    theta: np.ndarray
    keypoints: np.ndarray
    fit_mm: float
    points: int
    ms: float
    mask: np.ndarray | None = None

    @property
    def found(self) -> bool:
        """Whether this frame has a hand (tracked, found anew or predicted)."""
        return self.status != "lost"


class HandTracker:
    """Track one hand through depth images from any source (a RealSense loop, ROS, OpenCV, files).

    Parameters
    ----------
    camera : a :class:`tracker.io.cameras.Camera`, a preset name (``"sr305"``, ``"kinect1"`` …, see
        ``tracker.io.cameras.PRESETS``) or anything with ``width height fx fy cx cy`` (or ``ppx ppy``: pyrealsense2's
        intrinsics)
    hand : ``"left"`` or ``"right"``
    synergies : a synergy bundle — a name (``"fingerfist"``, ``"grasp@1.0.0"``), a ``.npz`` path, or a
        loaded :class:`synergy.bundle.Bundle`; None tracks all 26 DoF without synergies (``mode="full"``)
    settings : :class:`tracker.track.TrackerSettings` (None: the defaults; ``.paper()`` is the paper's method)
    hand_model : the hand model's name or YAML path (a calibrated hand file from ``tracker calibrate``);
        :data:`tracker.TRACKING_HAND` by default
    segmenter : :class:`tracker.segment.Segmenter` (None: its defaults)
    registries : extra synergy registry folders searched for ``synergies``
    budget_ms : None (the default): every frame is fitted before :meth:`step` returns, as ``tracker
        track`` does. A number: real-time mode for a live sensor — frames are fitted by a worker thread
        and :meth:`step` waits at most this long for the frame's fit; a frame whose fit takes longer
        (a start search can take a second) gets the latest fitted hand moved on by its last motion
        (status ``"predicted"``), and frames that come while the worker is busy are not fitted at all
        (the worker takes the newest frame next), so the loop keeps up with the sensor

    Attributes
    ----------
    camera : the :class:`~tracker.io.cameras.Camera`; model : the :class:`handmodel.HandModel` tracked
        (its size once calibrated); core : the frame tracker underneath (its counters and hand size)
    """

    def __init__(self, camera, hand: str = "left", synergies=None, settings: TrackerSettings | None = None, *,
                 hand_model: str = TRACKING_HAND, segmenter=None, registries=None, budget_ms: float | None = None):
        if hand not in HANDS:
            raise TrackerError("hand", f"must be 'left' or 'right', got {hand!r}")
        self.camera = as_camera(camera)
        bundle = synergies
        if isinstance(synergies, str) or hasattr(synergies, "__fspath__"):
            bundle = load_bundle(synergies, registries=list(registries) if registries else None)
        model = HandModel.load(hand_model, right=hand == "right")
        self.core = FrameTracker(model, settings_for_hand(model, settings or TrackerSettings()), synergies=bundle)
        # one segmenter for the stream: its frame buffers are reused frame after frame (Segmenter.buffers)
        self.segmenter = segmenter if segmenter is not None else Segmenter()
        self._budget = None if budget_ms is None else FrameBudget(budget_ms)  # checks the number
        self._last = []        # the last two fitted results (oldest first): what a predicted frame extrapolates
        self._last_hand = None  # the hand model of the last fitted result

    @property
    def budget_ms(self) -> float | None:
        """Real-time mode's wait for a fit (ms), or None; may be changed between frames."""
        return None if self._budget is None else self._budget.budget_ms

    @budget_ms.setter
    def budget_ms(self, value: float) -> None:
        if self._budget is None:
            raise TrackerError("budget_ms", "this tracker was made without a budget (not in real-time mode)")
        self._budget.budget_ms = float(value)

    @property
    def model(self) -> HandModel:
        return self.core.hand

    def step(self, depth_m, color=None) -> HandResult:
        """Track the hand in one depth image ``(H, W)`` in metres (0 or NaN: no depth); ``color``: the
        colour image registered to it, ``(H, W, 3)`` uint8, or None."""
        t0 = time.perf_counter()
        d = np.asarray(depth_m, np.float64)
        cam = self.camera
        if d.shape != (cam.height, cam.width):
            raise TrackerError("depth", f"frame of shape {d.shape}, the camera's is {(cam.height, cam.width)}")
        if self._budget is None:
            return self._fit(d, color, t0)
        r = self._budget(self._fit, d, color, t0)
        return self._predicted(t0) if r is None else r

    def _predicted(self, t0) -> HandResult:
        """The latest fitted hand moved on by its last change (:func:`tracker.realtime.predicted_theta`):
        what a frame gets while the worker is still fitting an earlier one."""
        if not self._last or not self._last[-1].found:
            nan = np.full_like(self._last[-1].theta if self._last else np.zeros(26), np.nan)
            kp = np.full((self.core.hand.n_nodes, 3), np.nan)
            return HandResult("lost", nan, kp, float("nan"), 0, (time.perf_counter() - t0) * 1000.0)
        last = self._last[-1]
        before = self._last[0].theta if len(self._last) == 2 and self._last[0].found else None
        theta = predicted_theta(last.theta, before, self.core.settings.predict.turn)
        return replace(last, status="predicted", theta=theta, keypoints=self._last_hand.keypoints(theta),
                       points=0, mask=None, ms=(time.perf_counter() - t0) * 1000.0)

    def _fit(self, d, color, t0) -> HandResult:
        cam = self.camera
        ob = observe(d, cam, self.core.settings.observe, segmenter=self.segmenter, color=color,
                     window=self.core.segment_window(cam))
        r = self.core.track(ob, cam, color=color)
        kp = (np.full((self.core.hand.n_nodes, 3), np.nan) if not np.all(np.isfinite(r.theta))
              else self.core.hand.keypoints(r.theta))
        out = HandResult(r.status, r.theta, kp, r.fit_mm, len(ob.points), (time.perf_counter() - t0) * 1000.0,
                         ob.mask)
        # the hand the result was fitted with: the worker may be changing its size while a frame is predicted
        self._last, self._last_hand = [*self._last[-1:], out], self.core.hand
        return out

    def wait(self) -> HandResult | None:
        """Real-time mode: wait for the frame the worker is fitting and return its result (None when
        it is idle) — e.g. at the end of a recording, whose last frames came while it was busy."""
        return None if self._budget is None else self._budget.wait()

    def reset(self) -> None:
        """Forget the last frame: the next one is searched from scratch (a cut in the video)."""
        self.wait()
        self._last = []
        self.core.reset()

    def close(self) -> None:
        """Stop the real-time worker (after the frame it is fitting)."""
        if self._budget is not None:
            self._budget.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
