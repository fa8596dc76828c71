"""The paper's experiments on our renderer with real trajectories (fingerfist postures):
error and time vs ICP iterations (Fig. 8) and vs sampling density (Fig. 9), the occluded grasp (full
vs reduced), single-frame hierarchical vs flat, capsules vs mesh, and the noise model; and ours:
realistic scenes (clutter × sensor noise × hand size, :func:`experiment_realistic`). The labelled real
frames: :mod:`tracker.sim.real_frames`.

Everything runs in memory (render → observe → track), so the same code serves the report
(:mod:`tracker.sim.report`, ``tracker experiments -o report/``) and the tests (small sizes).
"""
from __future__ import annotations

import time
from pathlib import Path
from dataclasses import dataclass, field

import numpy as np

from handmodel import HandModel
from handmodel.dofs import POSTURE_DOF_NAMES
from handmodel.rigid import euler_to_matrix
from handmodel.solver import SolverSettings, fit_points
from synergy import simulate
from synergy.bundle import Bundle
from synergy.pca import SynergyModel

from ..io.cameras import as_camera, preset
from ..correspond import ModelSamples, Silhouette
from ..evaluate import posture_error_deg
from ..observe import observe
from ..init import InitSettings
from ..track import FrameTracker, TrackerSettings
from .hands import FINGERS, HandShape, wrist_to_middle_tip_mm
from .motions import GlobalPath, fingerfist_path, hand_centre, make_motion, read_schroeder26, with_path
from .noise import NoiseModel
from .clutter import Clutter
from .render import DepthRenderer

PAPER = {
    "fig8_error_5icp_deg": 2.0, "fig9_ms_stride3": 40.0, "occluded_full_deg": 12.0, "occluded_reduced_deg": 4.0,
    "single_flat_deg": 22.0, "single_hier_deg": 0.4, "single_s": 10.0, "cylinders_full_deg": 4.0, "mesh_full_deg": 2.0,
    "fps_full": 25.0, "fps_reduced": 30.0,
}


def default_camera():
    return preset("kinect1")


@dataclass
class SequenceResult:
    error_deg: np.ndarray
    ms: np.ndarray
    status: np.ndarray
    theta: np.ndarray
    lead: int = 0
    extra: dict = field(default_factory=dict)

    @property
    def mean_error(self) -> float:
        return float(np.nanmean(self.error_deg[self.lead:]))

    @property
    def median_ms(self) -> float:
        return float(np.median(self.ms[self.lead:]))


def fingerfist_postures():
    return read_schroeder26(fingerfist_path())


def sequence(postures, start_posture, *, lead=10, distance=0.75, tilt=(0.2, 0.3, 0.0), lateral=(0.0, -0.05)):
    """θ truth: a ``lead``-frame transition from ``start_posture`` into the posture rows, hand
    centred ``distance`` m in front of the camera, palm towards it with a tilt (radians)."""
    hand = HandModel.load()
    P = np.vstack([np.linspace(start_posture, postures[0], lead), postures]) if lead else np.asarray(postures)
    th = np.zeros((len(P), hand.n_dofs))
    th[:, ~hand.pose_mask] = P
    th[:, 3:6] = tilt
    # put the palm centre (≈ 6 cm along the fingers from the wrist) at the requested spot
    R = euler_to_matrix(np.asarray(tilt, float))
    th[:, :3] = np.array([lateral[0], lateral[1], distance]) - R @ np.array([0.0, 0.06, 0.0])
    return th


def run_sequence(hand, truth, camera, tracker, *, renderer=None, noise=None, stride=None, seed=0, lead=0,
                 blank=None):
    """Render each frame, observe it (segmentation, stride sampling, normals) and track it."""
    ren = renderer or DepthRenderer(hand, camera)
    stride = stride or tracker.settings.observe.stride
    F = len(truth)
    err, ms, status, th = np.full(F, np.nan), np.zeros(F), np.empty(F, object), np.full((F, hand.n_dofs), np.nan)
    net = np.empty(F, object)
    for f in range(F):
        depth = ren.render(truth[f], labels=False).depth
        if noise is not None:
            depth = noise.apply(depth, camera, rng=np.random.default_rng([seed, f]))
        if blank is not None and blank[0] <= f < blank[1]:
            depth = np.full_like(depth, np.nan)
        ob = observe(depth, camera, tracker.settings.observe, stride=stride)
        t0 = time.perf_counter()
        r = tracker.track(ob, camera)
        ms[f] = (time.perf_counter() - t0) * 1000.0
        status[f] = r.status
        net[f] = r.net
        th[f] = r.theta
        if np.all(np.isfinite(r.theta)):
            err[f] = posture_error_deg(r.theta, truth[f], hand.pose_mask)
    return SequenceResult(err, ms, status, th, lead, {"net": net})


