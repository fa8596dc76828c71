"""Every labelled real SR305 frame (../shared/data/realsense_sr305_lada, hand masks and wrist /
fingertip pixels made by eye) tracked as a user would: the camera preset, the right hand, the hand
size calibrated on each recording's first labelled frame in recording order (``hand_scale="auto"``)
and reused for its other frames, everything else default — the tracker's hand is the human one
(:data:`tracker.TRACKING_HAND`, the finger bases on the metacarpal arc, :mod:`handmodel.anthropometry`).
The keypoint-in-mask floor is the issue's; the tip and wrist floors are what the tracker reaches today
(the issue's: tips ≤ 15 px and wrist ≤ 20 px on every frame: all 19 frames meet them, on every
processor); they catch a fit on the body, an upside-down hand, a hand turned over (palm and back swapped,
the thumb folded into the palm) or a lost wrist. The labelled wrist (the middle of the skin crease, where
the labelled hand mask ends) is compared with where the model hand ends (:meth:`HandModel.wrist_crease`,
~11 mm past the wrist joint on the hand's axis at these sizes).

Measured (every processor, sizes 1.254 and 1.290): 19 frames within every floor, all 95 tips within 15 px,
median 5.2 px, worst 13.4 px; the wrist within 20 px on every frame (median 6.3 px, worst 16.0). Until a
start's last fits held the wrist crease on the arm's centre line (the wrist-line pair,
``IcpSettings.wrist_line_weight``): 18 frames, median 4.9 px, worst 13.5, the wrist median 7.4 px and
230536_110's 21.1 px — the fitted crease lay 4–29 mm to the thumb's side of the line through the frame's
wrist cue on all 18 frames with a cue, the labelled creases within 3 mm of it on 16. (17 frames, 93 tips,
worst 20.8 px — 231615_140's thumb lying across the palm, its end phalanx without a data point — until a
start's unseen joints were pulled all the way to the synergies' conditional mean, ``unseen_prior``.) On the paper's hand, whose four finger bases lie
on one line (``models/hands/default.yaml``), the same protocol gave 15 frames, 92 tips, median 5.0 px,
worst 24.9 px (230536_30's little finger curled into the palm on an open hand: a little finger that
starts 9 mm too far from the wrist is too long for the hand seen). The frames are chaotic in the size
(one still decides between near-equal fits), so the two hands were also compared with both sizes × 0.98
… 1.02 (9 factors): 16.4 frames within every floor on average (15–18) against 14.4 (12–17), 93.3 tips
against 90.8. With a start's unseen joints pulled (same 9 factors, every frame's size fixed): 17.1 frames
(16–18) against 16.4 (15–18), 94.0 tips against 93.3, median 5.1 px against 4.9. With the wrist line as well:
17.9 frames (17–19), 93.9 tips, median 5.1 px, the wrist within 20 px on every frame of every run (worst
19.4 px; 20.6–22.2 px on 230536_110 at 7 of the 9 factors before).

The fits are the same on every processor (:func:`test_the_fits_are_the_same_on_every_processor`). They were not
until :mod:`handmodel.libm`: on AVX-512 numpy runs its own ``exp``, ``log``, ``arccos``, ``arctan2``..., which
differ from the C library's (numpy's loops elsewhere) in the last bits, and numpy's ``arccos`` of the palm mesh's
sphere samples changed the mesh; the size search followed and the frames followed the size. Numba's target,
scipy and OpenBLAS change nothing. The fits are the same whatever ran before them in the process
(:mod:`tests.tracker.test_init_reproducible`), so the floors need no margin for the suite; their margin is
for small changes of the fit (the 9 resized runs above: 17–19 frames, 93–95 tips, worst 14.5–44.7 px)."""
from __future__ import annotations


import json
import os
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image
from scipy import ndimage

from tests.conftest import shared
from tracker.sim.real_frames import experiment_real_frames

TIPS = ("thumb", "index", "middle", "ring", "pinky")
pytestmark = pytest.mark.slow


#: numpy's AVX-512 loops switched off (numpy's own variable, read at import): numpy then computes as on a
#: processor without AVX-512 (its ``exp``, ``log``, ``arccos``... by the C library).
AVX2_PATH = {"NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL"}

_ROWS = """
import json, sys
from tracker.sim.real_frames import experiment_real_frames
rows = experiment_real_frames(sys.argv[1])
json.dump([{k: (r[k].tolist() if hasattr(r[k], "tolist") else r[k]) for k in ("name", "uv", "scale", "crease_uv")}
           for r in rows], sys.stdout)
"""


#: The frames :func:`test_the_fits_are_the_same_on_every_processor` tracks again: each recording's first
#: (where its size is calibrated, the step AVX-512's ``arccos`` once changed) and second labelled frame.
SAME_BITS_FRAMES = ("20210326-230536_30", "20210326-230536_50", "20210326-231615_0", "20210326-231615_20")


