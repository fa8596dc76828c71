"""The experiments report: every experiment of :mod:`tracker.sim.experiments` and the labelled real
frames (:mod:`tracker.sim.real_frames`) run once, written as ``report.md`` with tables next to the
paper's numbers and PNG figures (``tracker experiments``)."""
from __future__ import annotations

import io
from concurrent.futures import ProcessPoolExecutor, as_completed
from functools import lru_cache
from multiprocessing import get_context
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from handmodel import HandModel
from handmodel.fileio import atomic_write_bytes, atomic_write_text
from synergy.bundle import load_bundle

from .experiments import (
    FIRST_FRAME_MM, PAPER, REALISTIC_SCENES, REALISTIC_SENSORS, SCENARIO_NAMES, default_camera,
    experiment_density, experiment_icp, experiment_modes, experiment_occlusion,
    experiment_realistic,
    experiment_reduced_pcs, experiment_scenarios, experiment_single_frame, segments,
)
from .real_frames import (
    REAL_CALIBRATE_EACH, REAL_MASK_DILATE_PX, REAL_MASK_SHARE, REAL_TIP_PX, REAL_TIPS, REAL_WRIST_PX,
    experiment_real_frames,
)
from .. import TRACKING_HAND
from ..errors import TrackerError
from .noise import NoiseModel


def _figure():
    """A figure and its axes, drawn off-screen (no pyplot: no global backend to switch or figures to close)."""
    fig = Figure(figsize=(5.5, 3.6))
    FigureCanvasAgg(fig)
    return fig, fig.subplots()


def _save(fig, path):
    """Write a matplotlib figure as PNG atomically."""
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    atomic_write_bytes(path, buf.getvalue())


def _fig(path, xs, ys, xlabel, ylabel, ys2=None, ylabel2=None, paper=None, title=""):
    """Posture error (and optionally time on a second axis) against one setting."""
    fig, ax = _figure()
    ax.plot(xs, ys, "o-", color="C0", label="posture error (ours)")
    if paper is not None:
        ax.axhline(paper, color="C0", ls=":", label="paper")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel, color="C0")
    if ys2 is not None:
        ax2 = ax.twinx()
        ax2.plot(xs, ys2, "s--", color="C1", label="time")
        ax2.set_ylabel(ylabel2, color="C1")
    ax.set_title(title)
    ax.legend(loc="upper center", fontsize=8)
    _save(fig, path)


def _fig_pcs(path, rows):
    """Reduced mode against the number of PCs: tracked, geometric optimum, projection."""
    k = [r["n_pcs"] for r in rows]
    fig, ax = _figure()
    ax.plot(k, [r["error_deg"] for r in rows], "o-", label="tracked (reduced mode)")
    ax.plot(k, [r["oracle_deg"] for r in rows], "s--", label="geometric optimum of the subspace")
    ax.plot(k, [r["projection_deg"] for r in rows], "^:", label="projection of the truth")
    ax.axhline(2.0, color="grey", lw=0.8, ls="-.", label="2°")
    ax.set_xlabel("PCs")
    ax.set_ylabel("posture error (°)")
    ax.set_title("Reduced mode vs subspace size (noise-free)")
    ax.legend(fontsize=8)
    _save(fig, path)


def _nanmean(values) -> float:
    """Mean of the finite values, NaN (silently) when there are none."""
    v = np.asarray(values, float)
    return float(v[np.isfinite(v)].mean()) if np.isfinite(v).any() else float("nan")


def realistic_frames(quick: bool) -> int:
    """Frames per realistic-scene sequence."""
    return 5 if quick else 30


