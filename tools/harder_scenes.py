"""Harder realistic scenes (issue 38, acceptance 1): fists, pinches, grasps; forearm + torso; Kinect v1 and SR305
noise; hands 0.8/1.0/1.5x; the tracker with the size calibrated, settings changes as JSON. One row per run.

Run: .venv/bin/python tools/harder_scenes.py LABEL [SETTINGS_JSON] [MOTIONS] [FRAMES]
(e.g. `defaults '{}' fist-palm,fist-side,pinch,grasp-back 45`)
"""
import sys, json, time
import numpy as np
from handmodel import HandModel
from synergy.bundle import load_bundle
from tracker import TRACKING_HAND
from tracker.sim.experiments import experiment_realistic
label = sys.argv[1]
settings = json.loads(sys.argv[2]) if len(sys.argv) > 2 else None
motions = sys.argv[3].split(",") if len(sys.argv) > 3 else ["fist-palm", "fist-side", "pinch", "grasp-back"]
frames = int(sys.argv[4]) if len(sys.argv) > 4 else 60
hand, bundle = HandModel.load(TRACKING_HAND), load_bundle("fingerfist")
st = {"scale": {"hand_scale": "auto"}, **(settings or {})}
allk = []
for m in motions:
    t = time.time()
    rows = experiment_realistic(hand, bundle, scenes={"+forearm+torso": "forearm,torso"}, motion=m, frames=frames, settings=st)
    for r in rows:
        allk.append(r["keypoint_mm"])
        print(f"{label:10s} {m:11s} {r['sensor']:9s} x{r['scale']:<4g} kp {r['keypoint_mm']:6.1f} mm  post {r['posture_deg']:5.1f}  first {r['first_frame_mm']:6.1f}  lost {100*r['lost']:3.0f}%  fps {r['fps']:6.1f}  scale {r['scale_found']:.3f}", flush=True)
    print(f"# {m} {time.time()-t:.0f}s", flush=True)
print(f"{label} mean keypoint mm over runs {np.nanmean(allk):.1f}, worst {np.nanmax(allk):.1f}")