def segments(n, length, seed=0):
    """``n`` start rows of fingerfist segments spread over both recordings of the file."""
    starts = np.linspace(100, 6000 - length - 100, n).astype(int)
    return [(int(s), length) for s in starts]


# ----------------------------------------------------------------------------------------- report
def _tracker(hand, bundle, paper=False, **kw):
    """A tracker with our defaults, or with ``TrackerSettings.paper()``, changed by ``kw``; at the
    model's size (``hand_scale=1.0``: these experiments render our own hand)."""
    base = TrackerSettings.paper() if paper else TrackerSettings().replace(scale=dict(hand_scale=1.0))
    return FrameTracker(hand, base.replace(**kw), synergies=bundle)


def _segment_truths(bundle, segs):
    """θ truth of each fingerfist segment, the hand at 0.6, 0.7, 0.8, 0.9 m in turn."""
    P = fingerfist_postures()
    return [sequence(P[s:s + n], bundle.model.mean_, distance=0.6 + 0.3 * (i % 4) / 3) for i, (s, n) in enumerate(segs)]


def _over_segments(hand, bundle, camera, truths, noise=None, **settings):
    """Track every segment with one setting; the trackers, the mean posture error and ms per frame."""
    trackers, e, t = [], [], []
    for i, truth in enumerate(truths):
        tr = _tracker(hand, bundle, **settings)
        r = run_sequence(hand, truth, camera, tr, noise=noise, seed=i, lead=10)
        trackers.append(tr)
        e.append(r.mean_error)
        t.append(r.median_ms)
    return trackers, float(np.mean(e)), float(np.mean(t))


def experiment_icp(hand, bundle, camera, segs, iterations=(0, 1, 2, 3, 4, 6, 8), mode="full"):
    """Fig. 8: posture error and time vs non-rigid ICP iterations (1 rigid + k), stride 3."""
    truths = _segment_truths(bundle, segs)
    return [(k, *_over_segments(hand, bundle, camera, truths, mode=mode, icp=dict(icp_iterations=k),
                                  observe=dict(target_points=None))[1:])
            for k in iterations]


def experiment_density(hand, bundle, camera, segs, strides=(1, 2, 3, 4, 6), mode="full"):
    """Fig. 9: posture error and time vs sampling density (every k-th pixel in x and y), 1+4 ICP."""
    truths = _segment_truths(bundle, segs)
    return [(k, 1.0 / k ** 2, *_over_segments(hand, bundle, camera, truths, mode=mode,
                                                  observe=dict(stride=k, target_points=None))[1:])
            for k in strides]


# the tracking variants compared throughout: label → settings
VARIANTS = {"full, paper's method (our start)": {"paper": True, "mode": "full", "init": InitSettings()},
            "full": {"mode": "full"}, "reduced": {"mode": "reduced"},
            "reduced, 2 steps projected": {"mode": "reduced", "icp": {"projected_steps": 2}},
            "hierarchical": {"mode": "hierarchical"}}


def experiment_modes(hand, bundle, camera, segs, noise=None, model="capsules", variants=VARIANTS):
    """Full / reduced (α-only, and with the last steps projected) / hierarchical on the same
    sequences; optional noise model."""
    truths = _segment_truths(bundle, segs)
    res = {}
    for label, kw in variants.items():
        trackers, e, t = _over_segments(hand, bundle, camera, truths, noise=noise, correspond=dict(model=model), **kw)
        res[label] = {"error_deg": e, "ms": t, "fps": 1000.0 / t}
        if label == "reduced":
            recon = [np.mean(posture_error_deg(tr.reduced.project(truth), truth, hand.pose_mask)[10:])
                     for tr, truth in zip(trackers, truths)]
            res[label]["subspace_reconstruction_deg"] = float(np.mean(recon))
    return res


