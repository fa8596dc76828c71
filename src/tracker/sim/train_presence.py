"""Training and held-out evaluation of the hand-presence CNN (:mod:`tracker.hand_presence`).

Is the region the tracker segmented a hand? The keypoint CNN was trained on hands only, so its
confidence says how sure its keypoints are, not whether a hand is there (on held-out whole frames its
mean confidence told the segmentation's hand regions from its other regions at an ROC AUC of 0.945:
at 99 % of hands kept it turned away 42 % of the rest). This network is trained for that question on
the same crops (the keypoint CNN's 64 × 64 input, :func:`tracker.keypoint_cnn.crop_image`), drawn from
whole rendered frames (:func:`tracker.sim.dataset.draw_scene` with the frame as the window):

- **hands**: the true hand pixels' box, jittered as a segmentation errs (size ±15 %, centre ±10 %,
  depth origin ±1 cm), and the box of the tracker's own segmentation (:func:`tracker.observe.observe`)
  where it holds at least half the hand and the hand is at least 30 % of it;
- **not hands**: the segmentation's box where at most 10 % of it is hand (it took the forearm, the
  torso, the table's edge or the object), and boxes of a hand's size (at that depth) on random
  surface pixels that are not hand (at most 3 % hand pixels in the box), and boxes of a hand's size or
  smaller beside the hand (``near``: centred on a non-hand pixel within a hand's extent of the hand, at
  most 10 % hand pixels; mostly the forearm's piece next to the wrist, which a segmentation cut by its
  window keeps and 1.1.0 called a hand at up to 0.93); and, on a share of frames
  (``PresenceSettings.p_hand_less``), frames without the hand (:func:`hand_less_scene`: a torso, a
  table and an object of any size from 2 to 24 cm where the hand would be), the segmentation's box and
  random boxes on them: what the tracker segments when no hand is in view.

Held-out frames are drawn with seed ``S + HELDOUT_SEED_OFFSET``. :func:`build` trains (PyTorch, the
``[train]`` extra), exports to ONNX, checks the export against torch, evaluates the exported network
on the held-out frames, on the labelled SR305 stills (hands; evaluation only) and on the real
hand-less recordings in ``../shared/data/sensor_recordings`` (evaluation only), and writes the sealed
model.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from handmodel import HandModel

from ..detector import OTHER
from ..errors import TrackerError
from ..hand_presence import BOX_SIDE_M, PRESENCE_FORMAT, PRESENCE_NAME, PresenceCNN, presence_input
from ..io.cameras import Camera
from ..keypoint_cnn import BOX_GROW, DEPTH_RANGE_M, INPUT_SIDE, hand_box, save_cnn
from .clutter import Clutter
from .dataset import Crop, DataRecipe, draw_scene
from .noise import NoiseModel
from .render import DepthRenderer
from .train_cnn import (down_block, export_onnx, in_chunks, jittered, model_output, require_torch, train,
                        training_record)
from .train_detector import HELDOUT_SEED_OFFSET, _r

#: A hand's extent (m) at size 1 from wrist to the middle fingertip, open: the random boxes' size.
HAND_EXTENT_M = 0.19


@dataclass(frozen=True)
class PresenceSettings:
    """What :func:`fit` does (every field goes into the manifest).

    Parameters
    ----------
    n_scenes : whole frames drawn for training
    epochs, batch, lr, weight_decay : AdamW with a one-cycle schedule over all steps
    threads : torch's intra-op threads
    jitters : jittered true-box crops per scene
    random_boxes : boxes on random non-hand surface per scene, each ``random_size`` (log-uniform) × a
        hand's box at that depth (a segmentation's region of something else has any size)
    size_jitter, shift_jitter, median_jitter_m : the true box's jitter (as the keypoint CNN's training)
    p_hand_less : the share of frames drawn without the hand (:func:`hand_less_scene`; 1.0.0 had none)
    near_boxes : boxes beside the hand per scene (none before 1.2.0), centred on a non-hand pixel within
        ``near_reach`` × a hand's extent (image distance at the hand's depth) of a hand pixel, each
        ``near_size`` (log-uniform) × a hand's box, labelled no hand where at most ``near_share`` of it is hand
    """

    n_scenes: int = 2000
    epochs: int = 12
    batch: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    threads: int = 1
    jitters: int = 1
    random_boxes: int = 3
    random_size: tuple = (0.4, 3.0)
    size_jitter: float = 0.15
    shift_jitter: float = 0.10
    median_jitter_m: float = 0.01
    p_hand_less: float = 0.25
    near_boxes: int = 2
    near_reach: float = 1.0
    near_size: tuple = (0.3, 1.2)
    near_share: float = 0.10

    def to_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- crops
def scene_camera(crop) -> Camera:
    """The whole frame's camera of a scene drawn with the frame as its window."""
    h, w = crop.depth.shape
    fx, fy, cx, cy = map(float, crop.camera)
    return Camera(w, h, fx, fy, cx, cy, 0.001, "uint16", "frame")