def _avx512_loops() -> bool:
    """Whether numpy runs its AVX-512 loops on this processor (else :data:`AVX2_PATH` changes nothing)."""
    from numpy._core._multiarray_umath import __cpu_features__

    return bool(__cpu_features__.get("X86_V4") or __cpu_features__.get("AVX512_SKX"))


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    # as a user tracks a recording: the size calibrated on its first frame (hand_scale="auto"), then
    # reused for its other frames (--hand-scale from the output header); the report's protocol
    root = shared("realsense_sr305_lada")
    overlays = tmp_path_factory.mktemp("overlays")
    rows = experiment_real_frames(root, overlay_dir=overlays)
    assert len(rows) == 19
    for r in rows:  # every overlay written and readable, at the frame's size
        assert np.asarray(Image.open(overlays / f"{r['name']}.png")).shape[1] == r["mask"].shape[1]
    return rows


@pytest.fixture(scope="module")
def fits(tracked):
    return {r["name"]: (r["labels"], r["mask"], r["uv"], r["names"], r["scale"], r["crease_uv"]) for r in tracked}


def test_the_fits_are_the_same_on_every_processor(tracked, tmp_path):
    """The same fits, to the last bit, with numpy's AVX-512 loops switched off (:data:`AVX2_PATH`, in a
    process of its own): an AVX-512 processor fits these frames as an AVX2 one does. Before
    :mod:`handmodel.libm` they did not: numpy's ``arccos`` of the palm mesh's sphere samples changed the
    mesh in the last bits, the size search followed (1.238 against 1.267 on 230536_30) and 18 of the 19
    frames met every floor on an AVX-512 EPYC, 15 on an AVX2 one. (Skipped where numpy has no AVX-512
    loops: the switch would change nothing.)

    The other process tracks :data:`SAME_BITS_FRAMES` (a folder of links to them and their labels), not
    all 19: each frame is tracked by a tracker of its own, so a frame's fit is the same in any selection
    that keeps its recording's first frame (the size is calibrated there); these hold both calibrations
    and a frame tracked on each size, and the whole run took ~30 s of the suite's time in that process."""
    if not _avx512_loops():
        pytest.skip("numpy runs no AVX-512 loops on this processor: nothing to switch off")
    root, some = shared("realsense_sr305_lada"), tmp_path / "some"
    (some / "labels").mkdir(parents=True)
    labels = json.loads((root / "labels" / "labels.json").read_text())
    (some / "labels" / "labels.json").write_text(json.dumps({n: labels[n] for n in SAME_BITS_FRAMES}))
    for n in SAME_BITS_FRAMES:
        (some / f"{n}.png").symlink_to(root / f"{n}.png")
        (some / "labels" / f"{n}_hand.png").symlink_to(root / "labels" / f"{n}_hand.png")
    out = subprocess.run([sys.executable, "-c", _ROWS, str(some)], capture_output=True,
                         text=True, env={**os.environ, **AVX2_PATH}, check=True)
    other = {r["name"]: r for r in json.loads(out.stdout)}
    assert sorted(other) == sorted(SAME_BITS_FRAMES)
    for r in tracked:
        if r["name"] not in other:
            continue
        o = other[r["name"]]
        assert o["scale"] == r["scale"], (r["name"], o["scale"], r["scale"])
        assert np.array_equal(np.asarray(o["uv"]), r["uv"]), r["name"]
        assert np.array_equal(np.asarray(o["crease_uv"]), r["crease_uv"]), r["name"]


def test_the_avx2_path_is_another_processors():
    """The switch does change numpy's results here (else the test above would compare a run with itself):
    numpy's ``exp`` and ``arccos`` differ in their last bits between the two paths (AVX-512 builds its own
    vector maths; sin, cos and sums agree)."""
    if not _avx512_loops():
        pytest.skip("numpy runs no AVX-512 loops on this processor")
    code = ("import numpy as np; x = np.random.default_rng(0).uniform(-10, 10, 10001); "
            "print(np.exp(x).tobytes().hex(), np.arccos(x / 10).tobytes().hex())")
    a = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    b = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                       env={**os.environ, **AVX2_PATH}).stdout
    assert a != b


def test_every_real_frame_fits_the_hand_not_the_body(fits):
    """≥ 90 % of the 21 projected keypoints inside the labelled hand mask dilated by 8 px on every
    frame (measured 0.90–1.00: 231615_140 at 19 of 21, its little finger straightened by the start's pull of its
    unseen end joint reaches past the tip; 1.00 before), and the size found is a hand's (this subject's hand is 1.2–1.5× the
    model; measured 1.254 and 1.290 on the two recordings)."""
    for name, (_, truth, uv, _, scale, _) in fits.items():
        near = ndimage.binary_dilation(truth, iterations=8)
        ui = np.clip(np.rint(uv).astype(int), 0, [truth.shape[1] - 1, truth.shape[0] - 1])
        inside = near[ui[:, 1], ui[:, 0]].mean()
        assert inside >= 0.90, f"{name}: only {inside:.0%} of the keypoints on the hand"
        assert 1.1 <= scale <= 1.8, f"{name}: hand size {scale:.2f}"