def realistic_lines(rows, frames) -> list:
    """The "realistic scenes" sections of the report (markdown lines): the runs with the colour frame, then
    those without it (rows whose ``color`` is False), each under its own heading."""
    seen = [r for r in rows if r.get("color", True)]
    blind = [r for r in rows if not r.get("color", True)]
    L = (["## Realistic scenes (clutter × sensor noise × hand size)", "", *_realistic_intro(frames),
          *_realistic_table(seen)] if seen else [])
    if blind:
        L += ["## Realistic scenes without colour (depth only)", "",
              "The same runs observed without the colour frame, as from a depth-only recording: the segmentation "
              "has no skin test and leaves out the frame's support plane instead (a table or floor seen at least "
              "30° off face-on, `Segmenter(plane=\"auto\")`, `tracker.segment.support_plane`). Before the plane, "
              "every frame of the `+table` runs was lost.", "", *_realistic_table(blind)]
    return L


def _realistic_intro(frames) -> list:
    """The realistic scenes' protocol (markdown lines)."""
    return [
         f"Motion open-close, {frames} frames per sequence, tracked from the first frame by today's default tracker "
         "with the hand size calibrated (`TrackerSettings().replace(scale=dict(hand_scale=\"auto\"))`: the first frame, refined over the "
         "next two), fingerfist bundle, default segmentation with the colour frame, gating by the predicted hand. "
         f"The rendered and the tracked hand are the tracker's (`{TRACKING_HAND}`: the paper's hand with its finger bases "
         "on the human metacarpal arc); the rendered one is it × scale with each finger's length × its own factor (drawn in 0.9–1.1, "
         "listed below the table), its forearm sized with it (keypoints compared on the rendered "
         "hand, mm; scale found / true: the tracker's size over the rendered global scale); cameras and noise: kinect1 "
         "(Kinect v1 preset), realsense (sr305 camera and noise). Scenes: " +
         "; ".join(f"{k}: `{v or 'none'}`" for k, v in REALISTIC_SCENES.items()) +
         f". First frame found: keypoint error ≤ {FIRST_FRAME_MM:g} mm. Acceptance target of the issue: "
         "keypoints ≤ 10 mm, first frame ≥ 95 %, scale within 3 %.", ""]


def _realistic_table(rows) -> list:
    """One realistic-scenes table with its summaries (markdown lines)."""
    L = ["| scene | sensor | hand scale | keypoint error mm | posture error ° | first frame found | first frame mm | "
         "lost frames | fps | scale found / true |", "|---|---|---|---|---|---|---|---|---|---|"]

    def num(x, fmt=".1f"):
        return "—" if not np.isfinite(x) else format(x, fmt)

    for r in rows:
        L.append(f"| {r['scene']} | {r['sensor']} | {r['scale']:g} | {num(r['keypoint_mm'])} | {num(r['posture_deg'])} | "
                 f"{'yes' if r['first_ok'] else 'no'} | {num(r['first_frame_mm'])} | {100 * r['lost']:.0f} % | "
                 f"{num(r['fps'])} | {num(r['scale_found'], '.3f')} |")
    L += ["", "— : no θ in any frame (nothing segmented) or no size estimate (fixed-size tracker).", ""]
    shapes = {r["scale"]: r.get("fingers") for r in rows if r.get("fingers")}
    if shapes:
        L += ["Rendered finger length factors (thumb, index, middle, ring, pinky): " + "; ".join(
            f"×{s:g}: " + " / ".join(f"{v:.2f}" for v in f.values()) for s, f in shapes.items()) + ".", ""]
    L += ["By scene (all sensors and sizes; errors over the runs with a θ):", "",
          "| scene | keypoint error mm | posture error ° | first frame found | lost frames |", "|---|---|---|---|---|"]
    for scene in dict.fromkeys(r["scene"] for r in rows):
        sel = [r for r in rows if r["scene"] == scene]
        L.append(f"| {scene} | {num(_nanmean([r['keypoint_mm'] for r in sel]))} | "
                 f"{num(_nanmean([r['posture_deg'] for r in sel]))} | "
                 f"{100 * np.mean([r['first_ok'] for r in sel]):.0f} % | {100 * np.mean([r['lost'] for r in sel]):.0f} % |")
    sc = np.array([r["scale_found"] for r in rows], float)
    kp = np.array([r["keypoint_mm"] for r in rows], float)
    L += ["", f"Against the acceptance: runs with mean keypoint error ≤ 10 mm: {np.sum(kp <= 10.0)} of {len(rows)} "
          f"(mean over runs {num(_nanmean(kp))} mm); first frame found: "
          f"{100 * np.mean([r['first_ok'] for r in rows]):.0f} %; size within 3 %: "
          + (f"{np.sum(np.abs(sc - 1.0) <= 0.03)} of {np.isfinite(sc).sum()} runs" if np.isfinite(sc).any()
             else "— (fixed-size tracker)") + ".", ""]
    return L


