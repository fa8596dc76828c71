"""Regenerate models/hands/default.yaml from htrack's default.calib (provenance of the shipped file).

Usage: python tools/make_default_hand.py ../shared/data/htrack_schroeder/default.calib models/hands/default.yaml

Facts used (../shared/data/htrack_schroeder/FORMAT.md): the 16 numbers of a joint are a column-major
4x4 in unscaled millimetres; the `scale` joint (0.811646) is folded into every translation and radius,
and the result is written in metres. Radius rows are indexed by segment in file order.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import yaml

FINGERS = ["thumb", "index", "middle", "ring", "pinky"]
HTRACK = {"thumb": "HandThumb", "index": "HandIndex", "middle": "HandMiddle", "ring": "HandRing", "pinky": "HandPinky"}
# Active ("conservative") limits of the original tracker (FORMAT.md section 3), radians.
ABD_LIMITS = {"thumb": [-0.3, 0.3], "index": [-0.5, 0.4], "middle": [-0.3, 0.3], "ring": [-0.3, 0.3], "pinky": [-0.5, 0.3]}
FLEX_LIMITS = [-1.5, 0.1]


def main(calib: str, out: str) -> None:
    lines = Path(calib).read_text().splitlines()
    end = lines.index("end_of_skeleton")
    mats, parents, order = {}, {}, []
    for ln in lines[:end]:
        f = ln.split()
        name, parent, v = f[0], f[1], np.array([float(x) for x in f[2:18]])
        mats[name] = v.reshape(4, 4).T  # column-major
        parents[name] = parent
        order.append(name)
    scale = mats["scale"][0, 0]
    radii = {}
    seg_joints = [n for n in order if n not in ("root", "pose", "scale") and any(parents[c] == n for c in order if c != n)]
    for ln in lines[end + 1:]:
        f = ln.split()
        if len(f) == 5:
            radii[seg_joints[int(f[0])]] = [float(x) for x in f[1:]]
    mm = float(scale) / 1000.0  # unscaled file units -> metres

    def rest(name):
        m = mats[name]
        return {"translation": [round(float(x) * mm, 12) for x in m[:3, 3]],
                "rotation": [[round(float(x), 9) for x in row] for row in m[:3, :3]]}

    joints = [{"name": "wrist", "parent": None, "htrack": "Hand", "rest": rest("Hand"),
               "dofs": ["tx", "ty", "tz", "rx", "ry", "rz"]}]
    dofs = [{"name": n, "type": "translation", "axis": n[1], "limits": [-np.inf, np.inf]} for n in ("tx", "ty", "tz")]
    dofs += [{"name": n, "type": "rotation", "axis": n[1], "limits": [-np.inf, np.inf]} for n in ("rx", "ry", "rz")]
    segments = []
    palm_len_mm = np.mean([np.linalg.norm(mats[HTRACK[f] + "1"][:3, 3]) for f in FINGERS[1:]]) * scale - 11.122
    r = radii["Hand"]
    segments.append({"joint": "wrist", "shape": "slab", "length": round(float(palm_len_mm) / 1000.0, 9),
                     "half_width": [round(r[0] * mm, 9), round(r[1] * mm, 9)],
                     "half_thickness": round(r[2] * mm, 9)})
    for f in FINGERS:
        dofs.append({"name": f"{f}1_abd", "type": "rotation", "axis": "z", "limits": list(ABD_LIMITS[f])})
        for k in (1, 2, 3):
            dofs.append({"name": f"{f}{k}_flex", "type": "rotation", "axis": "x", "limits": list(FLEX_LIMITS)})
        for k in (1, 2, 3, 4):
            h = f"{HTRACK[f]}{k}"
            name = f"{f}{k}" if k < 4 else f"{f}_tip"
            parent = "wrist" if k == 1 else f"{f}{k - 1}"
            # Code fact (Skeleton::move): L = rest . Rx(flex) . Rz(abd) -> flexion first in the product.
            jd = [f"{f}1_flex", f"{f}1_abd"] if k == 1 else ([f"{f}{k}_flex"] if k < 4 else [])
            joints.append({"name": name, "parent": parent, "htrack": h, "rest": rest(h), "dofs": jd})
            if k < 4:
                child = f"{HTRACK[f]}{k + 1}"
                length = float(np.linalg.norm(mats[child][:3, 3])) * mm
                rr = radii[h]
                segments.append({"joint": name, "shape": "capsule", "length": round(length, 12),
                                 "radius": [round(rr[0] * mm, 9), round(rr[1] * mm, 9)]})
    doc = {
        "schema_version": 1,
        "name": "default",
        "description": "The hand skeleton of Schroeder et al. (ICRA 2014) as shipped in htrack's default.calib, "
                       "scale 0.811646 folded in, metres. Left hand: fingers along +y, palm faces -z, thumb on +x.",
        "provenance": {"source": "OpenGP/htrack tracker/Calibration/default.calib",
                       "commit": "7cfef0328f1a6bab2087c5b0f742618ac762a812", "license": "LGPL-3.0",
                       "scale_folded_in": float(scale),
                       "generator": "tools/make_default_hand.py"},
        "units": "m",
        "handedness": "left",
        "n_dofs": 26,
        "pose": {"joint": "wrist", "order": "T . Rx . Ry . Rz"},
        "joints": joints,
        "dofs": dofs,
        "segments": segments,
        "mesh": {"ring_vertices": 18, "cap_rings": 5, "axial_rings_per_cm": 3, "blend_length": 0.006},
    }
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=120)
    text = text.replace("-.inf", "-.inf")
    Path(out).write_text("# Generated by tools/make_default_hand.py from htrack's default.calib; see provenance.\n" + text)


if __name__ == "__main__":
    main(*sys.argv[1:3])
