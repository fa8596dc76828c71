"""Held-out evaluation of the keypoint CNN (:mod:`tracker.keypoint_cnn`): on held-out crops with the true
and a jittered box (:func:`evaluate_samples`), on whole held-out frames through the tracker's own
segmentation (:func:`evaluate_segmented`, the forest comparable on the same frames) and the start fitted to
its keypoints (:func:`evaluate_starts`). Used by :func:`tracker.sim.train_cnn.build` and
:func:`~tracker.sim.train_cnn.compare_heads`; needs no torch (the model is anything with ``run``)."""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ..detector import OTHER
from ..io.cameras import Camera
from ..keypoint_cnn import box_keypoints, crop_image, detect
from .dataset import DataRecipe, draw_scene
from .train_cnn import TIPS, CnnSettings, jitter_box
from .train_detector import HELDOUT_SEED_OFFSET, _r


def _errors(model, samples, boxes, batch: int = 256):
    """Per sample the keypoint errors in mm ``(21,)`` and px, and the spreads."""
    mm, px, spread = [], [], []
    for k in range(0, len(samples), batch):
        S, B = samples[k:k + batch], boxes[k:k + batch]
        X = np.stack([crop_image(s.depth, b, s.mirror) for s, b in zip(S, B)])
        out, sp = model.run(X)
        for s, b, o in zip(S, B, out):
            fx, fy, cx, cy = s.camera
            uv, z, xyz = box_keypoints(o, b, s.mirror, Camera(1, 1, fx, fy, cx, cy))
            truth = np.stack([(s.uv[:, 0] - cx) * s.z / fx, (s.uv[:, 1] - cy) * s.z / fy, s.z], axis=1)
            mm.append(1000 * np.linalg.norm(xyz - truth, axis=1))
            px.append(np.linalg.norm(uv - s.uv, axis=1))
        spread.append(sp)
    return np.array(mm), np.array(px), np.concatenate(spread)