def real_lines(rows, overlay_dir="real", each=None) -> list:
    """The "real labelled frames" section of the report (markdown lines; overlays in ``overlay_dir``);
    ``each``: the same frames' rows on the hand calibrated from each recording's first stills."""
    L = ["## Real labelled frames (Intel RealSense SR305, ../shared/data/realsense_sr305_lada)", "",
         "Each labelled frame tracked as a user would: the `sr305` preset, the right hand, defaults (the tracker's "
         f"hand, `{TRACKING_HAND}`), the hand size calibrated on each recording's first labelled frame and reused for its "
         "other frames. Labels (wrist crease, "
         "fingertips, hand mask) were made by eye: straight tips ~5 px, curled ~8 px; the depth frames are "
         "LadaOndris/hand-recognition's (MIT licence; the overlays draw them under our fit). Floors of the issue: every "
         f"labelled tip ≤ {REAL_TIP_PX:g} px from its model tip, wrist ≤ {REAL_WRIST_PX:g} px, ≥ "
         f"{100 * REAL_MASK_SHARE:.0f} % of the keypoints inside the hand mask dilated by {REAL_MASK_DILATE_PX} px.", "",
         "| frame | size | " + " | ".join(f"{t} px" for t in REAL_TIPS) + " | wrist px | wrist joint px | keypoints in mask | all floors | overlay |",
         "|---|---|" + "---|" * len(REAL_TIPS) + "---|---|---|---|---|"]
    for r in rows:
        tips = " | ".join(f"{r['tips_px'][t]:.0f}" if t in r["tips_px"] else "—" for t in REAL_TIPS)
        L.append(f"| {r['name']} | {r['scale']:.2f} | {tips} | {r['wrist_px']:.0f} | {r['wrist_joint_px']:.0f} | {100 * r['in_mask']:.0f} % | "
                 f"{'yes' if r['ok'] else 'no'} | [png]({overlay_dir}/{r['name']}.png) |")
    wrists = np.array([r["wrist_px"] for r in rows])
    joints = np.array([r["wrist_joint_px"] for r in rows])
    palmward = sum(_toward_palm(r) > 0 for r in rows)
    L += ["", f"Frames meeting {_floor_counts(rows)}; keypoints in the mask ≥ "
          f"{100 * REAL_MASK_SHARE:.0f} %: {sum(r['in_mask'] >= REAL_MASK_SHARE for r in rows)} of {len(rows)}.", "",
          "The wrist is labelled as the middle of the skin crease, where the hand mask ends; it is compared with "
          "where the model hand ends, the middle of its palm's rounded base (`HandModel.wrist_crease`, the palm's "
          "half thickness past the wrist joint on the hand's axis, 11 mm at size 1.25): median "
          f"{np.median(wrists):.0f} px apart. The wrist joint itself (the palm's origin, the `wrist` keypoint of the "
          f"keypoint files) lies a median {np.median(joints):.0f} px from the label, on the palm side of the crease in "
          f"{palmward} of {len(rows)} frames: the difference of definition. The overlays draw the labelled wrist as "
          "a cyan cross beside the tips.", ""]
    keys, ends = _past_label(rows, "uv"), _past_label(rows, "ends_uv")
    if keys.size:
        end_tips = np.array([v for r in rows for v in r["tip_ends_px"].values()])
        L += ["A tip is labelled as the finger's outermost point on its centre line. The model finger's surface ends "
              "past its tip keypoint by the last segment's end radius (`HandModel.fingertip_ends`, 6.5 mm at size "
              f"1.25). Along the last bone, over the {keys.size} tip{'s' * (keys.size != 1)} not pointing at the camera, the tip keypoint "
              f"lies a median {np.median(keys):+.1f} px past the label (quartiles {np.percentile(keys, 25):+.1f} / "
              f"{np.percentile(keys, 75):+.1f}) and the finger's end {np.median(ends):+.1f} px "
              f"({np.percentile(ends, 25):+.1f} / {np.percentile(ends, 75):+.1f}): the fitted fingers reach past "
              "the fingers seen, as a model finger longer than the hand's would (the calibrated stills below find "
              "this hand's index and little finger ~0.9× the model's). Measured at the ends, tips within "
              f"{REAL_TIP_PX:g} px: {int(np.sum(end_tips <= REAL_TIP_PX))} of {end_tips.size} (median "
              f"{np.median(end_tips):.1f} px). The floors above are measured at the tip keypoints.", ""]
    if each:
        L += _each_lines(each)
    return L