def _box_share(mask, box) -> tuple[float, int]:
    """The share of the box's pixels in ``mask``, and the box's pixel count (inside the image)."""
    cu, cv, size, _ = box
    h, w = mask.shape
    c0, c1 = int(max(0, np.floor(cu - size / 2))), int(min(w, np.ceil(cu + size / 2)))
    r0, r1 = int(max(0, np.floor(cv - size / 2))), int(min(h, np.ceil(cv + size / 2)))
    n = max(0, c1 - c0) * max(0, r1 - r0)
    return (float(mask[r0:r1, c0:c1].sum()) / n if n else 0.0), n


def segmented_label(mask, hand) -> int | None:
    """1 when the segmentation holds at least half the hand and the hand is at least 30 % of it, 0 when
    at most 10 % of it is hand, None between (ambiguous, left out)."""
    both = int((mask & hand).sum())
    if mask.sum() == 0:
        return None
    if both >= 0.5 * max(int(hand.sum()), 1) and both >= 0.3 * mask.sum():
        return 1
    return 0 if both <= 0.1 * mask.sum() else None


def scene_crops(crop, rng, st: PresenceSettings, *, segment=True) -> tuple[list, list, list]:
    """Inputs ``(2, 64, 64)`` (:func:`tracker.hand_presence.presence_input`), labels (1 hand, 0 not) and
    kinds (``true``, ``segmented``, ``random``, ``near``) of one whole-frame scene."""
    from ..observe import observe

    depth = crop.depth
    ok = np.isfinite(depth) & (depth > 0)
    hand = (crop.parts >= 0) & (crop.parts < OTHER) & ok
    mirror = bool(crop.mirror < 0)
    fx = float(crop.camera[0])
    X, y, kind = [], [], []
    box = hand_box(depth, hand)
    if box is not None:
        for _ in range(st.jitters):
            X.append(presence_input(depth, jittered(box, rng, st), mirror, fx))
            y.append(1)
            kind.append("true")
    if segment:
        mask = observe(depth, scene_camera(crop)).mask
        sbox = hand_box(depth, mask)
        lab = None if sbox is None else segmented_label(mask, hand)
        if lab is not None:
            X.append(presence_input(depth, sbox, mirror, fx))
            y.append(lab)
            kind.append("segmented")
    other = np.flatnonzero((ok & ~hand).ravel())
    for k, boxes in (("random", boxes_on(other, st.random_boxes, st.random_size, 0.03, depth, hand, fx, rng)),
                     ("near", near_boxes(depth, ok, hand, fx, rng, st) if st.near_boxes and hand.any() else [])):
        X += boxes
        y += [0] * len(boxes)
        kind += [k] * len(boxes)
    return X, y, kind


def boxes_on(pixels, n, size_range, max_share, depth, hand, fx: float, rng) -> list:
    """Inputs of up to ``n`` no-hand boxes, each centred on one of ``pixels`` (flat indices) drawn at random,
    ``size_range`` (log-uniform) × a hand's box at that pixel's depth, kept where at most ``max_share`` of
    it is hand (``hand``), mirrored at random (a non-hand has no side)."""
    out = []
    for _ in range(n if len(pixels) else 0):
        r, c = divmod(int(pixels[rng.integers(len(pixels))]), depth.shape[1])
        z = float(depth[r, c])
        size = BOX_GROW * HAND_EXTENT_M * np.exp(rng.uniform(*np.log(size_range))) * fx / z + 2.0
        b = (float(c), float(r), size, z)
        if _box_share(hand, b)[0] <= max_share:
            out.append(presence_input(depth, b, bool(rng.random() < 0.5), fx))
    return out


