"""Training and held-out evaluation of the hand-part forest (:mod:`tracker.detector`).

:func:`train` draws the training crops (:mod:`tracker.sim.dataset`, seed ``S``), samples pixels of
each (hand pixels and other surfaces), computes their depth-difference features for a fixed bank
of random offset pairs (:func:`offset_bank`), fits a scikit-learn ``RandomForestClassifier``,
exports it to flat arrays and learns each keypoint's push along the ray (the median depth from a
part's mode to its joint over a slice of the training crops). :func:`evaluate_synthetic` measures
keypoints on crops drawn with other seeds (other hands, postures, scenes and sensors);
:func:`evaluate_real` on the labelled SR305 stills (tips and wrist against their labels; never used
for training or choices). ``tracker train-detector`` runs both and writes the sealed model.
"""
from __future__ import annotations

import hashlib
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..io.cameras import Camera
from ..detector import (DETECTOR_NAME, N_CLASSES, N_PARTS, OTHER, PART_NAMES, ROLL_BINS, HandPartForest, detect,
                        feature_matrix, forest_arrays, offset_map, roll_bin, save_detector)
from ..errors import TrackerError
from .dataset import DataRecipe, draw_crops

#: Seeds of the held-out crops are drawn from ``seed + HELDOUT_SEED_OFFSET`` (never a training seed).
HELDOUT_SEED_OFFSET = 1_000_003


@dataclass(frozen=True)
class TrainSettings:
    """What :func:`train` does (every field goes into the model's manifest).

    Parameters
    ----------
    n_crops : training crops drawn
    hand_pixels, other_pixels : pixels sampled per crop on the hand and elsewhere (with depth)
    n_features : offset pairs in the bank the trees choose from
    max_offset_m : the farthest probe (metres at 1 m depth)
    n_trees, max_depth, max_features, min_samples_leaf : the forest (scikit-learn's parameters)
    push_crops : training crops on which the keypoints' push along the ray is learned
    bandwidth_m : mean-shift bandwidth
    roll_jitter_deg : the spread of the roll the parts layer is trained at around the true one
    jobs : scikit-learn's n_jobs
    """

    n_crops: int = 600
    hand_pixels: int = 240
    other_pixels: int = 80
    n_features: int = 400
    max_offset_m: float = 0.10
    n_trees: int = 3
    max_depth: int = 20
    max_features: int = 40
    min_samples_leaf: int = 5
    push_crops: int = 150
    bandwidth_m: float = 0.012
    roll_jitter_deg: float = 15.0
    jobs: int = 2

    def to_dict(self) -> dict:
        return asdict(self)