def _floor_counts(rows) -> str:
    """The counts of real-frame rows against the floors: ``every floor: k of n; tips within …; wrist within …``."""
    tips = np.array([v for r in rows for v in r["tips_px"].values()])
    return (f"every floor: {sum(r['ok'] for r in rows)} of {len(rows)}; tips within {REAL_TIP_PX:g} px: "
            f"{int(np.sum(tips <= REAL_TIP_PX))} of {tips.size} (median {np.median(tips):.1f} px, worst "
            f"{tips.max():.0f} px); wrist within {REAL_WRIST_PX:g} px: "
            f"{sum(r['wrist_px'] <= REAL_WRIST_PX for r in rows)} of {len(rows)}")


def _each_lines(rows) -> list:
    """The real frames tracked on the hand calibrated from each recording's first stills, summed up."""
    hands = {}
    for r in rows:
        hands.setdefault(r["name"].split("_")[0], r)
    told = "; ".join(f"{k}: size {r['scale']:.3f}, " + ", ".join(f"{f} {v:.2f}" for f, v in r["fingers"].items())
                     for k, r in hands.items())
    return [f"The same frames on the hand calibrated from each recording's first {REAL_CALIBRATE_EACH} labelled "
            "frames, each fitted from its own start (`tracker calibrate --each`: the size their median, each "
            f"finger's length from all of them; {told}): frames meeting {_floor_counts(rows)}; frames off a floor: "
            + (", ".join(r["name"] for r in rows if not r["ok"]) or "none") + ".", ""]


def _past_label(rows, key) -> np.ndarray:
    """How far (px) each model tip (``key``: ``"uv"`` keypoints, ``"ends_uv"`` finger ends) lies past its
    label along the finger's projected last bone; fingers pointing at the camera (a last bone under
    8 px in the image) left out."""
    out = []
    for r in rows:
        uv, names = np.asarray(r["uv"], float), r["names"]
        for i, t in enumerate(REAL_TIPS):
            if t not in r["labels"]:
                continue
            bone = uv[names.index(t + "_tip")] - uv[names.index(t + "3")]
            n = np.linalg.norm(bone)
            if n >= 8.0:
                tip = np.asarray(r[key], float)[names.index(t + "_tip") if key == "uv" else i]
                out.append(float((tip - np.asarray(r["labels"][t], float)) @ bone / n))
    return np.array(out)


