"""Training and held-out evaluation of the keypoint CNN (:mod:`tracker.keypoint_cnn`), family (b).

The crops come from :mod:`tracker.sim.dataset` (seed ``S``; held-out crops seed
``S + HELDOUT_SEED_OFFSET``), drawn once and kept in memory (:class:`Sample`: the depth around the
hand, its true pixels' box, the keypoints). At run time the box comes from the tracker's
segmentation, not from the true pixels, so each training step draws the box anew around the true
pixels with the errors a segmentation makes (:func:`jitter_box`: size ±15 %, centre ±10 %, on 30 %
of steps stretched towards the forearm, the depth origin off by ~1 cm). Two heads on one backbone
(four strided conv blocks): ``regression`` (the keypoints' box coordinates and depth from the
pooled features) and ``heatmap`` (a 16×16 heatmap per keypoint from an upsampling path with skips,
its soft-argmax the keypoint, the heatmap-weighted mean of a depth map its depth; the heatmap's
spread its uncertainty). Both are trained with the same loss on the same coordinates.

:func:`build` trains, exports to ONNX (torch's exporter), evaluates the exported network
(onnxruntime, what ships) on held-out crops, on held-out whole frames through the tracker's own
segmentation (:func:`tracker.observe.observe`), on the labelled SR305 stills (never trained or tuned
on) and the start fitted to its keypoints, and writes the sealed model. :func:`compare_heads` is the
measurement behind the choice of head. Needs the ``[train]`` extra (torch is imported inside
functions only).
"""
from __future__ import annotations

import hashlib
import platform
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..detector import N_PARTS, OTHER
from ..errors import TrackerError
from ..keypoint_cnn import (BOX_GROW, CNN_NAME, DEPTH_RANGE_M, INPUT_SIDE, KeypointCNN, SPREAD_SCALE, Z_SCALE_M,
                            crop_image, detect, hand_box, save_cnn)
from .dataset import DataRecipe, draw_scene
from .train_detector import HELDOUT_SEED_OFFSET, evaluate_real

#: Fingertips in :data:`tracker.detector.PART_NAMES` order.
TIPS = (4, 8, 12, 16, 20)
HEATMAP_SIDE = 16


def require_torch():
    """torch, or a one-line error naming the extra."""
    try:
        import torch
    except ImportError:
        raise TrackerError("torch", "not installed: training the keypoint CNN needs it (pip install '.[train]')") from None
    return torch