def near_boxes(depth, ok, hand, fx: float, rng, st: PresenceSettings) -> list:
    """Inputs of up to ``st.near_boxes`` boxes beside the hand that are not a hand (at most
    ``st.near_share`` hand pixels): what a segmentation cut short by its window holds when it kept the
    forearm's piece by the wrist, or an object or table edge touching the hand."""
    from scipy.ndimage import distance_transform_edt

    z_hand = float(np.median(depth[hand]))
    reach = st.near_reach * HAND_EXTENT_M * fx / z_hand
    near = np.flatnonzero((ok & ~hand & (distance_transform_edt(~hand) <= reach)).ravel())
    return boxes_on(near, st.near_boxes, st.near_size, st.near_share, depth, hand, fx, rng)


def hand_less_scene(recipe: DataRecipe, rng):
    """A whole frame as :func:`tracker.sim.dataset.draw_scene` draws one (sensor, camera, distance, noise),
    with no hand (and so no forearm) in view: a torso and a table as the recipe draws them and always an
    object, a box or a cylinder of half-extents 1–12 cm, at the place and depth the hand would be; every
    pixel's part label is "other"."""
    from .dataset import SENSORS, _pick

    sensor = _pick(recipe.sensors, rng)
    cam, noise_name = SENSORS.get(sensor, SENSORS["kinect1"])
    z = float(rng.uniform(*recipe.distance_m))
    u, v = rng.uniform(0.15, 0.85) * cam.width, rng.uniform(0.15, 0.85) * cam.height
    centre = np.array([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z])
    clutter = Clutter(forearm=False, torso=bool(rng.random() < recipe.p_torso),
                      torso_gap_m=float(rng.uniform(0.05, 0.30)),
                      torso_offset_m=(float(rng.uniform(-0.1, 0.1)), float(rng.uniform(0.0, 0.2))),
                      table=bool(rng.random() < recipe.p_table), table_view_deg=float(rng.uniform(15, 90)),
                      table_gap_m=float(rng.uniform(0.04, 0.15)), object="box" if rng.random() < 0.5 else "cylinder",
                      object_offset_m=(0.0, 0.0, 0.0),
                      object_size_m=tuple(float(x) for x in np.exp(rng.uniform(np.log(0.01), np.log(0.12), 3))))
    hand = HandModel.load(recipe.hand_model)
    theta = np.zeros(hand.n_dofs)
    theta[:3] = centre + np.array([50.0, 0.0, 0.0])  # the hand far out of view; the clutter stays
    r = DepthRenderer(hand, cam).render(theta, labels=False, clutter=clutter.fixed(centre), incidence=True,
                                        reflectance=True)
    nm = NoiseModel.preset("none" if sensor == "none" else noise_name)
    depth = nm.apply(r.depth, cam, rng, r.cos_incidence, r.reflectance).astype(np.float32)
    parts = np.where(np.isfinite(depth), OTHER, -1).astype(np.int8)
    return Crop(depth, parts, np.array([cam.fx, cam.fy, cam.cx, cam.cy]), np.full((21, 2), np.nan),
                np.full(21, np.nan), 1.0 if rng.random() < 0.5 else -1.0, {"sensor": sensor, "hand_less": True})


def _draw(recipe_dict: dict, st_dict: dict, seed: int, indices) -> tuple:
    recipe, st = DataRecipe(**recipe_dict), PresenceSettings(**st_dict)
    X, y, kind = [], [], []
    for i in indices:
        rng = np.random.default_rng([seed, i])
        # a frame's kind is drawn from its own generator, so that p_hand_less 0 draws every frame as before
        empty = st.p_hand_less > 0 and np.random.default_rng([seed, i, 7]).random() < st.p_hand_less
        a, b, k = scene_crops(hand_less_scene(recipe, rng) if empty else draw_scene(recipe, rng), rng, st)
        X += a
        y += b
        kind += k
    return X, y, kind


def draw_presence(recipe: DataRecipe, st: PresenceSettings, seed: int, n: int, jobs: int = 1) -> tuple:
    """``(X (N, 2, 64, 64) float32, y (N,) uint8, kinds)`` of scenes ``(seed, 0…n−1)`` drawn with the whole
    frame as the window, by ``jobs`` processes."""
    whole = replace(recipe, window_m=100.0)
    parts = in_chunks(_draw, (whole.to_dict(), st.to_dict(), seed), n, 50, jobs, 100)
    X = [x for p in parts for x in p[0]]
    y = [v for p in parts for v in p[1]]
    kind = [k for p in parts for k in p[2]]
    return (np.stack(X).astype(np.float32) if X else np.zeros((0, 2, INPUT_SIDE, INPUT_SIDE), np.float32),
            np.asarray(y, np.uint8), kind)