def _toward_palm(row) -> float:
    """How far (px) the model's wrist lies from the labelled wrist toward the labelled hand's centroid."""
    v, u = np.nonzero(row["mask"])
    lab = np.asarray(row["labels"]["wrist"], float)
    axis = np.array([u.mean(), v.mean()]) - lab
    return float((np.asarray(row["uv"], float)[0] - lab) @ axis / max(np.linalg.norm(axis), 1e-9))


def _context(quick):
    """What every part of the report shares: the hands (the paper's for its experiments, the tracker's for
    the realistic scenes), the bundle, the camera, the fingerfist segments."""
    return SimpleNamespace(hand=HandModel.load(), human=HandModel.load(TRACKING_HAND), bundle=load_bundle("fingerfist"), cam=default_camera(),
                           segs=segments(2 if quick else 4, 30 if quick else 60), quick=quick,
                           scen=("count", "grasp-back") if quick else SCENARIO_NAMES, kinect=NoiseModel.preset("kinect1"))


NO_NET = {"net": {"enabled": False}}
#: The report's parts, each a function of the shared context, the longest first (workers take them in order).
STEPS = {
    "realistic kinect1": lambda c: experiment_realistic(c.human, c.bundle, frames=realistic_frames(c.quick),
                                                        sensors={"kinect1": REALISTIC_SENSORS["kinect1"]}),
    "realistic realsense": lambda c: experiment_realistic(c.human, c.bundle, frames=realistic_frames(c.quick),
                                                          sensors={"realsense": REALISTIC_SENSORS["realsense"]}),
    "realistic kinect1, depth only": lambda c: experiment_realistic(c.human, c.bundle, frames=realistic_frames(c.quick),
                                                                    sensors={"kinect1": REALISTIC_SENSORS["kinect1"]},
                                                                    color=False),
    "realistic realsense, depth only": lambda c: experiment_realistic(
        c.human, c.bundle, frames=realistic_frames(c.quick), sensors={"realsense": REALISTIC_SENSORS["realsense"]},
        color=False),
    "scenarios, Kinect v1 noise": lambda c: experiment_scenarios(c.hand, c.bundle, c.cam, c.scen, noise=c.kinect),
    "scenarios": lambda c: experiment_scenarios(c.hand, c.bundle, c.cam, c.scen),
    "single": lambda c: experiment_single_frame(c.hand, c.bundle, c.cam, n=4 if c.quick else 24),
    "scenarios, no net": lambda c: experiment_scenarios(c.hand, c.bundle, c.cam, c.scen, modes=("full",), settings=NO_NET),
    "scenarios, Kinect v1 noise, no net": lambda c: experiment_scenarios(c.hand, c.bundle, c.cam, c.scen, modes=("full",),
                                                                         noise=c.kinect, settings=NO_NET),
    "reduced PCs": lambda c: experiment_reduced_pcs(c.hand, c.bundle, c.cam, c.segs,
                                                    (6, 10, 14) if c.quick else (4, 6, 8, 10, 12, 14, 16)),
    "icp": lambda c: experiment_icp(c.hand, c.bundle, c.cam, c.segs, (0, 1, 2, 4) if c.quick else (0, 1, 2, 3, 4, 6, 8)),
    "density": lambda c: experiment_density(c.hand, c.bundle, c.cam, c.segs, (2, 3, 4) if c.quick else (1, 2, 3, 4, 6)),
    "modes": lambda c: experiment_modes(c.hand, c.bundle, c.cam, c.segs),
    "noise": lambda c: experiment_modes(c.hand, c.bundle, c.cam, c.segs, noise=c.kinect),
    "mesh": lambda c: experiment_modes(c.hand, c.bundle, c.cam, c.segs[:1] if c.quick else c.segs[:2], model="mesh"),
    "occlusion": lambda c: experiment_occlusion(c.hand, c.cam, frames=30 if c.quick else 60),
}


@lru_cache(maxsize=2)
def _shared(quick):
    return _context(quick)