@dataclass(frozen=True)
class CnnSettings:
    """What :func:`fit` does (every field goes into the model's manifest).

    Parameters
    ----------
    head : ``heatmap`` or ``regression``
    n_crops : training crops drawn
    epochs, batch, lr, weight_decay : AdamW with a cosine schedule over all steps
    threads : torch's intra-op threads
    jobs : processes drawing the crops
    size_jitter, shift_jitter : the training box's side × 1 ± this, its centre ± this × its side
    p_forearm, forearm_reach : the share of boxes stretched towards the forearm, and by how much
        (× the hand's extent), as a segmentation that keeps a stub of the arm
    median_jitter_m : the depth origin's error (SD)
    heatmap_weight : the heatmap head's second loss, the cross-entropy of each heatmap against a
        Gaussian of one cell at its keypoint (without it the heatmaps stay diffuse, and their
        spread says nothing of the error)
    """

    head: str = "heatmap"
    n_crops: int = 4000
    epochs: int = 16
    batch: int = 64
    lr: float = 2e-3
    weight_decay: float = 1e-4
    threads: int = 2
    jobs: int = 2
    size_jitter: float = 0.15
    shift_jitter: float = 0.10
    p_forearm: float = 0.3
    forearm_reach: tuple = (0.2, 0.8)
    median_jitter_m: float = 0.01
    heatmap_weight: float = 0.02

    def to_dict(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------- samples
@dataclass(frozen=True, eq=False)
class Sample:
    """A crop as the training keeps it: the depth around the hand (``float32``), the true hand
    pixels' bounding box ``(c0, c1, r0, r1)`` and :func:`tracker.keypoint_cnn.hand_box`, the
    keypoints (pixels and depth) and the intrinsics, all in the window's pixels."""

    depth: np.ndarray
    bbox: tuple
    box: tuple
    uv: np.ndarray
    z: np.ndarray
    camera: np.ndarray
    mirror: bool
    centroid: np.ndarray


def sample_of(crop) -> Sample | None:
    """The :class:`Sample` of a crop (None when its hand shows fewer pixels than the CNN needs)."""
    m = (crop.parts >= 0) & (crop.parts < OTHER) & np.isfinite(crop.depth)
    box = hand_box(crop.depth, m)
    if box is None:
        return None
    rows, cols = np.nonzero(m)
    ext = max(cols.max() - cols.min(), rows.max() - rows.min())
    # keep what any jittered box can reach: the forearm stretch, the grown and shifted side
    reach = int(np.ceil(2.2 * ext + 8))
    h, w = crop.depth.shape
    y0, y1 = max(0, int(box[1]) - reach), min(h, int(box[1]) + reach + 1)
    x0, x1 = max(0, int(box[0]) - reach), min(w, int(box[0]) + reach + 1)
    fx, fy, cx, cy = map(float, crop.camera)
    z = crop.depth[rows, cols].astype(float)
    centroid = np.stack([(cols - cx) * z / fx, (rows - cy) * z / fy, z], axis=1).mean(axis=0)
    return Sample(np.ascontiguousarray(crop.depth[y0:y1, x0:x1], np.float32),
                  (cols.min() - x0, cols.max() - x0, rows.min() - y0, rows.max() - y0),
                  (box[0] - x0, box[1] - y0, box[2], box[3]), crop.keypoints_uv - [x0, y0], crop.keypoints_z.copy(),
                  np.array([fx, fy, cx - x0, cy - y0]), bool(crop.mirror < 0), centroid)


def _draw(recipe_dict: dict, seed: int, indices) -> list:
    recipe = DataRecipe(**recipe_dict)
    return [sample_of(draw_scene(recipe, np.random.default_rng([seed, i]))) for i in indices]


def in_chunks(draw, args: tuple, n: int, chunk: int, jobs: int, serial_below: int) -> list:
    """``[draw(*args, indices) for each chunk of 0…n−1]``, in order: in this process when ``jobs`` ≤ 1 or
    ``n`` < ``serial_below``, else in ``jobs`` spawned processes (``draw`` a module-level function)."""
    chunks = [range(a, min(a + chunk, n)) for a in range(0, n, chunk)]
    if jobs <= 1 or n < serial_below:
        return [draw(*args, c) for c in chunks]
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as ex:
        return list(ex.map(draw, *([a] * len(chunks) for a in args), chunks))


def draw_samples(recipe: DataRecipe, seed: int, n: int, jobs: int = 1) -> list:
    """Samples of crops ``(seed, 0…n−1)`` (:func:`tracker.sim.dataset.draw_crops`'s scenes), drawn by
    ``jobs`` processes; crops whose hand shows too few pixels are left out."""
    parts = in_chunks(_draw, (recipe.to_dict(), seed), n, 100, jobs, 200)
    return [s for p in parts for s in p if s is not None]


def jittered(box, rng, st) -> tuple:
    """``box`` (:func:`tracker.keypoint_cnn.hand_box`'s ``(cu, cv, size, median_m)``) with a segmentation's
    errors: the side × 1 ± ``st.size_jitter``, the centre ± ``st.shift_jitter`` × the side, the depth origin
    ± ``st.median_jitter_m`` (SD) — both networks' training boxes."""
    cu, cv, size, med = box
    size = size * rng.uniform(1 - st.size_jitter, 1 + st.size_jitter)
    return (cu + rng.uniform(-st.shift_jitter, st.shift_jitter) * size,
            cv + rng.uniform(-st.shift_jitter, st.shift_jitter) * size, size, med + rng.normal(0.0, st.median_jitter_m))


def jitter_box(s: Sample, rng, st: CnnSettings) -> tuple:
    """A box as a segmentation might give it (see :class:`CnnSettings`) around the true pixels: stretched
    towards the forearm on a share of them, then :func:`jittered`."""
    c0, c1, r0, r1 = map(float, s.bbox)
    if rng.random() < st.p_forearm:
        e = s.uv[0] - s.uv[9]  # middle finger base → wrist: towards the forearm
        e = e / (np.linalg.norm(e) + 1e-9) * rng.uniform(*st.forearm_reach) * max(c1 - c0, r1 - r0)
        c0, c1 = min(c0, c0 + e[0]), max(c1, c1 + e[0])
        r0, r1 = min(r0, r0 + e[1]), max(r1, r1 + e[1])
    return jittered(((c0 + c1) / 2, (r0 + r1) / 2, BOX_GROW * max(c1 - c0, r1 - r0) + 2.0, s.box[3]), rng, st)


def target(s: Sample, box) -> np.ndarray:
    """``(21, 3)``: the keypoints in the box (0–1, mirrored for a right hand) and their depth
    relative to the box's origin in :data:`tracker.keypoint_cnn.Z_SCALE_M` (what the network gives)."""
    cu, cv, size, med = box
    x = (s.uv[:, 0] - (cu - size / 2)) / size
    t = np.stack([1.0 - x if s.mirror else x, (s.uv[:, 1] - (cv - size / 2)) / size, (s.z - med) / Z_SCALE_M], axis=1)
    return t.astype(np.float32)


def batch_arrays(samples, boxes):
    """Inputs ``(B, side, side)`` and targets ``(B, 21, 3)``."""
    X = np.stack([crop_image(s.depth, b, s.mirror) for s, b in zip(samples, boxes)])
    return X, np.stack([target(s, b) for s, b in zip(samples, boxes)])


# ----------------------------------------------------------------------------- the network
def down_block(i, o):
    """Two 3×3 convolutions (the second of stride 2), each with batch norm and ReLU: ``i`` → ``o`` channels,
    the side halved (both networks' backbone)."""
    from torch import nn

    return nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.BatchNorm2d(o), nn.ReLU(),
                         nn.Conv2d(o, o, 3, stride=2, padding=1), nn.BatchNorm2d(o), nn.ReLU())


