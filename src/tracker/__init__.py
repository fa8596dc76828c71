"""Synergistic hand tracking in depth images.

The user-facing names, imported lazily (``tracker --help`` must not pay for numpy or numba):

>>> import tracker
>>> [n for n in tracker.__all__ if getattr(tracker, n, None) is None]  # each resolves on first use
[]
"""
from .errors import RecordingError, TrackerError

#: The hand model the tracker fits when none is named (``--hand-model``): the shipped hand with its finger
#: bases on the human metacarpal arc (:mod:`handmodel.anthropometry`), which real hands fit better than the
#: paper's straight row of finger bases; ``--paper`` fits the paper's own (:data:`PAPER_HAND`).
TRACKING_HAND = "human"

#: The paper's hand (htrack's ``default.calib``, ``models/hands/default.yaml``), fitted with ``--paper``.
PAPER_HAND = "default"

# name -> the module (under tracker) that owns it
_LAZY = {
    "HandTracker": "stream", "HandResult": "stream",
    "TrackerSettings": "settings", "FrameTracker": "track",
    "Segmenter": "segment",
    "Camera": "io.cameras", "preset": "io.cameras",
    "Recording": "io.recording", "RecordingWriter": "io.recording", "open_recording": "io.recording",
    "observe": "observe", "Observation": "observe", "ObserveSettings": "observe",
    "CorrespondSettings": "correspond", "IcpSettings": "icp", "InitSettings": "init",
    "TrackJob": "run", "run_job": "run", "read_tracking": "io.tracking_file", "write_tracking": "io.tracking_file",
    "read_keypoints": "io.tracking_file", "write_keypoints": "io.tracking_file", "tracked_hand": "io.tracking_file",
    "keypoint_error_mm": "evaluate", "posture_error_deg": "evaluate",
}

__all__ = sorted(["PAPER_HAND", "RecordingError", "TRACKING_HAND", "TrackerError", *_LAZY])


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'tracker' has no attribute {name!r}")


def __dir__():
    return __all__