# ----------------------------------------------------------------------------- the network
def build_net():
    """The network (a ``torch.nn.Module``): input ``(B, 2, 64, 64)``; output the probability that the
    crop is a hand ``(B,)`` (a sigmoid on one logit; :meth:`forward` with ``logits=True`` gives the logit)."""
    require_torch()
    from torch import nn

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.features = nn.Sequential(down_block(2, 16), down_block(16, 32), down_block(32, 48),
                                          down_block(48, 64), nn.AdaptiveAvgPool2d(1), nn.Flatten())
            self.out = nn.Linear(64, 1)

        def forward(self, x, logits: bool = False):
            z = self.out(self.features(x))[:, 0]
            return z if logits else z.sigmoid()

    return Net()


class TorchPresence:
    """A torch network behind :class:`tracker.hand_presence.PresenceCNN`'s ``run`` (before export)."""

    def __init__(self, net):
        self.net = net

    def run(self, images):
        torch = require_torch()
        self.net.eval()
        with torch.no_grad():
            return self.net(torch.from_numpy(np.ascontiguousarray(np.asarray(images, np.float32)))).numpy()


def fit(X, y, st: PresenceSettings, seed: int, progress=None):
    """The trained network and its loss per epoch (:func:`tracker.sim.train_cnn.train`); each batch mirrored
    left–right at random (a hand's side is the input's mirroring; a non-hand has none)."""
    torch = require_torch()
    # the classes weighed equally whatever their counts
    w_pos = torch.tensor(float((y == 0).sum()) / max(float((y == 1).sum()), 1.0))

    def batch_loss(net, sel, rng):
        xb = X[sel].copy()
        flip = rng.random(len(sel)) < 0.5
        xb[flip] = xb[flip, :, :, ::-1]
        z = net(torch.from_numpy(xb), logits=True)
        return torch.nn.functional.binary_cross_entropy_with_logits(z, torch.from_numpy(y[sel].astype(np.float32)),
                                                                    pos_weight=w_pos)

    return train(build_net, batch_loss, len(X), st, seed, progress)