def build_net(head: str):
    """The network (a ``torch.nn.Module``): input ``(B, 1, 64, 64)``; outputs keypoints ``(B, 21, 3)``
    and spread ``(B, 21)``."""
    torch = require_torch()
    from torch import nn

    if head not in ("heatmap", "regression"):
        raise TrackerError("head", f"must be heatmap or regression, got {head!r}")

    block = down_block

    def conv(i, o):
        return nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.BatchNorm2d(o), nn.ReLU())

    g = (torch.arange(HEATMAP_SIDE, dtype=torch.float32) + 0.5) / HEATMAP_SIDE

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            self.b1, self.b2, self.b3, self.b4 = block(1, 24), block(24, 48), block(48, 96), block(96, 128)
            if head == "regression":
                self.fc = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(128, 256), nn.ReLU(),
                                        nn.Linear(256, 3 * N_PARTS))
            else:
                self.up = nn.Upsample(scale_factor=2.0, mode="nearest")
                self.u3, self.u2 = conv(128 + 96, 96), conv(96 + 48, 64)
                self.out = nn.Conv2d(64, 2 * N_PARTS, 1)
                self.register_buffer("gx", g.repeat(HEATMAP_SIDE))  # cell (r, c) at index r·16 + c
                self.register_buffer("gy", g.repeat_interleave(HEATMAP_SIDE))

        def forward(self, x, maps: bool = False):
            f2 = self.b2(self.b1(x))
            f3 = self.b3(f2)
            f4 = self.b4(f3)
            if head == "regression":
                kp = self.fc(f4).reshape(-1, N_PARTS, 3)
                return (kp, torch.zeros_like(kp[:, :, 0])) + ((None,) if maps else ())
            h = self.u2(torch.cat([self.up(self.u3(torch.cat([self.up(f4), f3], 1))), f2], 1))
            o = self.out(h).flatten(2)  # (B, 42, 256)
            p = torch.softmax(o[:, :N_PARTS], dim=2)
            x_ = (p * self.gx).sum(2)
            y_ = (p * self.gy).sum(2)
            z_ = (p * o[:, N_PARTS:]).sum(2)
            var = (p * ((self.gx - x_[:, :, None]) ** 2 + (self.gy - y_[:, :, None]) ** 2)).sum(2)
            out = torch.stack([x_, y_, z_], 2), torch.sqrt(var + 1e-8)
            return out + (torch.log_softmax(o[:, :N_PARTS], dim=2),) if maps else out

    return Net()