def subspace_oracle(hand, subspace, truth, theta0=None):
    """The subspace posture whose capsule surface best matches the truth's (every surface sample of
    the model, hidden ones included, with known correspondences): what any estimator that fits
    geometry inside ``subspace`` converges to at best on noise-free data. Compare with
    ``subspace.project(truth)``, the best in joint-angle terms, which geometry cannot see. The fit
    starts from that projection unless ``theta0`` is given."""
    ms = ModelSamples(hand, spacing=0.006)
    targets = np.stack([ms.pose(t)[0] for t in truth])
    start = subspace.project(truth) if theta0 is None else theta0
    th, _ = fit_points(hand, ms.nodes, ms.local, targets, theta0=start, subspace=subspace,
                       settings=SolverSettings(iterations=40, damping=0.01), restarts=0)
    return th


def experiment_reduced_pcs(hand, bundle, camera, segs, counts=(6, 8, 10, 12, 14)):
    """Reduced mode vs the number of PCs: tracked error, the subspace's angular projection error and
    its geometric optimum (:func:`subspace_oracle`), noise-free, capsule-tracked."""
    truths = _segment_truths(bundle, segs)
    m = bundle.model
    rows = []
    for k in counts:
        trackers, e, t = _over_segments(hand, bundle, camera, truths, mode="reduced",
                                        subspace=dict(n_pcs=k, variance=None))
        proj = np.mean([np.mean(posture_error_deg(tr.reduced.project(tt), tt, hand.pose_mask)[10:])
                        for tr, tt in zip(trackers, truths)])
        orac = np.mean([np.mean(posture_error_deg(subspace_oracle(hand, tr.reduced, tt[10:]), tt[10:], hand.pose_mask))
                        for tr, tt in zip(trackers, truths)])
        var = float(np.sum(m.all_explained_variance_ratio_[:k]))
        rows.append({"n_pcs": k, "variance": var, "error_deg": e, "projection_deg": float(proj),
                     "oracle_deg": float(orac), "ms": t})
    return rows


SCENARIO_NAMES = ("still", "open-close", "count", "spread", "random", "fast", "rotate", "grasp-back")


def experiment_scenarios(hand, bundle, camera, names=SCENARIO_NAMES, modes=("full", "hierarchical"), noise=None,
                         settings=None):
    """Our synthetic scenarios (tracker.sim.motions: finger counting, random postures, fast sweeps, a turn
    from palm to back, a grasp seen from the back) tracked from their first frame by our default tracker
    changed by ``settings`` (e.g. ``{"net": {"enabled": False}}``): mean posture error, share of frames ≤ 5°,
    share lost, share of frames the safety net ran on and fps (frames over the tracker's whole time,
    the net's searches included), per mode."""
    out = {}
    for name in names:
        th = make_motion(name, hand=hand).theta
        for mode in modes:
            tr = _tracker(hand, bundle, mode=mode, **(settings or {}))
            r = run_sequence(hand, th, camera, tr, noise=noise, seed=0)
            e = np.nan_to_num(r.error_deg, nan=np.inf)
            out[name, mode] = {"error_deg": r.mean_error, "share_5deg": float(np.mean(e <= 5.0)),
                               "lost": float(np.mean(r.status == "lost")), "frames": len(th),
                               "net_share": float(np.mean(r.extra["net"] != "")),
                               "fps": float(1000.0 * len(th) / np.sum(r.ms))}
    return out


def grasp_bundle(seed=0):
    """A grasp-only synergy bundle fitted in memory from our simulator's grasp trials (power and
    precision grasps, several seeds), like the paper's grasp data set."""
    X = np.vstack([simulate.motion(m, duration_s=3.0, seed=seed + k)[0][:, 6:]
                   for m in ("power_grasp", "precision_grasp") for k in range(6)])
    manifest = {"name": "simulated-grasps", "version": "0.0.0", "tasks": ["grasp"]}
    return Bundle(SynergyModel().fit(X), manifest, Path("(in memory)"), POSTURE_DOF_NAMES)


