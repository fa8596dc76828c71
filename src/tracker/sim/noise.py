"""Depth-sensor noise for synthetic frames: a :class:`NoiseModel` with switchable parts and presets
(``kinect1``: Kinect v1 structured light; ``sr305``: RealSense SR305/SR300 coded light, alias
``realsense``; ``d4xx``: RealSense D400 active stereo).

Parts (applied in this order by :meth:`NoiseModel.apply`; each can be switched off):

1. **Projector shadow** — structured-light sensors see no depth where the projector is occluded:
   a band of width ``f·b·(1/z_near − 1/z_far)`` pixels beside each depth step, on the side away
   from the projector (Kinect v1: projector ≈ 7.5 cm to the right of the IR camera in the image,
   so shadows fall left of objects).
2. **Holes on grazing and dark surfaces** — active sensors lose the pattern where the surface is
   seen at a grazing angle or reflects little infrared: pixels are lost with a probability rising
   linearly from 0 at incidence ``grazing_deg[0]`` to 1 at ``grazing_deg[1]``, and with
   ``dark_drop_prob`` where the renderer's infrared reflectance is below ``dark_reflectance``.
   The thresholds are our assumptions (no vendor figure); they make the dark sleeve and the rim
   of the fingers patchy, as on real RealSense frames.
3. **Lateral noise** — each pixel takes the depth of a neighbour displaced by a Gaussian offset of
   σ_L pixels; this frays silhouettes. Nguyen, Izadi & Lovell (2012, Fig. 6):
   σ_L(θ) = 0.8 + 0.035·θ/(π/2 − θ) px, θ the angle between the surface normal and the ray.
4. **Edge dropout** — valid pixels within ``edge_width_px`` of a silhouette or a depth jump larger
   than ``edge_jump_m`` are lost with probability ``edge_drop_prob`` (our defaults, not measured).
5. **Flying pixels** — a pixel beside a depth jump larger than ``edge_jump_m`` (a valid neighbour
   on both sides of it) takes, with probability ``flying_prob``, a depth between its own and its
   neighbour's (uniform fraction 0.1–0.9): the mixed-pixel artefact of stereo matching windows
   and of the sensors' edge filters, which puts points in mid-air between hand and background.
6. **Axial noise** growing with z², Nguyen, Izadi & Lovell (2012), "Modeling Kinect sensor noise for
   improved 3D reconstruction and tracking", 3DIMPVT, eq. (2): σ_z(z) = 0.0012 + 0.0019 (z − 0.4)² m
   for 10° ≤ θ ≤ 60°, plus 0.0001/√z · θ²/(π/2 − θ)² m beyond 60° (we add this term at every θ: it
   is below 0.12 mm up to 45°; θ is clipped at 85°). Their σ was measured on real Kinect depth,
   quantisation included, so with quantisation on the Gaussian part is reduced to
   ``sqrt(σ_z² − Δz²/12)`` and the total spread stays σ_z.
   Triangulating sensors in general follow σ_z = z²·σ_d/(f·b) (σ_d the disparity error in pixels):
   :meth:`NoiseModel.triangulation_coeffs` writes it in the same ``a + b (z − z0)²`` form. For the
   D400 Intel's white paper gives the RMS error z²·subpixel/(f·B) with subpixel ≈ 0.08 px
   (Grunnet-Jepsen, Sweetser & Woodfill, "Best-known-methods for tuning Intel RealSense D400 depth
   cameras for best performance", Intel white paper rev. 1.9, sec. 3), f = ½·Xres/tan(HFOV/2):
   D415 at 1280 px, HFOV 65°, B = 55 mm → f ≈ 1005 px, σ_z = 0.71 mm at 0.7 m, 1.45 mm at 1 m.
   The SR305 has no published formula: we use the same z² law with 3 mm/m² (0.75 mm at 0.5 m,
   1.5 mm at 0.7 m), our assumption of the order of the plane-fit residuals reported for the SR300.
7. **Disparity quantisation** — Kinect v1 reports disparity in 1/8-pixel steps with baseline
   b ≈ 7.5 cm and focal length f ≈ 580 px (Konolige & Mihelich 2011, "Technical description of
   Kinect calibration", ROS wiki), so depth comes in steps Δz = z²·Δd/(f·b) (Khoshelham &
   Elberink 2012, Sensors 12:1437, eq. 9): 1.4 mm at 0.7 m, 2.9 mm at 1 m.
8. **Depth quantisation** — depth comes in multiples of ``depth_step_m``: 0.125 mm for the SR300/SR305
   (Zabatani et al. 2020, "Intel RealSense SR300 coded light depth camera", IEEE TPAMI 42:2333),
   1 mm for the D400's default depth unit.
9. **Range** — no depth outside ``range_m`` (Kinect v1: 0.5–5 m, Khoshelham & Elberink 2012; SR300:
   0.2–1.5 m, librealsense camera_specs.md; D400: from MinZ = f·B/126 px ≈ 0.3 m at 848 px).
10. **Random dropout** of single pixels with ``random_drop_prob``.

Shadows: Kinect v1's projector sits 7.5 cm beside the camera; the D400 computes depth in the left
imager, so the region the right imager cannot see (a band f·B·(1/z_near − 1/z_far) wide, B = 55 mm)
has no depth — the same geometry with the right imager as "projector"; for the SR305 the
projector–camera distance is not published and we assume 4 cm.

Randomness comes only from the ``rng`` passed in, so frames are reproducible from a seed.

Examples
--------
>>> import numpy as np
>>> k = NoiseModel.preset("kinect1")
>>> round(float(k.sigma_z(1.0)) * 1000, 3)   # mm at 1 m
1.884
>>> d = k.apply(np.full((4, 4), 1.0, np.float32), rng=np.random.default_rng(0))
>>> d.dtype, bool(np.isfinite(d).all())
(dtype('float32'), True)
>>> round(float(NoiseModel.preset("d4xx").sigma_z(1.0)) * 1000, 2)   # D415 at 1 m
1.45
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.ndimage import binary_dilation

from handmodel import libm

from ..errors import TrackerError
from ._kernels import lateral_resample, projector_shadow

_THETA_MAX = np.radians(85.0)


@dataclass(frozen=True)
class NoiseModel:
    """Switchable sensor-noise parts; see the module docstring for the models and their sources.

    Parameters
    ----------
    axial : bool
        Gaussian axial noise σ_z(z) = a + b (z − z0)², ``axial_coeffs = (a, b, z0)`` in metres.
    angle_terms : bool
        Add Nguyen's incidence-angle terms to σ_z and σ_L (needs the renderer's incidence image).
    axial_includes_quantization : bool
        σ_z is the total spread including quantisation (reduce the Gaussian part accordingly).
    lateral_px : float
        σ_L at normal incidence in pixels (0: off).
    quantize : bool
        Quantise disparity ``f·b/z`` to multiples of ``disparity_step_px``.
    focal_px, baseline_m : float
        Focal length (pixels; ``None``: the camera's fx) and projector–camera baseline (metres),
        used by quantisation and shadows.
    shadow : bool
        Projector shadows; ``projector_side`` +1 = projector to the right of the camera in the image.
    edge_drop_prob, edge_width_px, edge_jump_m : float, int, float
        Dropout near silhouettes and depth jumps.
    random_drop_prob : float
        Probability of losing any valid pixel.
    range_m : (float, float)
        Depths outside are lost.
    depth_step_m : float
        Quantise depth itself to multiples of this (0: off).
    flying_prob : float
        Probability that a pixel beside a depth jump (> ``edge_jump_m``) becomes a flying pixel.
    grazing_deg : (float, float) or None
        Incidence angles (degrees) between which the loss probability rises from 0 to 1 (needs the
        renderer's incidence image).
    dark_reflectance, dark_drop_prob : float
        Pixels whose infrared reflectance (the renderer's ``reflectance``) is below the threshold are
        lost with this probability.
    """

    name: str = "custom"
    axial: bool = False
    axial_coeffs: tuple = (0.0012, 0.0019, 0.4)
    angle_terms: bool = False
    axial_includes_quantization: bool = True
    lateral_px: float = 0.0
    quantize: bool = False
    disparity_step_px: float = 0.125
    baseline_m: float = 0.075
    focal_px: float | None = None
    shadow: bool = False
    projector_side: int = 1
    edge_drop_prob: float = 0.0
    edge_width_px: int = 1
    edge_jump_m: float = 0.02
    random_drop_prob: float = 0.0
    range_m: tuple = (0.0, float("inf"))
    depth_step_m: float = 0.0
    flying_prob: float = 0.0
    grazing_deg: tuple | None = None
    dark_reflectance: float = 0.0
    dark_drop_prob: float = 0.0

    def __post_init__(self):
        _check(self)

    # ------------------------------------------------------------------ presets
    @classmethod
    def preset(cls, name: str) -> "NoiseModel":
        """A named preset (:data:`PRESETS`: ``none``, ``kinect1``, ``sr305``, ``d4xx``; ``realsense``
        is ``sr305``)."""
        try:
            return PRESETS[ALIASES.get(name, name)]
        except KeyError:
            raise TrackerError(f"noise {name}", f"unknown noise preset (known: {', '.join([*PRESETS, *ALIASES])})"
                               ) from None

    @staticmethod
    def triangulation_coeffs(disparity_sigma_px: float, focal_px: float, baseline_m: float) -> tuple:
        """``axial_coeffs`` of σ_z = z²·σ_d/(f·b), the error of any triangulating sensor (Intel's RMS
        formula with σ_d the subpixel accuracy).

        >>> a, b, z0 = NoiseModel.triangulation_coeffs(0.08, 1005.0, 0.055)
        >>> (a, z0), round(b * 1e3, 3)
        ((0.0, 0.0), 1.447)
        """
        if not (disparity_sigma_px > 0 and focal_px > 0 and baseline_m > 0):
            raise TrackerError("noise", "disparity σ, focal length and baseline must be positive")
        return (0.0, float(disparity_sigma_px / (focal_px * baseline_m)), 0.0)

    def with_(self, **changes) -> "NoiseModel":
        """A copy with some parts changed, e.g. ``kinect1.with_(shadow=False)``."""
        known = {f.name for f in fields(self)}
        bad = sorted(set(changes) - known)
        if bad:
            raise TrackerError(f"noise {self.name}", f"unknown setting(s): {', '.join(bad)}")
        return replace(self, **changes)

    @property
    def is_noise_free(self) -> bool:
        return _noise_free(self)

    @property
    def needs_incidence(self) -> bool:
        """Whether :meth:`apply` uses the incidence-angle image (``cos_incidence``)."""
        return (self.angle_terms and (self.axial or self.lateral_px > 0)) or self.grazing_deg is not None

    @property
    def needs_reflectance(self) -> bool:
        """Whether :meth:`apply` uses the infrared reflectance image (``reflectance``)."""
        return self.dark_drop_prob > 0 and self.dark_reflectance > 0

    def grazing_loss(self, cos_incidence) -> np.ndarray:
        """Probability of losing a pixel at this incidence (0 when the part is off)."""
        c = np.asarray(cos_incidence, float)
        if self.grazing_deg is None:
            return np.zeros_like(c)
        th = np.degrees(libm.acos(np.clip(np.abs(np.nan_to_num(c, nan=1.0)), 0.0, 1.0)))
        lo, hi = self.grazing_deg
        return np.clip((th - lo) / (hi - lo), 0.0, 1.0)

    # ------------------------------------------------------------------ the documented curves
    def sigma_z(self, z, cos_incidence=None) -> np.ndarray:
        """Documented total axial standard deviation σ_z (metres) at depth ``z`` (0 when axial is off)."""
        z = np.asarray(z, float)
        if not self.axial:
            return np.zeros_like(z)
        a, b, z0 = self.axial_coeffs
        s = a + b * (z - z0) ** 2
        if self.angle_terms and cos_incidence is not None:
            th = _theta(cos_incidence)
            s = s + 0.0001 / np.sqrt(np.maximum(z, 1e-6)) * th ** 2 / (np.pi / 2 - th) ** 2
        return s

    def sigma_lateral(self, cos_incidence=None) -> np.ndarray | float:
        """Lateral σ_L in pixels."""
        if self.lateral_px <= 0:
            return 0.0
        if self.angle_terms and cos_incidence is not None:
            th = _theta(cos_incidence)
            return self.lateral_px + 0.035 * th / (np.pi / 2 - th)
        return self.lateral_px

    def focal(self, camera=None) -> float:
        if self.focal_px is not None:
            return float(self.focal_px)
        if camera is None:
            raise TrackerError(f"noise {self.name}", "needs a camera (focal_px is None)")
        return float(camera.fx)

    def quantization_step(self, z, camera=None) -> np.ndarray:
        """Depth step Δz = z²·Δd/(f·b) (metres) at depth ``z``; 0 when quantisation is off."""
        z = np.asarray(z, float)
        if not self.quantize:
            return np.zeros_like(z)
        return z ** 2 * self.disparity_step_px / (self.focal(camera) * self.baseline_m)

    # ------------------------------------------------------------------ applying
    def apply(self, depth, camera=None, rng=None, cos_incidence=None, reflectance=None) -> np.ndarray:
        """A noisy copy of ``depth`` ((H, W) metres, NaN = no data) as float32.

        ``camera`` supplies fx when ``focal_px`` is None; ``rng`` a :class:`numpy.random.Generator`
        (default: seed 0); ``cos_incidence`` (H, W) the cosine between surface normal and ray;
        ``reflectance`` (H, W) the surfaces' infrared reflectance. Parts that need an image which is
        not given are skipped.
        """
        d = np.array(depth, dtype=np.float64)
        if d.ndim != 2:
            raise TrackerError(f"noise {self.name}", f"depth must be (H, W), got shape {d.shape}")
        rng = np.random.default_rng(0) if rng is None else rng
        out = np.full(d.shape, np.nan, np.float32)
        valid = np.isfinite(d) & (d > 0)
        if not valid.any():
            return out
        # work on the bounding box of valid pixels plus the reach of the lateral jitter
        smax = float(self.sigma_lateral(np.cos(_THETA_MAX) if self.angle_terms else None))
        jitter = int(np.ceil(4 * smax))
        win = _window(valid, jitter + self.edge_width_px + 1)
        d = d[win].copy()
        d[~valid[win]] = np.nan
        cosi = None if cos_incidence is None else np.asarray(cos_incidence, float)[win]

        d, cosi = _holes(self, d, cosi, None if reflectance is None else np.asarray(reflectance, float)[win], camera,
                         jitter, rng)
        ok = np.isfinite(d)
        z = _perturbed(self, d[ok], None if cosi is None else cosi[ok], camera, rng)
        d[ok] = z
        if self.random_drop_prob > 0:
            d[rng.random(d.shape) < self.random_drop_prob] = np.nan
        out[win] = d
        return out


def _check(nm):
    """Refuse a :class:`NoiseModel` whose settings are out of range (``TrackerError`` naming the setting)."""
    if nm.depth_step_m < 0:
        raise TrackerError(f"noise {nm.name}", f"depth_step_m must be >= 0, got {nm.depth_step_m}")
    if nm.grazing_deg is not None and not 0 <= nm.grazing_deg[0] < nm.grazing_deg[1] <= 90:
        raise TrackerError(f"noise {nm.name}", f"grazing_deg must be 0 <= start < end <= 90, got {nm.grazing_deg}")
    for p in ("edge_drop_prob", "random_drop_prob", "flying_prob", "dark_drop_prob"):
        v = getattr(nm, p)
        if not 0.0 <= v <= 1.0:
            raise TrackerError(f"noise {nm.name}", f"{p} must be in [0, 1], got {v}")
    if nm.lateral_px < 0 or nm.edge_width_px < 0 or nm.disparity_step_px <= 0 or nm.baseline_m <= 0:
        raise TrackerError(f"noise {nm.name}", "lateral_px, edge_width_px must be >= 0; disparity step and "
                                               "baseline > 0")
    if nm.projector_side not in (-1, 1):
        raise TrackerError(f"noise {nm.name}", "projector_side must be +1 or -1")


def _noise_free(nm) -> bool:
    """Whether every part of ``nm`` is off (:attr:`NoiseModel.is_noise_free`)."""
    return not (nm.axial or nm.lateral_px > 0 or nm.quantize or nm.shadow or nm.edge_drop_prob > 0
                or nm.random_drop_prob > 0 or nm.range_m[0] > 0 or np.isfinite(nm.range_m[1])
                or nm.depth_step_m > 0 or nm.flying_prob > 0 or nm.grazing_deg is not None
                or nm.dark_drop_prob > 0)


def _window(valid, reach):
    """The ``(rows, cols)`` slice pair of the bounding box of ``valid`` grown by ``reach`` pixels (within the image)."""
    rows, cols = np.flatnonzero(valid.any(1)), np.flatnonzero(valid.any(0))
    r0, r1 = max(rows[0] - reach, 0), min(rows[-1] + reach + 1, valid.shape[0])
    c0, c1 = max(cols[0] - reach, 0), min(cols[-1] + reach + 1, valid.shape[1])
    return (slice(r0, r1), slice(c0, c1))


def _holes(nm, d, cosi, reflectance, camera, jitter, rng):
    """Pixels a sensor loses or misplaces: projector shadows, grazing and dark surfaces, lateral
    jitter, edge drop-outs and flying pixels (in this order: the random draws follow it)."""
    if nm.shadow:
        sh = np.zeros(d.shape, np.bool_)
        projector_shadow(d, nm.focal(camera) * nm.baseline_m, nm.projector_side, sh)
        d[sh] = np.nan
    if nm.grazing_deg is not None and cosi is not None:
        d[rng.random(d.shape) < nm.grazing_loss(cosi)] = np.nan
    if nm.needs_reflectance and reflectance is not None:
        with np.errstate(invalid="ignore"):
            dark = reflectance < nm.dark_reflectance
        d[dark & (rng.random(d.shape) < nm.dark_drop_prob)] = np.nan
    if nm.lateral_px > 0:
        d, cosi = _lateral(d, cosi, nm.lateral_px, nm.angle_terms, max(jitter, 1), rng)
    if nm.edge_drop_prob > 0 and nm.edge_width_px > 0:
        near_edge = _edge_band(d, nm.edge_width_px, nm.edge_jump_m)
        d[near_edge & (rng.random(d.shape) < nm.edge_drop_prob)] = np.nan
    if nm.flying_prob > 0:
        d = _flying(d, nm.edge_jump_m, nm.flying_prob, rng)
    return d, cosi


def _perturbed(nm, z, cosi, camera, rng):
    """Depths ``z`` of the surviving pixels with axial noise, disparity or depth quantisation and the
    sensor's range applied (NaN outside it)."""
    if nm.axial:
        s = nm.sigma_z(z, None if cosi is None else cosi)
        if nm.quantize and nm.axial_includes_quantization:
            q = nm.quantization_step(z, camera)
            s = np.sqrt(np.maximum(s ** 2 - q ** 2 / 12.0, 0.0))
        z = z + s * rng.standard_normal(z.shape)
    if nm.quantize:
        fb = nm.focal(camera) * nm.baseline_m
        step = nm.disparity_step_px
        disp = np.round(fb / np.maximum(z, 1e-6) / step) * step
        z = np.where(disp > 0, fb / np.maximum(disp, 1e-12), np.nan)
    if nm.depth_step_m > 0:
        z = np.round(z / nm.depth_step_m) * nm.depth_step_m
    lo, hi = nm.range_m
    z = np.where((z >= lo) & (z <= hi), z, np.nan)
    return z

def _theta(cos_incidence) -> np.ndarray:
    c = np.clip(np.abs(np.nan_to_num(np.asarray(cos_incidence, float), nan=1.0)), 0.0, 1.0)
    return np.minimum(libm.acos(c), _THETA_MAX)  # the same bits on every processor


def _lateral(d, cosi, sigma0, angle, reach, rng):
    """Nearest-pixel resampling at Gaussian offsets (σ_L pixels, clipped to ±reach)."""
    nu = rng.standard_normal(d.shape, dtype=np.float32)
    nv = rng.standard_normal(d.shape, dtype=np.float32)
    c = np.zeros((0, 0)) if cosi is None else np.ascontiguousarray(cosi, dtype=np.float64)
    out_d = np.empty_like(d)
    out_c = np.empty_like(c)
    lateral_resample(np.ascontiguousarray(d), c, nu, nv, float(sigma0), bool(angle), int(reach), out_d, out_c)
    return out_d, (None if cosi is None else out_c)


def _flying(d, jump, prob, rng):
    """Pixels beside a depth jump > ``jump`` (both neighbours valid) moved, with probability ``prob``,
    a uniform 10–90 % of the way towards the neighbour across the largest jump."""
    ok = np.isfinite(d)
    partner = np.full(d.shape, np.nan)
    best = np.zeros(d.shape)
    for axis in (0, 1):
        for shift in (1, -1):
            nb = np.roll(d, shift, axis=axis)
            edge = 0 if shift == 1 else -1
            if axis == 0:
                nb[edge, :] = np.nan  # the image border wraps around: no neighbour there
            else:
                nb[:, edge] = np.nan
            with np.errstate(invalid="ignore"):
                gap = np.abs(nb - d)
                take = ok & np.isfinite(nb) & (gap > jump) & (gap > best)
            partner[take] = nb[take]
            best[take] = gap[take]
    fly = np.isfinite(partner) & (rng.random(d.shape) < prob)
    out = d.copy()
    out[fly] = d[fly] + rng.uniform(0.1, 0.9, int(fly.sum())) * (partner[fly] - d[fly])
    return out


def _edge_band(d, width, jump):
    """Valid pixels within ``width`` pixels (4-connected) of an invalid pixel or a depth jump."""
    ok = np.isfinite(d)
    edge = np.zeros_like(ok)
    filled = np.where(ok, d, np.inf)
    for axis in (0, 1):
        for shift in (1, -1):
            nb = np.roll(filled, shift, axis=axis)
            # the image border is no silhouette
            if axis == 0:
                nb[0 if shift == 1 else -1, :] = filled[0 if shift == 1 else -1, :]
            else:
                nb[:, 0 if shift == 1 else -1] = filled[:, 0 if shift == 1 else -1]
            with np.errstate(invalid="ignore"):
                edge |= ok & (~np.isfinite(nb) | (np.abs(nb - filled) > jump))
    if width > 1:
        cross = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], bool)
        edge = binary_dilation(edge, structure=cross, iterations=width - 1, mask=ok)
    return edge


PRESETS: dict[str, NoiseModel] = {
    "none": NoiseModel(name="none"),
    "kinect1": NoiseModel(
        name="kinect1", axial=True, angle_terms=True, axial_includes_quantization=True, lateral_px=0.8,
        quantize=True, disparity_step_px=0.125, baseline_m=0.075, focal_px=580.0, shadow=True, projector_side=1,
        edge_drop_prob=0.5, edge_width_px=2, edge_jump_m=0.02, random_drop_prob=0.0, range_m=(0.5, 5.0),
    ),
    # RealSense SR305 / SR300 coded light (sources and assumptions in the module docstring)
    "sr305": NoiseModel(
        name="sr305", axial=True, axial_coeffs=(0.0, 0.003, 0.0), angle_terms=False, axial_includes_quantization=False,
        lateral_px=0.5, quantize=False, baseline_m=0.04, focal_px=None, shadow=True, projector_side=1,
        edge_drop_prob=0.4, edge_width_px=1, edge_jump_m=0.02, flying_prob=0.2, grazing_deg=(65.0, 82.0),
        dark_reflectance=0.15, dark_drop_prob=0.8, depth_step_m=0.000125, range_m=(0.2, 1.5),
    ),
    # RealSense D415 active stereo at 1280×720 (Intel's RMS formula, subpixel 0.08, B = 55 mm, HFOV 65°)
    "d4xx": NoiseModel(
        name="d4xx", axial=True, axial_coeffs=NoiseModel.triangulation_coeffs(0.08, 1005.0, 0.055), angle_terms=False,
        axial_includes_quantization=False, lateral_px=0.6, quantize=False, baseline_m=0.055, focal_px=None,
        shadow=True, projector_side=1, edge_drop_prob=0.3, edge_width_px=1, edge_jump_m=0.02, flying_prob=0.35,
        grazing_deg=(70.0, 86.0), dark_reflectance=0.15, dark_drop_prob=0.5, depth_step_m=0.001, range_m=(0.3, 10.0),
    ),
}

#: Other names of presets.
ALIASES: dict[str, str] = {"realsense": "sr305"}