class TorchRunner:
    """A torch network behind :class:`tracker.keypoint_cnn.KeypointCNN`'s ``run`` (to evaluate it
    before export)."""

    def __init__(self, net):
        self.net = net

    def run(self, images):
        torch = require_torch()
        self.net.eval()
        with torch.no_grad():
            kp, spread = self.net(torch.from_numpy(np.ascontiguousarray(np.asarray(images, np.float32)[:, None])))
        return kp.numpy(), spread.numpy()


def heatmap_loss(logp, Y, gx, gy, sigma: float = 1.0 / HEATMAP_SIDE):
    """Mean cross-entropy of the heatmaps ``logp`` (B, 21, cells; log-probabilities) against a
    Gaussian of ``sigma`` (box units) at each keypoint ``Y[..., :2]``, normalised over the cells."""
    import torch

    d2 = (gx - Y[:, :, :1]) ** 2 + (gy - Y[:, :, 1:2]) ** 2
    t = torch.softmax(-d2 / (2 * sigma * sigma), dim=2)
    return -(t * logp).sum(2).mean()


def train(make_net, batch_loss, n: int, st, seed: int, progress=None):
    """The network ``make_net()`` trained on ``n`` items and its loss per epoch: AdamW (``st.lr``,
    ``st.weight_decay``) with a one-cycle schedule over ``st.epochs`` passes in batches of ``st.batch``
    on ``st.threads`` threads; ``batch_loss(net, indices, rng)`` gives a batch's loss. Seeded: torch's
    generator (before the network is made) and the numpy generator ``(seed, 2)`` that orders each pass
    and is handed to ``batch_loss`` (both networks' :func:`fit`)."""
    torch = require_torch()
    say = progress or (lambda msg: None)
    torch.manual_seed(seed)
    torch.set_num_threads(st.threads)
    rng = np.random.default_rng([seed, 2])
    net = make_net()
    opt = torch.optim.AdamW(net.parameters(), st.lr, weight_decay=st.weight_decay)
    steps = st.epochs * int(np.ceil(n / st.batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, st.lr, total_steps=steps, pct_start=0.1)
    losses = []
    for ep in range(st.epochs):
        net.train()
        perm = rng.permutation(n)
        total, t0 = 0.0, time.perf_counter()
        for k in range(0, len(perm), st.batch):
            sel = perm[k:k + st.batch]
            loss = batch_loss(net, sel, rng)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(sel)
        losses.append(round(total / n, 5))
        say(f"epoch {ep + 1}/{st.epochs}: loss {losses[-1]:.4f} ({time.perf_counter() - t0:.0f} s)")
    net.eval()
    return net, losses


def fit(samples, st: CnnSettings, seed: int, progress=None):
    """The trained network and its loss per epoch (:func:`train`): each batch's boxes jittered as a
    segmentation errs (:func:`jitter_box`, the batches' generator)."""
    torch = require_torch()

    def batch_loss(net, sel, rng):
        batch = [samples[i] for i in sel]
        X, Y = batch_arrays(batch, [jitter_box(s, rng, st) for s in batch])
        Y = torch.from_numpy(Y)
        kp, _, logp = net(torch.from_numpy(X[:, None]), True)
        loss = torch.nn.functional.smooth_l1_loss(kp, Y, beta=0.02)
        if logp is not None and st.heatmap_weight > 0:
            loss = loss + st.heatmap_weight * heatmap_loss(logp, Y, net.gx, net.gy)
        return loss

    return train(lambda: build_net(st.head), batch_loss, len(samples), st, seed, progress)


def export_onnx(net, output_names=("keypoints", "spread"), channels: int = 1) -> bytes:
    """The network as ONNX bytes (torch's exporter; input ``depth`` (B, ``channels``, 64, 64), outputs
    ``output_names``: the keypoint CNN's ``keypoints`` and ``spread``; the batch size dynamic)."""
    torch = require_torch()
    net.eval()
    x = torch.zeros(2, channels, INPUT_SIDE, INPUT_SIDE)
    try:
        prog = torch.onnx.export(net, (x,), None, input_names=["depth"], output_names=list(output_names),
                                 dynamic_shapes=({0: torch.export.Dim("batch")},), dynamo=True, verbose=False)
    except ImportError as exc:
        raise TrackerError("onnx", f"the exporter needs onnx and onnxscript ({exc}; pip install '.[train]')") from None
    return without_trace(prog.model_proto).SerializeToString()


def without_trace(model):
    """The ONNX model without the exporter's per-node trace (stack traces with the build machine's file
    paths, fx node names): what runs is unchanged, and the shipped file names no machine."""
    for node in model.graph.node:
        del node.metadata_props[:]
    return model


# ----------------------------------------------------------------------------- experiments and the product
def compare_heads(recipe: DataRecipe, seed: int, n_train: int, n_heldout: int, epochs: int,
                  heads=("regression", "heatmap"), progress=None, **changes) -> dict:
    """Each head trained on the same crops (drawn once) with the same settings and seed, measured on
    the same held-out crops (:func:`evaluate_samples`): the measurement behind the shipped head.
    ``heads`` names a head, or ``(label, head, {setting: value})`` for a variant; ``changes`` apply
    to all (:class:`CnnSettings`)."""
    from .eval_cnn import evaluate_samples  # it imports this module

    say = progress or (lambda msg: None)
    t0 = time.perf_counter()
    st = CnnSettings(n_crops=n_train, epochs=epochs, **changes)
    train = draw_samples(recipe, seed, n_train, st.jobs)
    held = draw_samples(recipe, seed + HELDOUT_SEED_OFFSET, n_heldout, st.jobs)
    say(f"drew {len(train)} + {len(held)} samples in {time.perf_counter() - t0:.0f} s")
    out = {"train_crops": len(train), "heldout_crops": len(held), "epochs": epochs, "seed": seed}
    for spec in heads:
        label, head, extra = (spec, spec, {}) if isinstance(spec, str) else spec
        t1 = time.perf_counter()
        net, losses = fit(train, replace(st, head=head, **extra), seed, progress)
        res = evaluate_samples(TorchRunner(net), held, st, seed)
        res.update(losses=losses, fit_s=round(time.perf_counter() - t1, 1),
                   parameters=int(sum(p.numel() for p in net.parameters())))
        out[label] = res
        say(f"{label}: {res['true_box']} / jittered {res['jittered_box']}")
    return out


def model_output(output, name: str, version: str, overwrite: bool) -> Path:
    """The manifest path ``output/<name>-<version>.json`` of a network to write, refused when it or its
    ``.onnx`` exists (unless ``overwrite``)."""
    out = Path(output) / f"{name}-{version}.json"
    if (out.exists() or out.with_suffix(".onnx").exists()) and not overwrite:
        raise TrackerError(str(out), "exists (give another output folder or --version)")
    return out


def training_record(net, losses, seconds: dict, **extra) -> dict:
    """The manifest's ``training`` entry: ``extra`` (crops, the data's SHA-256 …), the losses, the
    parameter count, the seconds each part took and the versions that trained it."""
    torch = require_torch()
    return {**extra, "losses": losses, "parameters": int(sum(p.numel() for p in net.parameters())),
            "seconds": {k: round(v, 1) for k, v in seconds.items()}, "torch": torch.__version__,
            "numpy": np.__version__, "python": platform.python_version()}


def build(output, *, seed: int = 0, recipe: DataRecipe | None = None, settings: CnnSettings | None = None,
          heldout: int = 200, segmented: int = 100, real_data=None, version: str = "1.0.0", command: str = "",
          progress=None, overwrite: bool = False) -> tuple[Path, dict]:
    """Train, export, evaluate the exported network and write ``output/hand-keypoints-cnn-<version>``
    (``.onnx`` and ``.json``); returns the manifest's path and the manifest."""
    from .eval_cnn import evaluate_samples, evaluate_segmented, evaluate_starts  # it imports this module

    require_torch()
    recipe = recipe or DataRecipe()
    st = settings or CnnSettings()
    say = progress or (lambda msg: None)
    out = model_output(output, CNN_NAME, version, overwrite)
    t0 = time.perf_counter()
    say(f"drawing {st.n_crops} training crops and {heldout} held-out ones ({st.jobs} processes)")
    train = draw_samples(recipe, seed, st.n_crops, st.jobs)
    held = draw_samples(recipe, seed + HELDOUT_SEED_OFFSET, heldout, st.jobs)
    t_draw = time.perf_counter() - t0
    data_hash = hashlib.sha256()
    for s in train:
        data_hash.update(s.depth.tobytes() + s.uv.tobytes() + s.z.tobytes())
    net, losses = fit(train, st, seed, progress)
    t_fit = time.perf_counter() - t0 - t_draw
    onnx_bytes = export_onnx(net)
    model = KeypointCNN(onnx_bytes, {})
    ref = TorchRunner(net).run(np.zeros((1, INPUT_SIDE, INPUT_SIDE), np.float32))[0]
    if not np.allclose(model.run(np.zeros((1, INPUT_SIDE, INPUT_SIDE), np.float32))[0], ref, atol=1e-4):
        raise TrackerError("onnx", "the exported network does not give torch's output")
    from synergy.bundle import load_bundle

    bundle = load_bundle("fingerfist")
    say(f"evaluating the exported network on {len(held)} held-out crops")
    metrics = {"heldout": evaluate_samples(model, held, st, seed),
               "start": evaluate_starts(model, held, bundle)}
    say(f"evaluating on {segmented} held-out whole frames through the tracker's segmentation")
    metrics["segmented"] = evaluate_segmented(model, recipe, seed, segmented, bundle)
    if real_data is not None:
        say("evaluating on the labelled SR305 stills")
        metrics["real_sr305"] = evaluate_real(model, real_data, detect_fn=detect)
    manifest = {"name": CNN_NAME, "version": version, "command": command, "seed": seed, "family": "cnn",
                "recipe": recipe.to_dict(), "settings": st.to_dict(), "input_side": INPUT_SIDE,
                "box_grow": BOX_GROW, "depth_range_m": DEPTH_RANGE_M, "z_scale_m": Z_SCALE_M,
                "spread_scale": SPREAD_SCALE, "heldout_seed": seed + HELDOUT_SEED_OFFSET,
                "training": training_record(net, losses, {"draw": t_draw, "fit": t_fit,
                                                          "total": time.perf_counter() - t0},
                                            crops=len(train), samples_sha256=data_hash.hexdigest()),
                "metrics": metrics, "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    path = save_cnn(out, onnx_bytes, manifest, overwrite=overwrite)
    return path, manifest