def experiment_occlusion(hand, camera, frames=45, seed=0):
    """Grasp seen from the back of the hand (fingers self-occluded): full vs reduced (grasp synergies)."""
    gb = grasp_bundle(seed=100)
    n_pcs = gb.model.n_components_for(0.99)
    th, _ = simulate.motion("power_grasp", duration_s=frames / 30.0, rate=30.0, seed=seed + 50)
    path = GlobalPath(facing="back", tilt_deg=(-15.0, 0.0, 0.0), wobble_deg=(0.0, 0.0, 0.0))
    truth = with_path(th[:, 6:], hand, 30.0, path)
    res = {}
    for label in ("full", "reduced", "reduced, 2 steps projected"):
        tr = _tracker(hand, gb, subspace=dict(n_pcs=n_pcs, variance=None), **VARIANTS[label])
        r = run_sequence(hand, truth, camera, tr, lead=5)
        res[label] = r.mean_error
    res["n_pcs"] = n_pcs
    return res


SINGLE_METHODS = (  # key, mode, search, settings: the paper's two fits from the mean posture with its method
    ("flat_paper", "full", False, "paper"), ("hierarchical_paper", "hierarchical", False, "paper"),
    # … the same two fits with our estimation (silhouette term, Cauchy weights, normal test) …
    ("flat_plain", "full", False, "ours"), ("hierarchical_plain", "hierarchical", False, "ours"),
    # … and ours: the start search (synergy grid, finger-wise restarts) first
    ("flat", "full", True, "ours"), ("hierarchical", "hierarchical", True, "ours"))


def experiment_single_frame(hand, bundle, camera, n=12, icp=30, seed=0, methods=SINGLE_METHODS, from_pose=True):
    """Single frames from the global pose only (posture unknown), full cloud. The paper's flat (all
    DoF) and hierarchical (1 → 4 → l PCs → all DoF) fits from the synergy mean, with
    ``TrackerSettings.paper()`` (``*_paper``) and with our estimation (``*_plain``), and ours: our
    defaults after the start search (synergy grid, finger-wise restarts). ``from_pose`` False: the same
    frames from no pose at all (the search places the hand from the cloud).

    Returns per method ``(mean, median)`` degrees, ``<key>_frames`` (per frame), ``<key>_share``
    (share of frames ≤ 1, 2, 5°) and ``s_<key>`` (seconds per frame, mean and median)."""
    P = fingerfist_postures()
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(P), n, replace=False)
    ren = DepthRenderer(hand, camera)
    trackers = {"ours": _tracker(hand, bundle, mode="full", init=dict(icp_iterations=icp)),
                "paper": _tracker(hand, bundle, paper=True, mode="full", init=dict(icp_iterations=icp))}
    out = {k: [] for k, *_ in methods}
    sec = {k: [] for k, *_ in methods}
    for i, row in enumerate(rows):
        truth = sequence(P[row:row + 1], bundle.model.mean_, lead=0, distance=0.6 + 0.3 * (i % 4) / 3)[0]
        depth = ren.render(truth, labels=False).depth
        ob = observe(depth, camera, stride=1, target_points=None, smooth=0)
        sil = Silhouette(ob.mask, ob.depth, camera)
        start = truth.copy()
        start[~hand.pose_mask] = bundle.model.mean_
        for key, mode, search, which in methods:
            t0 = time.perf_counter()
            th, _ = trackers[which].fit_single_frame(ob.points, theta0=start if from_pose else None, mode=mode,
                                                     silhouette=sil, normals=ob.normals,
                                                     postures=None if search else [bundle.model.mean_], search=search)
            sec[key].append(time.perf_counter() - t0)
            out[key].append(float(posture_error_deg(th, truth, hand.pose_mask)))
    res = {"rows": [int(r) for r in rows]}
    for key in out:
        e = np.asarray(out[key])
        res[key] = (float(np.mean(e)), float(np.median(e)))
        res["s_" + key] = (float(np.mean(sec[key])), float(np.median(sec[key])))
        res[key + "_frames"] = e
        res[key + "_share"] = {t: float(np.mean(e <= t)) for t in (1.0, 2.0, 5.0)}
    return res


# ------------------------------------------------------------------------------ realistic scenes
#: Scene label → clutter spec (:meth:`tracker.sim.clutter.Clutter.parse`); every cluttered scene has the forearm,
#: as a real hand does.
REALISTIC_SCENES = {"hand alone": None, "+forearm": "forearm", "+forearm+torso": "forearm,torso",
                    "+table": "forearm,table", "+object": "forearm,box",
                    # the near end of "a torso 3-30 cm behind the hand" (the scene above: 15 cm)
                    "+torso 4 cm": "forearm,torso=0.04"}