def test_no_real_frame_is_fitted_upside_down(fits):
    """The model hand's end (:meth:`HandModel.wrist_crease`) within 20 px of the labelled wrist crease on
    every frame, the issue's floor, and within 8 px in the median (measured: ≤ 16.0 px, median 6.3; 21.1 px
    on 230536_110 and median 7.4 before a start's crease was held on the arm's centre line; before the
    wrist cue one frame had it 125 px away, in the palm, the hand upside down), and the hand's axis (wrist
    → middle base) within 60° of the labelled wrist → middle tip."""
    errs = []
    for name, (lab, _, uv, names, _, crease) in fits.items():
        errs.append(float(np.hypot(*(crease - lab["wrist"]))))
        axis = uv[names.index("middle1")] - uv[0]
        want = np.asarray(lab["middle"], float) - lab["wrist"]
        cos = axis @ want / (np.linalg.norm(axis) * np.linalg.norm(want))
        assert cos >= np.cos(np.radians(60)), f"{name}: hand axis {np.degrees(np.arccos(cos)):.0f}° off"
    assert max(errs) <= 20 and np.median(errs) <= 8, np.round(errs, 1)


def test_no_open_hand_is_fitted_turned_over(fits):
    """The open and spread hands of recording 230536 (palm or back to the camera, every finger seen
    in the image): every tip within 30 px (measured ≤ 11.7 px; 24.9 px on the paper's hand, 230536_30's
    little finger curled on an open hand). Before the score measured each data point against the whole
    model (:func:`tracker.init.data_cost_mm`), five of its eight frames were fitted with the palm turned
    over — thumb folded into the palm, the model's index on the real thumb, 70–120 px at the thumb and pinky."""
    for name, (lab, _, uv, names, _, _) in fits.items():
        if name.startswith("20210326-230536"):
            e = [float(np.hypot(*(uv[names.index(t + "_tip")] - lab[t]))) for t in TIPS]
            assert max(e) <= 30, f"{name}: tips {np.round(e, 1)} px"


def test_real_frames_fingertips(fits):
    """Fingertips: at least 18 of the 19 frames have every labelled tip within 15 px of its model tip and the model
    hand's end within 20 px of the labelled wrist crease (the issue's floor for every frame), at least 94 of the
    95 labelled tips are within 15 px, the median tip error over all frames is ≤ 5.5 px, and no tip is more than
    45 px off on any frame. Measured (module note): 19 frames, 95 tips, median 5.2 px, worst 13.4 px
    (230536_110's wrist was 21.1 px until a start's crease was held on the arm's centre line). 231615_140 (thumb
    across the palm) was 20.8 px until a start's unseen joints were pulled all the way (its thumb's end phalanx
    has no data point; the search left it bent back 21°). The 45 px bound is for 231615_100's middle finger,
    pointing at the camera: at other sizes (× 0.995) the wrong fit wins there (41 px; it scores better, the
    search finds one or the other).

    What is left is the model's shape against this hand's: the fitted crease still lies on the thumb's side of
    the forearm's axis, which the labels follow (230536_110: the fit turns the palm in the image with every
    finger's abduction making up for it; the finger bases on the arc took it from 24 to 21 px, the wrist line to
    12 px); the thumb — its labelled tips lie a median 8 px beyond the model's along the last bone (the other
    fingers within ±4 px): the model's thumb phalanges are short (Buchholz et al. 1992 make them 1.28× the
    model's against its middle finger), but a thumb 1.28× long met the floors on fewer frames (15.2 of 19 over
    the 9 resized runs, median 4.0 px against 4.7): a longer thumb folded across the palm does not fit the blob
    the sensor sees there (231615_0's thumb 20–25 px)."""
    ok, tip_errs, worst = 0, [], 0.0
    for name, (lab, _, uv, names, _, crease) in fits.items():
        e = [float(np.hypot(*(uv[names.index(t + "_tip")] - lab[t]))) for t in TIPS]
        tip_errs += e
        worst = max(worst, max(e))
        assert max(e) <= 45, f"{name}: tips {np.round(e, 1)} px"
        ok += max(e) <= 15 and np.hypot(*(crease - lab["wrist"])) <= 20
    print(f"\nframes within every floor {ok}/19, tips within 15 px {np.sum(np.asarray(tip_errs) <= 15)}/95, "
          f"median {np.median(tip_errs):.1f} px, worst {worst:.1f} px")
    assert ok >= 18, ok
    assert np.sum(np.asarray(tip_errs) <= 15) >= 94, np.sum(np.asarray(tip_errs) <= 15)
    assert np.median(tip_errs) <= 5.5, np.median(tip_errs)