def _stats(mm, px) -> dict:
    """Errors over the keypoints found (the forest leaves some NaN; the CNN places all; None where none is)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an all-NaN slice: _r makes it None
        return {"found_share": round(float(np.isfinite(mm).mean()), 4), "mm_median": _r(np.nanmedian(mm)),
                "mm_mean": _r(np.nanmean(mm)), "mm_p90": _r(np.nanpercentile(mm, 90)),
                "px_median": _r(np.nanmedian(px)), "px_mean": _r(np.nanmean(px)),
                "tips_mm_median": _r(np.nanmedian(mm[:, TIPS])), "wrist_mm_median": _r(np.nanmedian(mm[:, 0]))}


def evaluate_samples(model, samples, st: CnnSettings, seed: int = 0) -> dict:
    """Errors on held-out samples with the true pixels' box and with a jittered one (the training's
    jitter, generator ``(seed, 3)``), the centroid baseline, and how the confidence sorts the errors."""
    rng = np.random.default_rng([seed, 3])
    true_boxes = [s.box for s in samples]
    mm, px, spread = _errors(model, samples, true_boxes)
    jm, jp, _ = _errors(model, samples, [jitter_box(s, rng, st) for s in samples])
    base = np.array([1000 * np.linalg.norm(
        np.stack([(s.uv[:, 0] - s.camera[2]) * s.z / s.camera[0], (s.uv[:, 1] - s.camera[3]) * s.z / s.camera[1], s.z],
                 axis=1) - s.centroid, axis=1) for s in samples])
    from ..keypoint_cnn import spread_confidence

    conf = spread_confidence(spread)
    hi = conf >= 0.5
    edges = np.quantile(spread, [0, 1 / 3, 2 / 3, 1])
    third = np.clip(np.searchsorted(edges, spread, side="right") - 1, 0, 2)
    return {"crops": len(samples), "true_box": _stats(mm, px), "jittered_box": _stats(jm, jp),
            "centroid_mm_median": _r(np.median(base)),
            "spread_quartiles": [_r(q, 4) for q in np.quantile(spread, [0.25, 0.5, 0.75])],
            "mm_median_by_spread_third": [_median(mm[third == k]) for k in range(3)],
            "confidence_ge_0.5_share": round(float(hi.mean()), 4),
            "mm_median_confidence_ge_0.5": _r(np.median(mm[hi])) if hi.any() else None,
            "mm_median_confidence_lt_0.5": _r(np.median(mm[~hi])) if (~hi).any() else None}


def evaluate_segmented(model, recipe: DataRecipe, seed: int, n: int, synergies=None, detect_fn=detect) -> dict:
    """The held-out scenes (seed ``seed + HELDOUT_SEED_OFFSET``, the crops' scenes) rendered as whole
    frames, the box from the tracker's own segmentation (:func:`tracker.observe.observe`), and the
    start fitted to the keypoints (:func:`tracker.keypoint_fit.fit_start`, the tracker's hand at size 1,
    ``synergies`` when given): keypoint errors in mm and px, the share of frames whose mask holds at
    least half the hand's true pixels ("on the hand"), the start's mean keypoint error, ms.
    ``detect_fn(depth, camera, mask, hand, detector=)``: the CNN's, or the forest's
    :func:`tracker.detector.detect` to compare on the same frames."""
    from handmodel import HandModel

    from .. import TRACKING_HAND
    from ..keypoint_fit import fit_start
    from ..observe import observe

    whole = replace(recipe, window_m=100.0)  # the crop window past the image: the whole frame
    hands = {m: HandModel.load(TRACKING_HAND, right=m) for m in (False, True)}
    mm, px, on, starts, det_ms, seg_ms = [], [], [], [], [], []
    for i in range(n):
        c = draw_scene(whole, np.random.default_rng([seed + HELDOUT_SEED_OFFSET, i]))
        h, w = c.depth.shape
        fx, fy, cx, cy = map(float, c.camera)
        cam = Camera(w, h, fx, fy, cx, cy, 0.001, "uint16", "frame")
        t0 = time.perf_counter()
        mask = observe(c.depth, cam).mask
        t1 = time.perf_counter()
        right = c.mirror < 0
        d = detect_fn(c.depth, cam, mask, "right" if right else "left", detector=model)
        det_ms.append(1000 * (time.perf_counter() - t1))
        seg_ms.append(1000 * (t1 - t0))
        if not d.found.any():
            continue
        hand = (c.parts >= 0) & (c.parts < OTHER) & np.isfinite(c.depth)
        on.append(bool((mask & hand).sum() >= 0.5 * max(hand.sum(), 1)))
        truth = np.stack([(c.keypoints_uv[:, 0] - cx) * c.keypoints_z / fx,
                          (c.keypoints_uv[:, 1] - cy) * c.keypoints_z / fy, c.keypoints_z], axis=1)
        mm.append(1000 * np.linalg.norm(d.keypoints_xyz - truth, axis=1))
        px.append(np.linalg.norm(d.keypoints_px - c.keypoints_uv, axis=1))
        theta = fit_start(d, hands[right], synergies)
        starts.append(np.nan if theta is None else
                      1000 * np.linalg.norm(hands[right].keypoints(theta) - truth, axis=1).mean())
    mm, px, on, starts = np.array(mm), np.array(px), np.array(on, bool), np.array(starts)
    out = {"frames": n, "with_keypoints": len(mm), "on_hand": int(on.sum()),
           "segment_ms_median": _r(np.median(seg_ms)), "detect_ms_median": _r(np.median(det_ms))}
    if len(mm):
        out["all"] = _stats(mm, px)
        if on.any():
            out["on_hand_frames"] = _stats(mm[on], px[on])
        out["starts"] = int(np.isfinite(starts).sum())
        out["start_mean_keypoint_mm_median"] = _median(starts)
        out["starts_within_20mm"] = int(np.sum(starts <= 20))
        if on.any():
            out["start_on_hand_mm_median"] = _median(starts[on])
            out["starts_on_hand_within_20mm"] = int(np.sum(starts[on] <= 20))
    return out


def _median(x):
    """The median of the finite values (None without any: no start was fitted)."""
    x = np.asarray(x, float)
    return _r(np.median(x[np.isfinite(x)])) if np.isfinite(x).any() else None


def evaluate_starts(model, samples, synergies=None, n: int = 100) -> dict:
    """The start fitted to the keypoints of held-out samples (true pixels' box): its mean keypoint
    error against the rendered hand's (cf. :func:`tracker.sim.train_detector.evaluate_start`)."""
    from handmodel import HandModel

    from .. import TRACKING_HAND
    from ..detector import Detection
    from ..keypoint_fit import fit_start
    from ..keypoint_cnn import spread_confidence

    hands = {m: HandModel.load(TRACKING_HAND, right=m) for m in (False, True)}
    S = samples[:n]
    out, spread = model.run(np.stack([crop_image(s.depth, s.box, s.mirror) for s in S]))
    res, det, ms = [], [], []
    for s, o, sp in zip(S, out, spread):
        fx, fy, cx, cy = s.camera
        uv, z, xyz = box_keypoints(o, s.box, s.mirror, Camera(1, 1, fx, fy, cx, cy))
        truth = np.stack([(s.uv[:, 0] - cx) * s.z / fx, (s.uv[:, 1] - cy) * s.z / fy, s.z], axis=1)
        det.append(1000 * np.linalg.norm(xyz - truth, axis=1))
        conf = spread_confidence(sp)
        t0 = time.perf_counter()
        theta = fit_start(Detection(uv, z, xyz, conf, float(conf.mean()), 0), hands[s.mirror], synergies)
        ms.append(1000 * (time.perf_counter() - t0))
        res.append(np.nan if theta is None else 1000 * np.linalg.norm(hands[s.mirror].keypoints(theta) - truth,
                                                                      axis=1).mean())
    res = np.array(res)
    return {"crops": len(S), "synergies": synergies is not None, "detected_mm_median": _r(np.median(det)),
            "starts": int(np.isfinite(res).sum()), "start_mean_keypoint_mm_median": _median(res),
            "start_within_20mm": int(np.sum(res <= 20)), "fit_start_ms_median": _r(np.median(ms))}