#: Sensor label → (camera preset, noise preset).
REALISTIC_SENSORS = {"kinect1": ("kinect1", "kinect1"), "realsense": ("sr305", "sr305")}
REALISTIC_SCALES = (0.8, 1.0, 1.5)
#: Half-width of the rendered fingers' length factors (the issue's "fingers ±10 %"): real hands differ from
#: the model in proportions, not only in size, and a tracker that only sizes the hand must cope with it.
REALISTIC_FINGER_SPREAD = 0.1
#: The tracker of the realistic scenes: today's defaults with the hand size calibrated from the
#: first frames (the rendered hands are not the model's size).
REALISTIC_SETTINGS = {"scale": {"hand_scale": "auto"}}
FIRST_FRAME_MM = 20.0  # a first frame counts as found when its mean keypoint error is at most this


def placed_clutter(clutter, hand, shown, truth):
    """``clutter`` (a :class:`~tracker.sim.render.Clutter` or its spec) as a scene of the hand ``shown``
    (the model ``hand`` resized, :class:`~tracker.sim.hands.HandShape`) moving through ``truth`` renders it:
    sized with the rendered hand (a resized hand comes with a resized forearm; the wrist-to-middle-tip
    length's ratio) and fixed at the hand's mean centre over the motion."""
    if isinstance(clutter, str):
        clutter = Clutter.parse(clutter)
    R = euler_to_matrix(truth[:, 3:6])
    size = wrist_to_middle_tip_mm(shown) / wrist_to_middle_tip_mm(hand)
    return clutter.sized(size).fixed((truth[:, :3] + R @ hand_centre(shown)).mean(axis=0))


def run_scene(hand, shown, truth, camera, tracker, *, clutter=None, noise=None, seed=0, color=True, segmenter=None):
    """Render the hand ``shown`` (possibly resized, :class:`~tracker.sim.hands.HandShape`) at each θ of
    ``truth`` with ``clutter`` and ``noise``, observe it with the default segmentation (colour frame
    included when ``color``; ``segmenter``: a :class:`tracker.segment.Segmenter` instead of the default)
    and track it with ``tracker``, whose model is ``hand``.

    Returns a dict of per-frame arrays: ``keypoint_mm`` (mean distance of the 21 keypoints of the
    tracker's hand at its θ to the rendered hand's at the truth, mm), ``posture_deg``, ``status``,
    ``ms`` (tracker only) and ``scale`` (the tracker's hand size; NaN before it has one)."""
    cam = as_camera(camera)
    ren = DepthRenderer(shown, cam)
    if clutter is not None:
        clutter = placed_clutter(clutter, hand, shown, truth)
    F = len(truth)
    out = {"keypoint_mm": np.full(F, np.nan), "posture_deg": np.full(F, np.nan), "status": np.empty(F, object),
           "ms": np.zeros(F), "scale": np.full(F, np.nan)}
    need_inc = noise is not None and noise.needs_incidence
    need_refl = noise is not None and noise.needs_reflectance
    for f in range(F):
        r = ren.render(truth[f], labels=False, color=color, clutter=clutter, incidence=need_inc,
                       reflectance=need_refl)
        depth = r.depth
        if noise is not None:
            depth = noise.apply(depth, cam, np.random.default_rng([seed, f]), r.cos_incidence, r.reflectance)
        ob = observe(depth, cam, tracker.settings.observe, color=r.color, segmenter=segmenter,
                     window=tracker.segment_window(cam))
        t0 = time.perf_counter()
        res = tracker.track(ob, cam, color=r.color)
        out["ms"][f] = (time.perf_counter() - t0) * 1000.0
        out["status"][f] = res.status
        if np.all(np.isfinite(res.theta)):
            kp = tracker.hand.keypoints(res.theta) - shown.keypoints(truth[f])
            out["keypoint_mm"][f] = float(np.linalg.norm(kp, axis=-1).mean() * 1000.0)
            out["posture_deg"][f] = float(posture_error_deg(res.theta, truth[f], hand.pose_mask))
        if tracker.scale_ is not None:
            out["scale"][f] = tracker.scale_
    return out