# ----------------------------------------------------------------------------- evaluation
def roc_auc(p, y) -> float:
    """The ROC AUC of scores ``p`` for labels ``y`` (the Mann–Whitney statistic, ties half)."""
    from scipy.stats import rankdata

    p, y = np.asarray(p, float), np.asarray(y, bool)
    n1, n0 = int(y.sum()), int((~y).sum())
    if not n1 or not n0:
        return float("nan")
    r = rankdata(p)
    return float((r[y].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def evaluate(model, X, y, kind) -> dict:
    """Held-out figures: ROC AUC over all crops and over the segmentation's boxes alone (what the tracker
    asks), and at the thresholds 0.5 and the tracker's (``start.presence_below``): the share of hands
    kept and of the rest turned away, per kind."""
    from ..settings import StartSettings

    p = model.run(X) if len(X) else np.zeros(0)
    kind = np.asarray(kind)
    seg = kind == "segmented"
    out = {"crops": int(len(y)), "hands": int((y == 1).sum()), "not_hands": int((y == 0).sum()),
           "auc": _r(roc_auc(p, y), 4), "auc_segmented": _r(roc_auc(p[seg], y[seg]), 4)}
    for t in (0.5, StartSettings().presence_below):
        row = {}
        for k in ("true", "segmented", "random", "near"):
            sel = kind == k
            if (sel & (y == 1)).any():
                row[f"{k}_hands_kept"] = _r(np.mean(p[sel & (y == 1)] >= t), 4)
            if (sel & (y == 0)).any():
                row[f"{k}_not_hands_turned_away"] = _r(np.mean(p[sel & (y == 0)] < t), 4)
        out[f"at_{t:g}"] = row
    return out


def evaluate_real(model, data_dir) -> dict:
    """The hand probability of the tracker's segmentation on real frames (evaluation only): the labelled
    SR305 stills (every one a right hand) and the hand-less real recordings beside them
    (``sensor_recordings``: a D435 bag, an Azure Kinect clip)."""
    from ..hand_presence import hand_probability
    from ..io.cameras import preset
    from ..io.images import read_depth_units, units_to_metres
    from ..io.recording import Recording
    from ..observe import observe
    from .real_frames import read_labels

    root = Path(data_dir)
    cam = preset("sr305")
    stills = []
    for name in sorted(k for k, v in read_labels(root).items() if isinstance(v, dict) and "wrist" in v):
        depth = units_to_metres(read_depth_units(root / f"{name}.png", cam), cam)
        stills.append(round(hand_probability(depth, cam, observe(depth, cam).mask, "right", model=model), 4))
    empty = []
    rec_dir = root.parent / "sensor_recordings"
    for f in ("librealsense_single_depth_color_640x480.bag", "azure_kinect_recording.mkv"):
        if not (rec_dir / f).exists():
            continue
        try:
            rec = Recording.open(rec_dir / f, handedness="right")
        except TrackerError:  # the recordings extra is not installed
            continue
        for frame in rec:
            mask = observe(frame.depth, rec.camera, color=frame.color).mask
            empty.append(round(hand_probability(frame.depth, rec.camera, mask, "right", model=model), 4))
    return {"stills": stills, "stills_min": min(stills) if stills else None, "hand_less_frames": empty}


def build(output, *, seed: int = 0, recipe: DataRecipe | None = None, settings: PresenceSettings | None = None,
          heldout: int = 400, real_data=None, version: str = "1.0.0", command: str = "", jobs: int = 2,
          progress=None, overwrite: bool = False) -> tuple[Path, dict]:
    """Train, export, evaluate the exported network and write ``output/hand-presence-cnn-<version>``
    (``.onnx`` and ``.json``); returns the manifest's path and the manifest."""
    require_torch()
    recipe = recipe or DataRecipe()
    st = settings or PresenceSettings()
    say = progress or (lambda msg: None)
    out = model_output(output, PRESENCE_NAME, version, overwrite)
    t0 = time.perf_counter()
    say(f"drawing {st.n_scenes} training frames and {heldout} held-out ones ({jobs} processes)")
    X, y, _ = draw_presence(recipe, st, seed, st.n_scenes, jobs)
    Xh, yh, kh = draw_presence(recipe, st, seed + HELDOUT_SEED_OFFSET, heldout, jobs)
    t_draw = time.perf_counter() - t0
    say(f"{len(y)} training crops ({int(y.sum())} hands), {len(yh)} held-out ({int(yh.sum())} hands)")
    data_hash = hashlib.sha256(X.tobytes() + y.tobytes()).hexdigest()
    net, losses = fit(X, y, st, seed, progress)
    t_fit = time.perf_counter() - t0 - t_draw
    onnx_bytes = export_onnx(net, output_names=("presence",), channels=2)
    model = PresenceCNN(onnx_bytes, {})
    probe = Xh[:8] if len(Xh) else np.zeros((1, 2, INPUT_SIDE, INPUT_SIDE), np.float32)
    if not np.allclose(model.run(probe), TorchPresence(net).run(probe), atol=1e-4):
        raise TrackerError("onnx", "the exported network does not give torch's output")
    say(f"evaluating the exported network on {len(yh)} held-out crops")
    metrics = {"heldout": evaluate(model, Xh, yh, kh)}
    if real_data is not None:
        say("evaluating on the labelled SR305 stills and the hand-less real recordings")
        metrics["real"] = evaluate_real(model, real_data)
    manifest = {"name": PRESENCE_NAME, "version": version, "command": command, "seed": seed, "family": "presence",
                "recipe": recipe.to_dict(), "settings": st.to_dict(), "input_side": INPUT_SIDE,
                "box_grow": BOX_GROW, "depth_range_m": DEPTH_RANGE_M, "box_side_m": BOX_SIDE_M,
                "heldout_seed": seed + HELDOUT_SEED_OFFSET,
                "training": training_record(net, losses, {"draw": t_draw, "fit": t_fit,
                                                          "total": time.perf_counter() - t0},
                                            crops=int(len(y)), hands=int(y.sum()), samples_sha256=data_hash),
                "metrics": metrics, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    path = save_cnn(out, onnx_bytes, manifest, overwrite=overwrite, fmt=PRESENCE_FORMAT)
    return path, manifest