def offset_bank(n: int, max_offset_m: float, rng) -> np.ndarray:
    """``(n, 4)`` offset pairs (ux, uy, vx, vy): directions uniform, radii ∝ √uniform (denser near
    the pixel); a third of the pairs compare one probe with the pixel itself (v = 0)."""
    a = rng.uniform(0, 2 * np.pi, (n, 2))
    r = max_offset_m * np.sqrt(rng.uniform(0, 1, (n, 2)))
    out = np.stack([r[:, 0] * np.cos(a[:, 0]), r[:, 0] * np.sin(a[:, 0]),
                    r[:, 1] * np.cos(a[:, 1]), r[:, 1] * np.sin(a[:, 1])], axis=1)
    out[: n // 3, 2:] = 0.0
    return out


def sample_pixels(crop, rng, n_hand: int, n_other: int):
    """``(rows, cols, labels)`` of pixels with depth: up to ``n_hand`` on the hand, ``n_other`` elsewhere
    (clutter, and hand-less flying pixels labelled other)."""
    ok = np.isfinite(crop.depth)
    hand = ok & (crop.parts >= 0) & (crop.parts < OTHER)
    other = ok & ~hand
    picks = []
    for sel, n in ((hand, n_hand), (other, n_other)):
        idx = np.flatnonzero(sel)
        if len(idx):
            picks.append(rng.choice(idx, min(n, len(idx)), replace=False))
    idx = np.concatenate(picks) if picks else np.zeros(0, np.int64)
    rows, cols = np.unravel_index(idx, crop.depth.shape)
    lab = crop.parts[rows, cols].astype(np.int64)
    lab[lab < 0] = OTHER  # a flying pixel over nothing
    return rows.astype(np.int64), cols.astype(np.int64), lab


def training_matrix(crops, offsets, rng, settings: TrainSettings):
    """Features and labels of pixels sampled from ``crops`` for both layers: ``(X, y)`` of the parts
    (offsets turned by the hand's true roll + a jitter of ``roll_jitter_deg``, as a voted roll
    errs) and ``(Xr, yr)`` of the roll bins (offsets not turned; the hand's pixels labelled with
    the roll bin of the mirrored-to-left hand, the others :data:`ROLL_BINS`)."""
    X, y, Xr, yr = [], [], [], []
    for c in crops:
        rows, cols, lab = sample_pixels(c, rng, settings.hand_pixels, settings.other_pixels)
        if len(rows) == 0:
            continue
        fx, fy = float(c.camera[0]), float(c.camera[1])
        roll = c.roll + np.radians(rng.normal(0.0, settings.roll_jitter_deg))
        X.append(feature_matrix(c.depth, rows, cols, fx, fy, offset_map(c.mirror, roll), offsets))
        y.append(lab)
        Xr.append(feature_matrix(c.depth, rows, cols, fx, fy, offset_map(c.mirror), offsets))
        yr.append(np.where(lab < OTHER, roll_bin(c.mirror * c.roll), ROLL_BINS))
    return np.concatenate(X), np.concatenate(y), np.concatenate(Xr), np.concatenate(yr)


def crop_camera(crop) -> Camera:
    h, w = crop.depth.shape
    fx, fy, cx, cy = map(float, crop.camera)
    return Camera(w, h, fx, fy, cx, cy, 0.001, "uint16", "crop")


def crop_truth_xyz(crop) -> np.ndarray:
    """The crop's 21 keypoints in its camera frame (metres)."""
    fx, fy, cx, cy = crop.camera
    z = crop.keypoints_z
    return np.stack([(crop.keypoints_uv[:, 0] - cx) * z / fx, (crop.keypoints_uv[:, 1] - cy) * z / fy, z], axis=1)


def learn_push(forest_arr: dict, crops, bandwidth_m: float) -> np.ndarray:
    """Per keypoint, the median of (true depth − the part mode's depth) over ``crops``: how far the
    joint lies behind the skin its part shows."""
    det = HandPartForest(dict(forest_arr, keypoint_push_m=np.zeros(N_PARTS)), {"bandwidth_m": bandwidth_m})
    return _push(det, crops)


def _push(det, crops) -> np.ndarray:
    diffs = [[] for _ in range(N_PARTS)]
    for c in crops:
        d = detect(c.depth, crop_camera(c), None, "right" if c.mirror < 0 else "left", detector=det)
        truth = crop_truth_xyz(c)
        for k in range(N_PARTS):
            if np.isfinite(d.keypoints_xyz[k]).all() and np.linalg.norm(d.keypoints_xyz[k, :2] - truth[k, :2]) < 0.02:
                diffs[k].append(truth[k, 2] - d.keypoints_xyz[k, 2])
    return np.array([float(np.median(v)) if len(v) >= 5 else 0.0 for v in diffs])


def train(recipe: DataRecipe, settings: TrainSettings, seed: int, progress=None):
    """``(arrays, info)``: the forest's flat arrays (:func:`tracker.detector.forest_arrays`) and what
    the manifest records (data sizes and hashes, timings, versions)."""
    from sklearn import __version__ as sklearn_version
    from sklearn.ensemble import RandomForestClassifier

    t0 = time.perf_counter()
    say = progress or (lambda msg: None)
    say(f"drawing {settings.n_crops} training crops")
    crops = draw_crops(recipe, seed, settings.n_crops)
    t_draw = time.perf_counter() - t0
    rng = np.random.default_rng([seed, 1])
    offsets = offset_bank(settings.n_features, settings.max_offset_m, rng)
    X, y, Xr, yr = training_matrix(crops, offsets, rng, settings)
    t_feat = time.perf_counter() - t0 - t_draw

    def forest(X, y, n_classes):
        rf = RandomForestClassifier(n_estimators=settings.n_trees, max_depth=settings.max_depth,
                                    max_features=settings.max_features, min_samples_leaf=settings.min_samples_leaf,
                                    n_jobs=settings.jobs, random_state=seed)
        return forest_arrays(rf.fit(X, y).estimators_, offsets, n_classes)

    say(f"fitting 2 × {settings.n_trees} trees (roll, parts) on {len(y)} pixels × {X.shape[1]} features")
    roll = forest(Xr, yr, ROLL_BINS + 1)
    del Xr
    arrays = forest(X, y, N_CLASSES)
    arrays.update({f"roll_{k}": v for k, v in roll.items()})
    t_fit = time.perf_counter() - t0 - t_draw - t_feat
    say("learning the keypoints' push along the ray")
    data_hash = hashlib.sha256(X.tobytes() + y.astype("<i8").tobytes()).hexdigest()
    del X
    arrays["keypoint_push_m"] = learn_push(arrays, crops[: settings.push_crops], settings.bandwidth_m)
    info = {"pixels": int(len(y)), "class_counts": np.bincount(y, minlength=OTHER + 1).tolist(),
            "training_matrix_sha256": data_hash, "nodes": int(len(arrays["thresholds"])),
            "roll_nodes": int(len(arrays["roll_thresholds"])),
            "seconds": {"draw": round(t_draw, 1), "features": round(t_feat, 1), "fit": round(t_fit, 1),
                        "total": round(time.perf_counter() - t0, 1)},
            "sklearn": sklearn_version, "numpy": np.__version__, "python": platform.python_version()}
    return arrays, info


def evaluate_synthetic(detector: HandPartForest, recipe: DataRecipe, seed: int, n: int) -> dict:
    """Keypoint errors on ``n`` crops drawn with seed ``seed + HELDOUT_SEED_OFFSET`` (never trained on),
    each classified whole (no mask): pixels and millimetres per keypoint and overall, share found,
    hand score on hands, pixel accuracy of the parts."""
    crops = draw_crops(recipe, seed + HELDOUT_SEED_OFFSET, n)
    px, mm, found, scores, acc, roll_err = [], [], [], [], [], []
    kpx, kmm, kfound = [], [], []
    for c in crops:
        hand = "right" if c.mirror < 0 else "left"
        d = detect(c.depth, crop_camera(c), None, hand, detector=detector)
        truth = crop_truth_xyz(c)
        px.append(np.linalg.norm(d.keypoints_px - c.keypoints_uv, axis=1))
        mm.append(1000 * np.linalg.norm(d.keypoints_xyz - truth, axis=1))
        found.append(d.found)
        scores.append(d.hand_score)
        # the roll known (a tracked previous frame gives it): the parts layer alone
        k = detect(c.depth, crop_camera(c), None, hand, detector=detector, roll=c.roll)
        kpx.append(np.linalg.norm(k.keypoints_px - c.keypoints_uv, axis=1))
        kmm.append(1000 * np.linalg.norm(k.keypoints_xyz - truth, axis=1))
        kfound.append(k.found)
        rows, cols, lab = sample_pixels(c, np.random.default_rng(0), 400, 0)
        if len(rows):
            voted = detector.roll(c.depth, rows, cols, c.camera[0], c.camera[1], c.mirror)
            roll_err.append(abs(np.degrees(np.angle(np.exp(1j * (voted - c.roll))))))
            p = detector.proba(c.depth, rows, cols, c.camera[0], c.camera[1], c.mirror, c.roll)
            acc.append(float(np.mean(np.argmax(p, axis=1) == lab)))
    px, mm, found = np.array(px), np.array(mm), np.array(found)
    known = summary(np.array(kpx), np.array(kmm), np.array(kfound))
    return {"crops": n, "seed": seed + HELDOUT_SEED_OFFSET, **summary(px, mm, found),
            "roll_known": known, "roll_error_deg_median": _r(np.median(roll_err)),
            "roll_within_30deg": round(float(np.mean(np.array(roll_err) <= 30)), 4),
            "hand_part_accuracy": round(float(np.mean(acc)), 4), "hand_score_mean": round(float(np.mean(scores)), 4),
            "per_keypoint_mm_median": {PART_NAMES[k]: _r(np.nanmedian(mm[:, k])) for k in range(N_PARTS)}}


def _r(x, nd=2):
    return None if not np.isfinite(x) else round(float(x), nd)


def summary(px, mm, found) -> dict:
    """Mean and median errors over the keypoints found, and the share found."""
    ok = found & np.isfinite(mm)
    return {"found_share": round(float(found.mean()), 4), "px_mean": _r(np.mean(px[ok])),
            "px_median": _r(np.median(px[ok])), "mm_mean": _r(np.mean(mm[ok])), "mm_median": _r(np.median(mm[ok])),
            "mm_p90": _r(np.percentile(mm[ok], 90))}


def evaluate_real(detector, data_dir, detect_fn=detect) -> dict:
    """The labelled SR305 stills (``../shared/data/realsense_sr305_lada``) as the tracker sees them:
    the ``sr305`` preset, the right hand, the tracker's own segmentation as the mask
    (:func:`tracker.observe.observe`; the labelled mask is not used). Tips: the detected tip
    keypoints against the labelled tips; wrist: the detected wrist joint against the labelled crease
    (not the same point: the crease lies ~1–2 cm further along the arm). Evaluation only.
    ``detect_fn(depth, camera, mask, hand, detector=)``: the forest's :func:`tracker.detector.detect`
    or the CNN's :func:`tracker.keypoint_cnn.detect`."""
    from ..io.cameras import preset
    from ..io.images import read_depth_units, units_to_metres
    from ..observe import observe
    from .real_frames import read_labels

    root = Path(data_dir)
    labels = read_labels(root)
    cam = preset("sr305")
    names = sorted(k for k, v in labels.items() if isinstance(v, dict) and "wrist" in v)
    rows = []
    for name in names:
        depth = units_to_metres(read_depth_units(root / f"{name}.png", cam), cam)
        mask = observe(depth, cam).mask
        t0 = time.perf_counter()
        d = detect_fn(depth, cam, mask, "right", detector=detector)
        ms = 1000 * (time.perf_counter() - t0)
        lab = labels[name]
        tips = {t: _r(np.hypot(*(d.keypoints_px[PART_NAMES.index(t + "_tip")] - lab[t]))) for t in
                ("thumb", "index", "middle", "ring", "pinky") if t in lab}
        rows.append({"name": name, "tips_px": tips, "wrist_px": _r(np.hypot(*(d.keypoints_px[0] - lab["wrist"]))),
                     "hand_score": round(d.hand_score, 3), "ms": round(ms, 1)})
    tip = np.array([v if v is not None else np.nan for r in rows for v in r["tips_px"].values()], float)
    wr = np.array([r["wrist_px"] if r["wrist_px"] is not None else np.nan for r in rows], float)
    return {"frames": len(rows), "tips_found_share": round(float(np.isfinite(tip).mean()), 4),
            "tips_px_median": _r(np.nanmedian(tip)), "tips_px_mean": _r(np.nanmean(tip)),
            "tips_within_15px": int(np.sum(tip <= 15)), "tips": int(len(tip)),
            "wrist_joint_to_crease_px_median": _r(np.nanmedian(wr)),
            "frames_all_tips_within_15px": int(sum(all(v is not None and v <= 15 for v in r["tips_px"].values())
                                                   for r in rows)),
            "rows": rows}


def build(output, *, seed: int = 0, recipe: DataRecipe | None = None, settings: TrainSettings | None = None,
          heldout: int = 200, real_data=None, version: str = "1.0.0", command: str = "", progress=None,
          overwrite: bool = False) -> tuple[Path, dict]:
    """Train, evaluate and write ``output/hand-parts-<version>.npz``; returns the path and its manifest."""
    recipe = recipe or DataRecipe()
    settings = settings or TrainSettings()
    say = progress or (lambda msg: None)
    out = Path(output) / f"{DETECTOR_NAME}-{version}.npz"
    if out.exists() and not overwrite:
        raise TrackerError(str(out), "exists (give another output folder or --version)")
    arrays, info = train(recipe, settings, seed, progress)
    det = HandPartForest(arrays, {"bandwidth_m": settings.bandwidth_m})
    say(f"evaluating on {heldout} held-out crops")
    metrics = {"heldout": evaluate_synthetic(det, recipe, seed, heldout)}
    if real_data is not None:
        say("evaluating on the labelled SR305 stills")
        metrics["real_sr305"] = evaluate_real(det, real_data)
    manifest = {"name": DETECTOR_NAME, "version": version, "command": command, "seed": seed,
                "recipe": recipe.to_dict(), "settings": settings.to_dict(), "bandwidth_m": settings.bandwidth_m,
                "parts": list(PART_NAMES), "training": info, "metrics": metrics,
                "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    path = save_detector(out, arrays, manifest, overwrite=overwrite)
    return path, manifest



def evaluate_start(detector: HandPartForest, recipe: DataRecipe, seed: int, n: int, *, ideal_mask: bool = False,
                   synergies=None) -> dict:
    """The detector's keypoints and the start fitted to them (:func:`tracker.keypoint_fit.fit_start` on
    the tracker's hand at size 1, with ``synergies`` when given) on ``n`` held-out crops (seed
    ``seed + HELDOUT_SEED_OFFSET``): keypoint errors in mm against the rendered hand's. With
    ``ideal_mask`` the detector is given the true hand pixels (a perfect segmentation), otherwise
    the whole crop."""
    from handmodel import HandModel

    from .. import TRACKING_HAND
    from ..keypoint_fit import fit_start

    hands = {m: HandModel.load(TRACKING_HAND, right=m) for m in (False, True)}
    det_mm, start_mm, starts, ms = [], [], 0, []
    for c in draw_crops(recipe, seed + HELDOUT_SEED_OFFSET, n):
        right = c.mirror < 0
        mask = ((c.parts >= 0) & (c.parts < OTHER)) if ideal_mask else None
        d = detect(c.depth, crop_camera(c), mask, "right" if right else "left", detector=detector)
        truth = crop_truth_xyz(c)
        e = 1000 * np.linalg.norm(d.keypoints_xyz - truth, axis=1)
        det_mm.append(e[np.isfinite(e)])
        t0 = time.perf_counter()
        theta = fit_start(d, hands[right], synergies)
        ms.append(1000 * (time.perf_counter() - t0))
        if theta is not None:
            starts += 1
            start_mm.append(1000 * np.linalg.norm(hands[right].keypoints(theta) - truth, axis=1).mean())
    det_mm = np.concatenate(det_mm)
    return {"crops": n, "ideal_mask": ideal_mask, "synergies": synergies is not None,
            "detected_mm_median": _r(np.median(det_mm)), "starts": starts,
            "start_mean_keypoint_mm_median": _r(np.median(start_mm)) if start_mm else None,
            "start_within_20mm": int(np.sum(np.array(start_mm) <= 20)), "fit_start_ms_median": _r(np.median(ms))}
