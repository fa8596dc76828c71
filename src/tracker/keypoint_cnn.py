"""Hand keypoints from one depth frame and the hand's segmentation: a small CNN run by onnxruntime.

The hand's box is the square around the mask's pixels, grown by :data:`BOX_GROW`; the depth in it
is sampled to :data:`INPUT_SIDE`² pixels (nearest pixel: no depth mixed across an edge), minus the
mask's median depth over :data:`DEPTH_RANGE_M`, clipped to ±1, 1 where there is no depth or no
image; a right hand is mirrored to a left one (one network serves both). The network gives each
keypoint's place in the box (0–1), its depth relative to the median (in :data:`Z_SCALE_M`) and the
spread of its 2-D heatmap (box units; 0 for a network that regresses the keypoints directly); the
spread becomes the keypoint's confidence (:func:`spread_confidence`). The result is a
:class:`tracker.detector.Detection`, so :func:`tracker.keypoint_fit.fit_start` takes it as it takes the
forest's.

The network is trained by :mod:`tracker.sim.train_cnn` (PyTorch, the ``[train]`` extra) and shipped
as ONNX under ``models/detectors/`` beside a JSON manifest (training command, data recipe, seed,
metrics, the ONNX file's SHA-256, sealed by its own ``manifest_sha256``). Inference needs only
onnxruntime (a core dependency), on one thread. This module never imports :mod:`tracker.sim`
nor torch.

Examples
--------
>>> import numpy as np
>>> box = hand_box(np.full((40, 60), 0.5), np.pad(np.ones((10, 20), bool), ((5, 25), (10, 30))))
>>> [round(float(v), 2) for v in box]
[19.5, 9.5, 26.7, 0.5]
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from handmodel.fileio import atomic_write_bytes, manifest_sha256, read_limited

from .detector import N_PARTS, PART_NAMES, Detection, checked_frame, newest_shipped, read_once
from .errors import TrackerError

CNN_NAME = "hand-keypoints-cnn"
FORMAT = "hand-keypoint-cnn/1"
#: The network's input: a square of this many pixels a side.
INPUT_SIDE = 64
#: The box's side over the mask's larger extent (a margin for keypoints inside the skin's outline,
#: and for a segmentation that cuts a finger short).
BOX_GROW = 1.3
#: Depth in the input: (depth − the mask's median) / this, clipped to ±1.
DEPTH_RANGE_M = 0.15
#: The network's depth output is (keypoint depth − the mask's median) / this.
Z_SCALE_M = 0.1
#: A mask with fewer pixels with depth gives no keypoints.
MIN_MASK_PIXELS = 20
#: A heatmap spread (box units) of this size gives a confidence of exp(−1). The heatmaps are broad
#: (spread quartiles 0.23 / 0.27 / 0.30 in the head comparison, seed 7's held-out crops): a median
#: keypoint gets ~0.45, one twice as spread ~0.04 (below fit_start's 0.2).
SPREAD_SCALE = 0.3
#: Re-crops of the box around the network's own keypoints, at most (the refined hand localisation of
#: DeepPrior++, Oberweger & Lepetit 2017): a segmentation that kept the forearm gives a box several hands
#: long, which the network never saw in training (boxes at most ~2 hands long: ``CnnSettings.forearm_reach``);
#: its keypoints there still lie towards the hand, and each box around them is nearer to one hand's.
RECROP_PASSES = 3
#: A re-cropped box: the keypoints' larger extent plus this margin (m, at their median depth) on each side
#: (the skin beyond the joints, a finger's width, and room for keypoints the pass before placed short).
RECROP_MARGIN_M = 0.03
#: Re-crops go on while each shortens the box's side by more than this share (a box already about the
#: hand's is left as it is: the same keypoints as without the re-crop) …
RECROP_CUT = 0.1
#: … and their last is taken only where the box's side is then at most this share of the mask's: a box
#: more than 1.67 hands long, longer than all but ~6 % of the training's boxes (a third of them
#: stretched towards the forearm by 0.2-0.8 of the hand: ``CnnSettings.forearm_reach``). Boxes the
#: network knows are better read whole (a 1.5x side fist with a third of its mask arm: 14 mm whole,
#: 16 mm re-cropped to 0.73 of the box).
RECROP_TAKE = 0.6
MAX_ONNX_BYTES = 64 << 20
MAX_MANIFEST_BYTES = 4 << 20


def _require_onnxruntime():
    try:
        import onnxruntime
    except ImportError:
        raise TrackerError("onnxruntime", "not installed: the keypoint CNN needs it (pip install onnxruntime; or track with --no-detector)") from None
    return onnxruntime


# ----------------------------------------------------------------------------- input and output
def hand_box(depth, mask, grow: float = BOX_GROW):
    """``(cu, cv, size, median_m)``: the square box around the mask's pixels with depth (centre in
    pixels, side ``grow`` × the larger extent + 2 px) and their median depth; None with fewer than
    :data:`MIN_MASK_PIXELS`."""
    d = np.asarray(depth)
    m = np.asarray(mask, bool) & np.isfinite(d) & (d > 0)
    if m.sum() < MIN_MASK_PIXELS:
        return None
    rows, cols = np.nonzero(m)
    cu, cv = (cols.min() + cols.max()) / 2.0, (rows.min() + rows.max()) / 2.0
    size = grow * max(cols.max() - cols.min(), rows.max() - rows.min()) + 2.0
    return float(cu), float(cv), float(size), float(np.median(d[m]))


def recrop_window(keypoints_px, keypoints_z, fx: float, shape, margin_m: float = RECROP_MARGIN_M):
    """``(r0, r1, c0, c1)``: the rows and columns of an image of ``shape`` within the square around the
    keypoints (their larger pixel extent plus ``margin_m`` on each side at their median depth), or None
    when no keypoint has a place or the square misses the image."""
    uv = np.asarray(keypoints_px, float)
    ok = np.isfinite(uv).all(axis=1)
    z = np.asarray(keypoints_z, float)[ok]
    z = z[np.isfinite(z) & (z > 0)]
    if not ok.any() or not len(z):
        return None
    lo, hi = uv[ok].min(axis=0), uv[ok].max(axis=0)
    cu, cv = (lo + hi) / 2.0
    half = 0.5 * float(np.max(hi - lo)) + margin_m * float(fx) / float(np.median(z))
    r0, r1 = max(0, int(np.ceil(cv - half))), min(shape[0], int(np.floor(cv + half)) + 1)
    c0, c1 = max(0, int(np.ceil(cu - half))), min(shape[1], int(np.floor(cu + half)) + 1)
    return (r0, r1, c0, c1) if r0 < r1 and c0 < c1 else None


def recropped(mask, keypoints_px, keypoints_z, fx: float, margin_m: float = RECROP_MARGIN_M):
    """``mask`` kept within :func:`recrop_window` (all False where there is none), or None when no keypoint
    has a place.

    >>> m = np.ones((100, 100), bool)
    >>> kp = np.array([[40.0, 40.0], [50.0, 60.0]])
    >>> r = recropped(m, kp, np.array([0.5, 0.5]), 100.0, margin_m=0.05)
    >>> int(r.sum()), np.argwhere(r).min(axis=0).tolist(), np.argwhere(r).max(axis=0).tolist()
    (1681, [30, 25], [70, 65])
    """
    if not np.isfinite(np.asarray(keypoints_px, float)).all(axis=1).any():
        return None
    m = np.asarray(mask, bool)
    return _kept_in(m, recrop_window(keypoints_px, keypoints_z, fx, m.shape, margin_m))


def _kept_in(mask, win):
    """``mask`` within the window ``win`` (:func:`recrop_window`), False elsewhere (all False without one)."""
    out = np.zeros_like(mask)
    if win is not None:
        r0, r1, c0, c1 = win
        out[r0:r1, c0:c1] = mask[r0:r1, c0:c1]
    return out


def _box_in(depth, mask, win):
    """:func:`hand_box` of ``mask`` kept within the window ``win`` (:func:`recrop_window`), computed on the
    window alone (the mask is False outside it)."""
    if win is None:
        return None
    r0, r1, c0, c1 = win
    b = hand_box(depth[r0:r1, c0:c1], mask[r0:r1, c0:c1])
    return None if b is None else (b[0] + c0, b[1] + r0, b[2], b[3])


def crop_image(depth, box, mirror: bool, side: int = INPUT_SIDE) -> np.ndarray:
    """The network's ``(side, side)`` float32 input for ``box`` (:func:`hand_box`): the nearest
    pixel at each cell's centre, (depth − median) / :data:`DEPTH_RANGE_M` clipped to ±1, 1 where
    there is no depth or no image; ``mirror`` (a right hand) flips it left–right."""
    cu, cv, size, med = box
    d = np.asarray(depth, np.float32)
    g = (np.arange(side) + 0.5) / side * size - size / 2.0
    uu = np.floor(cu + g + 0.5).astype(np.int64)
    vv = np.floor(cv + g + 0.5).astype(np.int64)
    okc = (uu >= 0) & (uu < d.shape[1])
    okr = (vv >= 0) & (vv < d.shape[0])
    img = np.ones((side, side), np.float32)
    sub = d[np.ix_(vv[okr], uu[okc])]
    with np.errstate(invalid="ignore"):
        val = np.where(np.isfinite(sub) & (sub > 0), np.clip((sub - med) / DEPTH_RANGE_M, -1.0, 1.0), 1.0)
    img[np.ix_(okr, okc)] = val
    return img[:, ::-1].copy() if mirror else img


def box_keypoints(out, box, mirror: bool, camera):
    """Pixels ``(21, 2)``, depths ``(21,)`` and camera-frame points ``(21, 3)`` of the network's
    output ``(21, 3)`` (x, y in the box 0–1, z relative in :data:`Z_SCALE_M`) for ``box``."""
    cu, cv, size, med = box
    o = np.asarray(out, float).reshape(N_PARTS, 3)
    x = 1.0 - o[:, 0] if mirror else o[:, 0]
    u = cu - size / 2.0 + x * size
    v = cv - size / 2.0 + o[:, 1] * size
    z = med + o[:, 2] * Z_SCALE_M
    xyz = np.stack([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z], axis=1)
    return np.stack([u, v], axis=1), z, xyz


def spread_confidence(spread) -> np.ndarray:
    """0–1 from each keypoint's heatmap spread (box units): exp(−(spread / :data:`SPREAD_SCALE`)²);
    1 for a network without heatmaps (spread 0)."""
    s = np.asarray(spread, float)
    return np.exp(-(s / SPREAD_SCALE) ** 2)


# ----------------------------------------------------------------------------- the model
@dataclass(eq=False)
class KeypointCNN:
    """A verified ONNX network with its manifest; the onnxruntime session is made on first use.

    Parameters
    ----------
    onnx_bytes : bytes
        The ONNX model (its SHA-256 is the manifest's ``onnx_sha256``).
    manifest : dict
    path : Path or None
        The manifest file it was read from.
    """

    onnx_bytes: bytes
    manifest: dict
    path: Path | None = None
    _session: object = field(default=None, repr=False)

    @property
    def session(self):
        if self._session is None:
            ort = _require_onnxruntime()
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1  # one core: the tracker's other work runs beside it
            opts.inter_op_num_threads = 1
            self._session = ort.InferenceSession(self.onnx_bytes, opts, providers=["CPUExecutionProvider"])
        return self._session

    def __deepcopy__(self, memo):
        # read-only once verified, and an onnxruntime session cannot be copied: a copied tracker
        # (copy.deepcopy) shares its network, as every tracker of a process shares load_cnn's
        return self

    def run(self, images) -> tuple[np.ndarray, np.ndarray]:
        """``(keypoints (B, 21, 3), spread (B, 21))`` of inputs ``(B, side, side)``."""
        x = np.ascontiguousarray(np.asarray(images, np.float32)[:, None])
        kp, spread = self.session.run(["keypoints", "spread"], {"depth": x})
        return kp, spread


def _cnn_paths(path) -> tuple[Path, Path]:
    """The manifest and the network of ``path`` (either, or their common stem: ``name-1.0.0``, whose
    ``.0`` is no suffix)."""
    p = Path(path)
    stem = p.name[: -len(p.suffix)] if p.suffix in (".json", ".onnx") else p.name
    return p.parent / f"{stem}.json", p.parent / f"{stem}.onnx"


def onnx_sha256(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def save_cnn(path, onnx_bytes: bytes, manifest: dict, *, overwrite: bool = False, fmt: str = FORMAT) -> Path:
    """Write ``<path>.onnx`` and its sealed ``<path>.json`` manifest (the ONNX's SHA-256 and the
    manifest's own), each verified by reading it back; returns the manifest's path. ``fmt``: the
    network's format (this module's, or :data:`tracker.hand_presence.PRESENCE_FORMAT`)."""
    jpath, opath = _cnn_paths(path)
    m = dict(manifest, format=fmt, onnx_file=opath.name, onnx_sha256=onnx_sha256(onnx_bytes))
    m["manifest_sha256"] = manifest_sha256(m)
    for p in (jpath, opath):
        if p.exists() and not overwrite:
            raise TrackerError(str(p), "exists (give another output folder or version)")
    try:
        atomic_write_bytes(opath, onnx_bytes, overwrite=overwrite)
        text = json.dumps(m, indent=1, sort_keys=True, allow_nan=False) + "\n"
        atomic_write_bytes(jpath, text.encode("utf-8"), overwrite=overwrite)
    except OSError as exc:
        raise TrackerError(str(exc.filename or jpath), f"cannot write ({exc.strerror or exc})") from None
    read_cnn(jpath, fmt=fmt)
    return jpath


def read_cnn(path, *, fmt: str = FORMAT, cls=None):
    """Read and verify a keypoint CNN (its ``.json`` manifest or ``.onnx``, the other beside it under
    the same stem): the manifest's seal, then the ONNX bytes against its ``onnx_sha256`` (before
    onnxruntime sees them; the pair may be renamed, not mixed). ``fmt`` and ``cls``: another network
    of the same file scheme and input (:func:`tracker.hand_presence.read_presence`)."""
    jpath, opath = _cnn_paths(path)
    raw = read_limited(jpath, MAX_MANIFEST_BYTES, TrackerError)
    try:
        manifest = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise TrackerError(str(jpath), f"manifest is not JSON ({getattr(exc, 'msg', exc)})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != fmt:
        raise TrackerError(str(jpath), f"not a {fmt} manifest")
    if manifest.get("manifest_sha256") != manifest_sha256(manifest):
        raise TrackerError(str(jpath), "manifest does not match its manifest_sha256 (manifest edited?)")
    data = read_limited(opath, MAX_ONNX_BYTES, TrackerError)
    if onnx_sha256(data) != manifest.get("onnx_sha256"):
        raise TrackerError(str(opath), "does not match the manifest's onnx_sha256 (file modified?)")
    if manifest.get("input_side") != INPUT_SIDE or manifest.get("box_grow") != BOX_GROW:
        raise TrackerError(str(jpath), "made for another input (input_side, box_grow) than this version reads")
    return (cls or KeypointCNN)(data, manifest, jpath)


def cnn_path(name: str = CNN_NAME, what: str = "keypoint CNN") -> Path:
    """The shipped network of that name (newest version under ``models/detectors/``) or a path."""
    p = Path(name)
    if p.suffix in (".json", ".onnx"):
        return _cnn_paths(p)[0]
    return newest_shipped(name, ".json", what)


def load_cnn(name_or_path: str = CNN_NAME) -> KeypointCNN:
    """The network by name (shipped, newest version) or path, read and verified once per process."""
    return read_once(cnn_path(str(name_or_path)), read_cnn, "keypoint CNN manifest")


# ----------------------------------------------------------------------------- detection
def _nothing(pixels: int = 0) -> Detection:
    return Detection(np.full((N_PARTS, 2), np.nan), np.full(N_PARTS, np.nan), np.full((N_PARTS, 3), np.nan),
                     np.zeros(N_PARTS), 0.0, pixels)


def detect(depth_m, camera, mask, hand: str = "left", *, detector: KeypointCNN | None = None,
           recrop: int = RECROP_PASSES) -> Detection:
    """The hand's 21 keypoints (:data:`tracker.detector.PART_NAMES` order) from one depth frame.

    Parameters
    ----------
    depth_m : (H, W) float
        Depth in metres, NaN or 0 where none.
    camera : a camera (``tracker.io.cameras``) or preset name
    mask : (H, W) bool
        The hand's segmentation (``tracker.observe.observe(...).mask``): it places the box and the
        depth origin; the network reads every pixel in the box.
    hand : "left" or "right"
    detector : the network (default: the shipped one)
    recrop : at most this many passes again on the mask :func:`recropped` around the last pass's keypoints,
        while each shortens the box by more than :data:`RECROP_CUT`; the last is the answer where its box
        is at most :data:`RECROP_TAKE` of the mask's, else the first (0: the mask's box only)

    Returns
    -------
    Detection
        Every keypoint has a place when the mask has :data:`MIN_MASK_PIXELS` pixels with depth
        (confidence from the heatmaps' spread); otherwise none (NaN, confidence 0, hand score 0).
        ``hand_score`` is the mean confidence: the network was not trained on crops without a hand,
        so it says how sure the keypoints are, not whether a hand is there. ``region``: the re-cropped
        mask of the last pass, None when no re-crop was taken.
    """
    cam, d = checked_frame(depth_m, camera, hand)
    if mask is None:
        raise TrackerError("mask", "the keypoint CNN needs the hand's segmentation (observe(...).mask)")
    m = np.asarray(mask, bool)
    if m.shape != d.shape:
        raise TrackerError("mask", f"shape {m.shape} differs from the depth's {d.shape}")
    box = hand_box(d, m)
    if box is None:
        return _nothing(int(m.sum()))
    net = detector or load_cnn()
    mirror = hand == "right"
    passes = []  # (window, spread, keypoints (uv, z, xyz)) of each pass
    box0, win = box, None
    for k in range(int(recrop) + 1):
        out, spread = net.run(crop_image(d, box, mirror)[None])
        passes.append((win, spread[0], box_keypoints(out[0], box, mirror, cam)))
        if k == recrop:
            break
        uv, z, _ = passes[-1][2]
        # the original mask around these keypoints: a pass that strayed is not compounded
        nwin = recrop_window(uv, z, cam.fx, m.shape)
        nbox = _box_in(d, m, nwin)
        if nbox is None or nbox[2] >= (1.0 - RECROP_CUT) * box[2]:
            break
        box, win = nbox, nwin
    win, spread, (uv, z, xyz) = passes[-1] if box[2] <= RECROP_TAKE * box0[2] else passes[0]
    region = None if win is None else _kept_in(m, win)
    conf = spread_confidence(spread)
    return Detection(uv, z, xyz, conf, float(conf.mean()), int(m.sum()), region)


__all__ = ["CNN_NAME", "INPUT_SIDE", "BOX_GROW", "KeypointCNN", "PART_NAMES", "RECROP_PASSES", "box_keypoints",
           "cnn_path", "crop_image", "detect", "hand_box", "load_cnn", "read_cnn", "recrop_window", "recropped",
           "save_cnn", "spread_confidence"]
