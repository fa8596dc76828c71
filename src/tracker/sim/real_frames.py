"""The labelled real SR305 frames (``../shared/data/realsense_sr305_lada``) tracked as a user would
(:func:`experiment_real_frames`), and the issue's floors they are held to: the report's "real labelled
frames" section (:mod:`tracker.sim.report`) and ``tests/tracker/test_track_real.py``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from handmodel import HandModel

from .. import TRACKING_HAND
from ..errors import TrackerError
from ..io.cameras import preset
from ..observe import observe
from ..track import FrameTracker, TrackerSettings

#: The labelled real frames' fingertip names (labels.json keys) and the issue's floors.
REAL_TIPS = ("thumb", "index", "middle", "ring", "pinky")
REAL_TIP_PX, REAL_WRIST_PX, REAL_MASK_SHARE, REAL_MASK_DILATE_PX = 15.0, 20.0, 0.90, 8
#: The report's second protocol: the hand calibrated from each recording's first this many stills (the
#: tracker's own scale_frames).
REAL_CALIBRATE_EACH = 5


def _frame_order(name):
    """Sort key of a labelled frame ``<recording>_<index>``: the recording, then the index as a number.

    >>> sorted(["r_110", "r_30", "q_5"], key=_frame_order)
    ['q_5', 'r_30', 'r_110']
    """
    rec, _, idx = name.rpartition("_")
    return (rec, int(idx)) if idx.isdigit() else (name, -1)


def read_labels(data_dir) -> dict:
    """The labelled stills' ``labels/labels.json`` (name → wrist and fingertip pixels); unreadable or not
    JSON → one :class:`TrackerError` naming the file."""
    import json

    path = Path(data_dir) / "labels" / "labels.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise TrackerError(str(path), f"cannot read the frame labels ({e})") from None


def _not_found(name, tr, kn, lab, mask, status) -> dict:
    """The row of a frame the tracker gave no θ (``status``): infinite distances, no keypoint in the mask."""
    inf = float("inf")
    tips = {t: inf for t in REAL_TIPS if t in lab}
    return {"name": name, "scale": float(tr.scale_ or float("nan")), "fingers": dict(tr.finger_scales_ or {}),
            "uv": np.full((len(kn), 2), np.nan), "names": kn, "labels": lab, "mask": mask, "tips_px": tips,
            "tip_ends_px": dict(tips), "ends_uv": np.full((len(REAL_TIPS), 2), np.nan), "wrist_px": inf,
            "wrist_joint_px": inf, "crease_uv": np.full(2, np.nan), "in_mask": 0.0, "ok": False, "status": status}


def experiment_real_frames(data_dir, *, overlay_dir=None, progress=None, calibrate_each=0, settings=None,
                           alone=False):
    """Every labelled real SR305 frame of ``data_dir`` (``../shared/data/realsense_sr305_lada``: depth
    PNGs, ``labels/labels.json`` with wrist and fingertip pixels, ``labels/<name>_hand.png`` hand masks)
    tracked as a user would: the ``sr305`` preset, the right hand, defaults, the hand size calibrated on
    each recording's first labelled frame (``hand_scale="auto"``) and reused for its other frames.

    Returns one dict per frame: ``name``, ``scale``, ``uv`` (projected keypoints, px), ``names``
    (keypoint names), ``labels``, ``mask`` (the labelled hand), ``tips_px`` (labelled tip → model tip
    keypoint), ``tip_ends_px`` (→ the model finger's end, :meth:`HandModel.fingertip_ends`, projected at
    ``ends_uv``),
    ``wrist_px`` (the labelled crease → the model hand's end, :meth:`HandModel.wrist_crease`, projected
    at ``crease_uv``), ``wrist_joint_px`` (→ the wrist joint), ``in_mask`` (share of keypoints inside the mask dilated by
    :data:`REAL_MASK_DILATE_PX`) and ``ok`` (every floor met); a frame the tracker found no hand in has
    infinite distances and ``status`` (e.g. ``"no hand"``). ``overlay_dir``: an overlay PNG per frame
    (:func:`tracker.plots.overlay_png`, the labelled tips and wrist drawn in). ``calibrate_each``: the
    hand is calibrated instead on each recording's first ``calibrate_each`` labelled frames, each fitted
    from its own start (:meth:`FrameTracker.calibrate_each`, ``tracker calibrate --each``: size and finger
    lengths), and every frame is tracked on that hand. ``settings``: the :class:`TrackerSettings` instead of
    the defaults (e.g. ``start.detector``). ``alone``: each frame is tracked as a recording of one still
    (the size calibrated on that frame itself), as a user tracking a single image would."""
    from PIL import Image
    from scipy import ndimage

    from synergy.bundle import load_bundle
    from ..io.images import read_depth_units, units_to_metres

    root = Path(data_dir)
    labels = read_labels(root)
    cam = preset("sr305")
    bundle = load_bundle("fingerfist")
    base = settings or TrackerSettings()
    # in recording order: "first labelled frame" is the earliest (230536_30, not 230536_110 as text sorts)
    names = sorted((k for k, v in labels.items() if isinstance(v, dict) and "wrist" in v), key=_frame_order)
    rows, sizes, calibrated = [], {}, {}
    depths = {name: units_to_metres(read_depth_units(root / f"{name}.png", cam), cam) for name in names}
    if calibrate_each:
        for recording in dict.fromkeys(n.split("_")[0] for n in names):
            first = [n for n in names if n.split("_")[0] == recording][:calibrate_each]
            tr = FrameTracker(HandModel.load(TRACKING_HAND, right=True), base, synergies=bundle)
            tr.calibrate_each([observe(depths[n], cam) for n in first], cam)
            calibrated[recording] = tr
    for k, name in enumerate(names):
        depth = depths[name]
        mask = np.asarray(Image.open(root / "labels" / f"{name}_hand.png")) > 0
        recording = name.split("_")[0]
        if calibrate_each:
            tr = calibrated[recording]
            tr.reset()
        else:
            tr = FrameTracker(HandModel.load(TRACKING_HAND, right=True),
                             base.replace(scale=dict(hand_scale="auto" if alone else sizes.get(recording, "auto"))),
                             synergies=bundle)
        ob = observe(depth, cam)
        res = tr.track(ob, cam)
        sizes.setdefault(recording, tr.scale_)
        kn = list(tr.hand.keypoint_names)
        lab = labels[name]
        if res.theta is None or not np.all(np.isfinite(res.theta)):
            # no hand found: every distance infinite, so the frame fails every floor
            rows.append(_not_found(name, tr, kn, lab, mask, res.status))
            if progress is not None:
                progress(k + 1, len(names), name)
            continue
        uv = cam.project(tr.hand.keypoints(res.theta))
        tips = {t: float(np.hypot(*(uv[kn.index(t + "_tip")] - lab[t]))) for t in REAL_TIPS if t in lab}
        # the label is the finger's outermost point by its definition: the model finger's end
        # (HandModel.fingertip_ends) measured beside the tip keypoint, which the floors use
        ends = cam.project(tr.hand.fingertip_ends(res.theta))
        tip_ends = {t: float(np.hypot(*(ends[i] - lab[t]))) for i, t in enumerate(REAL_TIPS) if t in lab}
        # the label is the crease, the hand mask's end: compared with the model hand's end there
        # (HandModel.wrist_crease), the joint's own distance kept beside it
        crease = cam.project(tr.hand.wrist_crease(res.theta))
        wrist = float(np.hypot(*(crease - lab["wrist"])))
        wrist_joint = float(np.hypot(*(uv[0] - lab["wrist"])))
        near = ndimage.binary_dilation(mask, iterations=REAL_MASK_DILATE_PX)
        ui = np.clip(np.rint(uv).astype(int), 0, [mask.shape[1] - 1, mask.shape[0] - 1])
        inside = float(near[ui[:, 1], ui[:, 0]].mean())
        rows.append({"name": name, "scale": float(tr.scale_), "fingers": dict(tr.finger_scales_ or {}),
                     "uv": uv, "names": kn, "labels": lab, "mask": mask,
                     "tips_px": tips, "tip_ends_px": tip_ends, "ends_uv": ends, "wrist_px": wrist,
                     "wrist_joint_px": wrist_joint, "crease_uv": crease, "in_mask": inside,
                     "ok": bool(max(tips.values()) <= REAL_TIP_PX and wrist <= REAL_WRIST_PX
                                and inside >= REAL_MASK_SHARE)})
        if overlay_dir is not None:
            from ..plots import overlay_png

            Path(overlay_dir).mkdir(parents=True, exist_ok=True)
            overlay_png(Path(overlay_dir) / f"{name}.png", depth, cam, tr.hand, res.theta,
                        status=f"{res.status}, size {tr.scale_:.2f}, worst tip {max(tips.values()):.0f} px, "
                               f"wrist crease {wrist:.0f} px (joint {wrist_joint:.0f})", mask=ob.mask,
                        labelled=[lab[t] for t in (*REAL_TIPS, "wrist") if t in lab])
        if progress is not None:
            progress(k + 1, len(names), name)
    return rows
