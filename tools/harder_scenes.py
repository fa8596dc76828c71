"""Harder realistic scenes (issue 38, acceptance 1): fists, pinches, grasps; forearm + torso; Kinect v1 and SR305
noise; hands 0.8/1.0/1.5x; the tracker with the size calibrated, settings changes as JSON. One row per run.

Run: .venv/bin/python tools/harder_scenes.py LABEL [SETTINGS_JSON] [MOTIONS] [FRAMES] [--clutter SPEC]
     [--upper-arm-dir X,Y,Z] [--scales 0.8,1.0,1.5]
(e.g. `defaults '{}' fist-palm,fist-side,pinch,grasp-back 45`; `upperarm '{}' pinch 45 --clutter
forearm,upperarm,torso --scales 0.8`)

``--clutter`` is a :meth:`tracker.sim.render.Clutter.parse` spec (default ``forearm,torso``). The scene keeps the
name of the realistic experiment's ``+forearm+torso`` scene whatever the clutter, because
``experiment_realistic`` seeds the sensor noise by the scene's place in ``REALISTIC_SCENES``: the rows of two
clutters then differ by the clutter alone (same motion, hand, fingers and noise draws).
``--upper-arm-dir`` sets the upper arm's direction from the elbow (camera frame), e.g. ``0,0.6,0.8``.
"""
import argparse
import json
import time
from dataclasses import replace

import numpy as np
from handmodel import HandModel
from synergy.bundle import load_bundle
from tracker import TRACKING_HAND
from tracker.sim.experiments import REALISTIC_SCALES, experiment_realistic
from tracker.sim.render import Clutter

DEFAULT_CLUTTER = "forearm,torso"

ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
ap.add_argument("label")
ap.add_argument("settings", nargs="?", default=None, help="TrackerSettings changes as JSON")
ap.add_argument("motions", nargs="?", default="fist-palm,fist-side,pinch,grasp-back")
ap.add_argument("frames", nargs="?", type=int, default=60)
ap.add_argument("--clutter", default=DEFAULT_CLUTTER, help="Clutter.parse spec (default forearm,torso)")
ap.add_argument("--upper-arm-dir", default=None, help="the upper arm's direction from the elbow, X,Y,Z (camera)")
ap.add_argument("--scales", default=None, help="rendered hand sizes, e.g. 0.8 (default 0.8,1.0,1.5)")
a = ap.parse_args()
label = a.label
settings = json.loads(a.settings) if a.settings else None
motions = a.motions.split(",")
frames = a.frames
scales = REALISTIC_SCALES if a.scales is None else tuple(float(s) for s in a.scales.split(","))
clutter = Clutter.parse(a.clutter)
if a.upper_arm_dir is not None:
    clutter = replace(clutter, upper_arm_dir=tuple(float(v) for v in a.upper_arm_dir.split(",")))
if a.clutter != DEFAULT_CLUTTER or a.upper_arm_dir is not None or a.scales is not None:
    print(f"# clutter {clutter.describe()}"
          + (f" upper arm along {clutter.upper_arm_dir}" if clutter.upper_arm else "")
          + f", scales {','.join(f'{s:g}' for s in scales)}", flush=True)
hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
st = {"scale": {"hand_scale": "auto"}, **(settings or {})}
allk = []
for m in motions:
    t = time.time()
    rows = experiment_realistic(hand, bundle, scenes={"+forearm+torso": clutter}, motion=m, frames=frames, settings=st,
                                scales=scales)
    for r in rows:
        allk.append(r["keypoint_mm"])
        print(f"{label:10s} {m:11s} {r['sensor']:9s} x{r['scale']:<4g} kp {r['keypoint_mm']:6.1f} mm  post {r['posture_deg']:5.1f}  first {r['first_frame_mm']:6.1f}  lost {100*r['lost']:3.0f}%  fps {r['fps']:6.1f}  scale {r['scale_found']:.3f}", flush=True)
    print(f"# {m} {time.time()-t:.0f}s", flush=True)
print(f"{label} mean keypoint mm over runs {np.nanmean(allk):.1f}, worst {np.nanmax(allk):.1f}")