def run_step(name, quick):
    """One part of the report (:data:`STEPS`); a worker process builds the shared context once."""
    return STEPS[name](_shared(quick))


def run_steps(names, quick, jobs=1, progress=None):
    """Run the report's parts ``names``, in ``jobs`` worker processes when ``jobs`` > 1 (the parts are
    independent: two cores halve the report's time). Returns ``{name: result}``."""
    out = {}

    def tick(name):
        if progress:
            progress(len(out), len(names), name)

    if jobs <= 1:
        for name in names:
            out[name] = run_step(name, quick)
            tick(name)
        return out
    # spawn, not fork: numba's and BLAS's threads do not survive a fork
    with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(run_step, name, quick): name for name in names}
        for fut in as_completed(futures):
            try:
                out[futures[fut]] = fut.result()
            except Exception as e:  # a worker's failure, named by its step (the others are cancelled)
                pool.shutdown(cancel_futures=True)
                raise TrackerError("experiments", f"step {futures[fut]!r} failed: {e}") from e
            tick(futures[fut])
    return out


def report(out_dir, *, quick=False, progress=None, parts=None, jobs=1, real_data=None):
    """Run every experiment (or only ``parts``: ``{"paper", "realistic", "real"}``), in ``jobs`` processes, and
    write ``report.md`` with tables and PNG plots next to the paper's numbers. ``real_data``: the labelled
    real frames' folder (:func:`experiment_real_frames`; with it the report gets their section and overlays)."""
    parts = ({"paper", "realistic"} | ({"real"} if real_data is not None else set())) if parts is None else set(parts)
    bad = parts - {"paper", "realistic", "real"}
    if bad or not parts:
        raise TrackerError("experiments", f"unknown part(s) {', '.join(sorted(bad))} (paper, realistic, real)")
    if "real" in parts and real_data is None:
        raise TrackerError("experiments", "the real part needs the labelled frames' folder (--real-data)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    real = (experiment_real_frames(real_data, overlay_dir=out / "real") if "real" in parts else None)
    # the same frames on the hand calibrated from each recording's first stills (tracker calibrate --each)
    each = experiment_real_frames(real_data, calibrate_each=REAL_CALIBRATE_EACH) if "real" in parts else None
    if parts == {"real"}:
        L = ["# Experiments: real labelled frames", "", *real_lines(real, each=each)]
        atomic_write_text(out / "report.md", "\n".join(L) + "\n", overwrite=True)
        return {"real": real, "real_each": each}
    parts -= {"real"}
    names = [n for n in STEPS if ("realistic" if n.startswith("realistic") else "paper") in parts]
    res = run_steps(names, quick, jobs, progress)
    realistic = ([r for n in names if n.startswith("realistic") for r in res[n]] if "realistic" in parts else None)
    if parts == {"realistic"}:
        L = ["# Experiments: realistic scenes", "", *realistic_lines(realistic, realistic_frames(quick)),
             *(real_lines(real, each=each) if real is not None else [])]
        atomic_write_text(out / "report.md", "\n".join(L) + "\n", overwrite=True)
        return {"realistic": realistic, "real": real}
    c = _shared(quick)
    hand, bundle, cam, segs, scen_names = c.hand, c.bundle, c.cam, c.segs, c.scen
    icp, dens, modes, pcs = res["icp"], res["density"], res["modes"], res["reduced PCs"]
    noisy, mesh, occ, single = res["noise"], res["mesh"], res["occlusion"], res["single"]
    scen = {("none", True): res["scenarios"], ("kinect1", True): res["scenarios, Kinect v1 noise"],
            ("none", False): res["scenarios, no net"], ("kinect1", False): res["scenarios, Kinect v1 noise, no net"]}
    _fig(out / "fig8_icp_iterations.png", [k + 1 for k, _, _ in icp], [e for _, e, _ in icp], "ICP iterations (1 rigid + k)",
         "posture error (°)", [t for _, _, t in icp], "ms / frame", PAPER["fig8_error_5icp_deg"], "Fig. 8: stride 3")
    _fig(out / "fig9_density.png", [d for _, d, _, _ in dens], [e for _, _, e, _ in dens], "share of pixels used (1/stride²)",
         "posture error (°)", [t for _, _, _, t in dens], "ms / frame", None, "Fig. 9: 1 rigid + 4 ICP")
    _fig_pcs(out / "reduced_pcs.png", pcs)
    L = ["# Experiments (the paper's, on our renderer, real fingerfist trajectories)", "",
         f"Camera: {getattr(cam, 'name', 'kinect1')} {cam.width}×{cam.height}; hand at 0.6–0.9 m; {len(segs)} fingerfist "
         f"segments of {segs[0][1]} frames after a 10-frame lead-in; mesh-rendered, capsule-tracked unless stated; "
         f"bundle fingerfist@1.0.0 ({bundle.model.n_components_for(0.99)} PCs for 99 %). One core of this machine.", "",
         "## Fig. 8 — ICP iterations (stride 3, full DoF)", "", "| ICP iterations | posture error ° | ms/frame |", "|---|---|---|"]
    L += [f"| 1 + {k} | {e:.2f} | {t:.1f} |" for k, e, t in icp]
    L += ["", f"Paper: < {PAPER['fig8_error_5icp_deg']}° after 5 iterations. ![](fig8_icp_iterations.png)", "",
          "## Fig. 9 — sampling density (1 + 4 ICP iterations)", "", "| stride | pixels used | posture error ° | ms/frame |",
          "|---|---|---|---|"]
    L += [f"| {k} | 1/{k * k} | {e:.2f} | {t:.1f} |" for k, d, e, t in dens]
    L += ["", f"Paper: ~{PAPER['fig9_ms_stride3']:.0f} ms/frame at 1/3 on 8 cores. ![](fig9_density.png)", "",
          "## Modes (noise-free / Kinect v1 noise model / mesh correspondences)", "",
          "| mode | error ° | fps | error ° with noise | error ° mesh model |", "|---|---|---|---|---|"]
    for m in modes:
        L.append(f"| {m} | {modes[m]['error_deg']:.2f} | {modes[m]['fps']:.0f} | {noisy[m]['error_deg']:.2f} | "
                 f"{mesh[m]['error_deg']:.2f} |")
    L += ["", "Paper: 25 fps full, 30 fps reduced (8-core Xeon); cylinders 4° vs mesh 2° full DoF.", "",
          "## Reduced mode vs number of PCs (noise-free)", "",
          "A subspace costs accuracy twice: the true posture is not in it (*projection*: the closest subspace "
          "posture in joint angles), and geometry cannot find that closest posture: the depth data pull the "
          "subspace coordinates towards the posture whose surface matches best (*geometric optimum*: every "
          "model surface sample, hidden ones included, fitted with known correspondences — no tracker that "
          "fits geometry in that subspace can do better on noise-free data).", "",
          "| PCs | variance | tracked ° | geometric optimum ° | projection ° | ms/frame |", "|---|---|---|---|---|---|"]
    L += [f"| {r['n_pcs']} | {100 * r['variance']:.1f} % | {r['error_deg']:.2f} | {r['oracle_deg']:.2f} | "
          f"{r['projection_deg']:.2f} | {r['ms']:.1f} |" for r in pcs]
    L += ["", "![](reduced_pcs.png)", "",
          "## Occluded grasp (back of the hand to the camera)", "", "| mode | posture error ° | paper ° |", "|---|---|---|",
          f"| full | {occ['full']:.2f} | {PAPER['occluded_full_deg']} |",
          f"| reduced ({occ['n_pcs']} grasp PCs) | {occ['reduced']:.2f} | {PAPER['occluded_reduced_deg']} |",
          f"| reduced, 2 steps projected | {occ['reduced, 2 steps projected']:.2f} | |", "",
          "## Single frame from the global pose only (full cloud)", "",
          f"{len(single['rows'])} random fingerfist rows (seeded); the global pose is given, the posture is not. "
          "*Paper*: the paper's fits from the synergy mean with its method (`TrackerSettings.paper()`: plain "
          "least squares on data→model pairs); *plain*: the same fits with our estimation (silhouette term, "
          "Cauchy weights, normal test); *ours*: after the start search (synergy grid and finger-wise "
          "restarts), which both fits use.", "",
          "| method | mean ° | median ° | ≤ 1° | ≤ 2° | ≤ 5° | s/frame | paper ° |", "|---|---|---|---|---|---|---|---|"]
    names = {"flat_paper": ("flat, paper's method", PAPER["single_flat_deg"]),
             "hierarchical_paper": ("hierarchical, paper's method", PAPER["single_hier_deg"]),
             "flat_plain": ("flat, plain", ""), "hierarchical_plain": ("hierarchical, plain", ""),
             "flat": ("flat, ours", ""), "hierarchical": ("hierarchical, ours", "")}
    for key, (label, paper) in names.items():
        sh = single[key + "_share"]
        L.append(f"| {label} | {single[key][0]:.2f} | {single[key][1]:.2f} | {100 * sh[1.0]:.0f} % | {100 * sh[2.0]:.0f} % | "
                 f"{100 * sh[5.0]:.0f} % | {single['s_' + key][0]:.2f} | {paper} |")
    worst = np.argsort(-single["hierarchical_frames"])[:4]
    L += ["", "Worst frames (hierarchical, ours): " + ", ".join(
        f"row {single['rows'][i]} {single['hierarchical_frames'][i]:.1f}°" for i in worst), "",
          "## Hard cases: our synthetic scenarios (not the paper's)", "",
          "Tracked from the first frame, fingerfist bundle, our default tracker (safety net on) and the same without "
          "the safety net (*no net*). Mean posture error ° (share of frames ≤ 5°, share lost); *net ran*: share of "
          "frames the safety net searched on (full DoF); fps: frames over the tracker's whole time, the net's "
          "searches included (full DoF, one core).", "",
          "| scenario | frames | full | full, no net | hierarchical | full, Kinect v1 noise | full, Kinect v1, no net | "
          "hierarchical, Kinect v1 | net ran (noise-free / Kinect v1) | fps (noise-free / Kinect v1) |",
          "|---|---|---|---|---|---|---|---|---|---|"]

    def cell(c):
        return f"{c['error_deg']:.1f} ({100 * c['share_5deg']:.0f} %, {100 * c['lost']:.0f} %)"

    for name in scen_names:
        cells = []
        for nz in ("none", "kinect1"):
            cells += [cell(scen[nz, True][name, "full"]), cell(scen[nz, False][name, "full"]),
                      cell(scen[nz, True][name, "hierarchical"])]
        on, onk = scen["none", True][name, "full"], scen["kinect1", True][name, "full"]
        L.append(f"| {name} | {on['frames']} | " + " | ".join(cells) +
                 f" | {100 * on['net_share']:.0f} % / {100 * onk['net_share']:.0f} % | {on['fps']:.0f} / {onk['fps']:.0f} |")
    L.append("")
    if realistic is not None:
        L += realistic_lines(realistic, realistic_frames(quick))
    if real is not None:
        L += real_lines(real, each=each)
    atomic_write_text(out / "report.md", "\n".join(L) + "\n", overwrite=True)
    return {"icp": icp, "density": dens, "modes": modes, "reduced_pcs": pcs, "noise": noisy, "mesh": mesh, "occlusion": occ, "single": single,
            "scenarios": {f"{nz}{'' if net else ', no net'}": v for (nz, net), v in scen.items()}, "realistic": realistic,
            "real": real}