def realistic_fingers(scale, seed=0, spread=REALISTIC_FINGER_SPREAD) -> dict:
    """The rendered hand's finger length factors for hand ``scale``: one draw per finger, uniform in
    1 ± ``spread``, seeded by ``seed`` and the scale (the same hand in every scene and sensor).

    >>> f = realistic_fingers(0.8)
    >>> sorted(f) == sorted(FINGERS) and all(0.9 <= v <= 1.1 for v in f.values())
    True
    >>> realistic_fingers(0.8, spread=0.0)["index"]
    1.0
    """
    draw = np.random.default_rng([int(seed), int(round(float(scale) * 1000))]).uniform(-1.0, 1.0, len(FINGERS))
    return {name: round(1.0 + spread * float(u), 3) for name, u in zip(FINGERS, draw)}


def experiment_realistic(hand, bundle, *, scenes=None, sensors=None, scales=REALISTIC_SCALES, frames=30,
                         motion="open-close", settings=None, seed=0, finger_spread=REALISTIC_FINGER_SPREAD,
                         progress=None, color=True):
    """Realistic scenes: each scene (:data:`REALISTIC_SCENES`) × sensor (:data:`REALISTIC_SENSORS`) ×
    rendered hand scale, tracked from its first frame by a fresh tracker of the model ``hand``
    (``settings``: :class:`TrackerSettings` changes; default: :data:`REALISTIC_SETTINGS`, today's
    defaults with the size calibrated). The rendered hand's fingers are lengthened or shortened by
    :func:`realistic_fingers` (``finger_spread`` 0: the model's proportions). ``color``: observed with
    the rendered colour frame (skin segmentation), else depth only.

    Returns one dict per run: ``scene``, ``sensor``, ``scale``, ``color``, ``frames``, ``keypoint_mm`` (mean over
    the frames with a θ), ``posture_deg``, ``first_frame_mm``, ``first_ok`` (≤ :data:`FIRST_FRAME_MM`),
    ``lost`` (share of frames), ``fingers`` (the rendered finger factors), ``fps`` (1000 / median tracker ms over the frames with a θ) and ``scale_found`` (the tracker's
    final hand size relative to the rendered one, 1 = exact; NaN when the tracker does not estimate it)."""
    scenes = REALISTIC_SCENES if scenes is None else scenes
    sensors = REALISTIC_SENSORS if sensors is None else sensors
    total = len(scenes) * len(sensors) * len(scales)
    rows = []
    for sensor, (cam_name, noise_name) in sensors.items():
        cam, nm = preset(cam_name), NoiseModel.preset(noise_name)
        for scale in scales:
            fingers = realistic_fingers(scale, seed, finger_spread)
            shown = HandShape(float(scale), fingers).apply(hand)
            truth = make_motion(motion, hand=shown, frames=frames, seed=seed).theta
            for k, (scene, spec) in enumerate(scenes.items()):
                tracker = FrameTracker(hand, TrackerSettings().replace(**(REALISTIC_SETTINGS if settings is None
                                                                        else settings)), synergies=bundle)
                # the noise's seed follows the scene's name, so a subset of scenes reproduces the full run's rows
                j = list(REALISTIC_SCENES).index(scene) if scene in REALISTIC_SCENES else k
                r = run_scene(hand, shown, truth, cam, tracker, clutter=spec, noise=nm, seed=seed + j, color=color)
                ke = r["keypoint_mm"]
                fitted = np.isfinite(ke)
                auto = tracker.settings.scale.hand_scale == "auto"
                rows.append({
                    "scene": scene, "clutter": spec or "none", "sensor": sensor, "scale": float(scale),
                    "color": bool(color),
                    "fingers": fingers,
                    "frames": len(truth),
                    "keypoint_mm": float(np.nanmean(ke)) if np.isfinite(ke).any() else float("nan"),
                    "posture_deg": (float(np.nanmean(r["posture_deg"])) if np.isfinite(r["posture_deg"]).any()
                                    else float("nan")),
                    "first_frame_mm": float(ke[0]), "first_ok": bool(ke[0] <= FIRST_FRAME_MM),
                    "lost": float(np.mean(r["status"] == "lost")),
                    # frames without points cost nothing: they would make an empty sequence look fast
                    "fps": float(1000.0 / np.median(r["ms"][fitted])) if fitted.any() else float("nan"),
                    "scale_found": float(r["scale"][-1] / scale) if auto else float("nan"),
                })
                if progress is not None:
                    progress(len(rows), total, f"{sensor} ×{scale:g} {scene}")
    return rows
