"""Is the segmented region a hand? A small CNN on the keypoint CNN's input, run by onnxruntime.

The region's box and the 64 × 64 depth input are the keypoint CNN's (:func:`tracker.keypoint_cnn.hand_box`,
:func:`tracker.keypoint_cnn.crop_image`), with a second channel the box's size in metres (the crop is
resampled to 64 pixels whatever its size, so without it a mug on a saucer 0.3 m wide reads like a hand;
:func:`presence_input`); the network gives the probability that the box holds a hand.
It is trained by :mod:`tracker.sim.train_presence` on whole rendered frames: hands (true and segmented
boxes) against what the tracker's segmentation takes when it misses the hand (a forearm's end, a torso,
a table's edge, an object) and hand-sized boxes on such surfaces. It answers what the keypoint CNN's
confidence cannot (that network never saw a crop without a hand): a fist is a hand, the end of a
sleeve is not. Shipped as ONNX with a sealed JSON manifest under ``models/detectors/``, in the
keypoint CNN's file scheme (:func:`tracker.keypoint_cnn.read_cnn`). This module never imports
:mod:`tracker.sim` nor torch.

Examples
--------
>>> import numpy as np
>>> model = load_presence()
>>> depth = np.full((480, 640), np.nan, np.float32)
>>> mask = np.zeros(depth.shape, bool)
>>> hand_probability(depth, "sr305", mask, "right", model=model)  # nothing segmented: no answer
nan
"""
from __future__ import annotations

import numpy as np

from .detector import checked_frame, read_once
from .errors import TrackerError
from .keypoint_cnn import INPUT_SIDE, KeypointCNN, cnn_path, crop_image, hand_box, read_cnn

PRESENCE_NAME = "hand-presence-cnn"
PRESENCE_FORMAT = "hand-presence-cnn/1"
#: The size channel: log(box side in metres / this), clipped to ±2 (a hand's box at size 1 is ~0.25 m).
BOX_SIDE_M = 0.25


def presence_input(depth, box, mirror: bool, fx: float, side: int = INPUT_SIDE) -> np.ndarray:
    """The network's ``(2, side, side)`` float32 input for ``box`` (:func:`tracker.keypoint_cnn.hand_box`):
    the keypoint CNN's depth crop, and a constant plane of log(the box's side in metres at its median
    depth / :data:`BOX_SIDE_M`) clipped to ±2 (``fx``: the camera's focal length in pixels)."""
    size_m = box[2] * box[3] / float(fx)
    level = np.clip(np.log(max(size_m, 1e-6) / BOX_SIDE_M), -2.0, 2.0)
    return np.stack([crop_image(depth, box, mirror, side), np.full((side, side), level, np.float32)])


class PresenceCNN(KeypointCNN):
    """A verified ONNX network with its manifest (as :class:`tracker.keypoint_cnn.KeypointCNN`) whose
    output is the probability that each input is a hand."""

    def run(self, images) -> np.ndarray:
        """``(B,)`` probabilities of inputs ``(B, 2, side, side)`` (:func:`presence_input`)."""
        x = np.ascontiguousarray(np.asarray(images, np.float32))
        (p,) = self.session.run(["presence"], {"depth": x})
        return np.asarray(p, float).reshape(-1)


def read_presence(path) -> PresenceCNN:
    """Read and verify a hand-presence network (its ``.json`` manifest or ``.onnx``)."""
    net = read_cnn(path, fmt=PRESENCE_FORMAT, cls=PresenceCNN)
    if net.manifest.get("box_side_m") != BOX_SIDE_M:
        raise TrackerError(str(net.path), "made for another size channel (box_side_m) than this version reads")
    return net


def load_presence(name_or_path: str = PRESENCE_NAME) -> PresenceCNN:
    """The network by name (shipped, newest version) or path, read and verified once per process."""
    return read_once(cnn_path(str(name_or_path), "hand-presence CNN"), read_presence, "hand-presence CNN manifest")


def hand_probability(depth_m, camera, mask, hand: str = "left", *, model: PresenceCNN | None = None) -> float:
    """The probability that the segmented region ``mask`` of a depth frame (metres) is a hand; NaN when
    the mask has too few pixels with depth to place a box (no answer, as the keypoint CNN gives none)."""
    cam, d = checked_frame(depth_m, camera, hand)
    m = np.asarray(mask, bool)
    if m.shape != d.shape:
        raise TrackerError("mask", f"shape {m.shape} differs from the depth's {d.shape}")
    box = hand_box(d, m)
    if box is None:
        return float("nan")
    net = model or load_presence()
    return float(net.run(presence_input(d, box, hand == "right", cam.fx)[None])[0])


__all__ = ["BOX_SIDE_M", "PRESENCE_FORMAT", "PRESENCE_NAME", "PresenceCNN", "hand_probability", "load_presence",
           "presence_input", "read_presence"]
