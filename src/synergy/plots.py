"""Pictures of a synergy bundle: the scree / cumulative-variance chart, the hand at μ − 2σ, μ and μ + 2σ
along the first principal components (the paper's Fig. 6) and the reconstruction error against the
number of PCs. Each function writes one PNG (atomically; an existing file only with ``overwrite``) and
returns its path.

Figures are built on matplotlib's object API with an Agg canvas, so nothing here touches pyplot's
global state or the user's backend.
"""
from __future__ import annotations

import io
from pathlib import Path

import mpl_toolkits.mplot3d  # noqa: F401  (registers the "3d" projection)
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from handmodel.fileio import atomic_write_bytes
from handmodel.model import HandModel
from handmodel.plots import draw_mesh


def _figure(**kw) -> Figure:
    fig = Figure(**kw)
    FigureCanvasAgg(fig)
    return fig


def _save_png(fig: Figure, path, dpi: int, overwrite: bool) -> Path:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return atomic_write_bytes(Path(path), buf.getvalue(), overwrite=overwrite)


def synergy_hands(bundle, path, n_pcs=3, sigmas=(-2.0, 0.0, 2.0), hand_model="default", overwrite=False) -> Path:
    """A grid of shaded hand meshes: one row per PC, one column per multiple of σ."""
    hand = HandModel.load(hand_model)
    m = bundle.model
    k = min(n_pcs, m.all_components_.shape[0])
    mesh = hand.mesh()
    fig = _figure(figsize=(2.6 * len(sigmas), 2.5 * k))
    for r in range(k):
        for c, s in enumerate(sigmas):
            th = np.zeros(hand.n_dofs)
            th[~hand.pose_mask] = m.posture(np.eye(r + 1)[r] * s)
            ax = fig.add_subplot(k, len(sigmas), r * len(sigmas) + c + 1, projection="3d", proj_type="ortho")
            draw_mesh(ax, hand, th, mesh)
            ax.view_init(elev=-60, azim=-100)
            ax.set_title(f"PC{r + 1} {'μ' if s == 0 else f'μ {s:+g}σ'} ({100 * m.all_explained_variance_ratio_[r]:.0f} %)"
                         if c == 0 else ("μ" if s == 0 else f"μ {s:+g}σ"), fontsize=8)
    fig.suptitle(f"{bundle.name}@{bundle.version}: synergies (hand at μ ± 2σ)", fontsize=10)
    fig.tight_layout()
    return _save_png(fig, path, dpi=90, overwrite=overwrite)


def scree_plot(bundle, path, overwrite=False) -> Path:
    """Variance explained per PC (bars) and cumulative (line), with the bundle's default PC count."""
    r = bundle.model.all_explained_variance_ratio_
    k = np.arange(1, r.size + 1)
    fig = _figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    ax.bar(k, 100 * r, color="tab:blue", alpha=0.7, label="per PC")
    ax.plot(k, 100 * np.cumsum(r), "o-", color="tab:red", ms=4, label="cumulative")
    n = bundle.model.n_components_
    ax.axvline(n + 0.5, color="0.4", ls="--", lw=1, label=f"default: {n} PCs")
    ax.set(xlabel="principal component", ylabel="variance explained (%)", ylim=(0, 102),
           title=f"{bundle.spec}: {bundle.manifest['n_samples']} postures", xticks=k)
    ax.grid(alpha=0.3)
    ax.legend(loc="center right")
    return _save_png(fig, path, dpi=120, overwrite=overwrite)


def reconstruction_curves(bundle, heldout=None) -> dict[str, np.ndarray]:
    """Label → RMS reconstruction error (degrees, all DoF pooled) for k = 0..D PCs: the curve stored
    in the manifest (if any) and that of ``heldout`` postures (N × D, if given)."""
    curves = {}
    if "heldout" in bundle.manifest:
        curves[f"stored ({bundle.manifest['heldout']['method']})"] = np.degrees(bundle.manifest["heldout"]["rms_rad"])
    if heldout is not None:
        c = bundle.model.reconstruction_curve(heldout)
        curves[f"--heldout files ({heldout.shape[0]} frames)"] = np.degrees(np.sqrt((c**2).mean(axis=1)))
    return curves


def reconstruction_plot(bundle, curves: dict, path, overwrite=False) -> Path:
    """The curves of :func:`reconstruction_curves` against the number of PCs."""
    fig = _figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.subplots()
    for label, rms_deg in curves.items():
        ax.plot(np.arange(len(rms_deg)), rms_deg, "o-", ms=4, label=label)
    ax.axvline(bundle.model.n_components_, color="0.4", ls="--", lw=1, label="default PCs")
    ax.set(xlabel="number of PCs", ylabel="held-out RMS error (deg, all DoF)",
           title=f"{bundle.spec}: reconstruction error", ylim=(0, None))
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.grid(alpha=0.3)
    ax.legend()
    return _save_png(fig, path, dpi=120, overwrite=overwrite)


def figure_paths(bundle, out, heldout: bool = False) -> list[Path]:
    """The PNGs :func:`bundle_figures` writes for ``bundle`` in folder ``out`` (``heldout``: extra held-out
    postures will be given), so that a caller can refuse existing ones before anything is drawn."""
    stem = Path(out) / f"{bundle.name}-{bundle.version}"
    kinds = ["scree", "hands"] + (["reconstruction"] if heldout or "heldout" in bundle.manifest else [])
    return [stem.with_name(f"{stem.name}-{k}.png") for k in kinds]


def bundle_figures(bundle, out, heldout=None, overwrite=False) -> list[Path]:
    """Scree, hands and (when any held-out data exist) reconstruction PNGs of ``bundle`` in folder
    ``out``, named ``<name>-<version>-<kind>.png`` (:func:`figure_paths`); ``heldout`` are extra held-out
    postures (N × D). An existing PNG is replaced only with ``overwrite`` (else ``FileExistsError``)."""
    paths = figure_paths(bundle, out, heldout is not None)
    written = [scree_plot(bundle, paths[0], overwrite=overwrite),
               synergy_hands(bundle, paths[1], overwrite=overwrite)]
    curves = reconstruction_curves(bundle, heldout)
    if curves:
        written.append(reconstruction_plot(bundle, curves, paths[2], overwrite=overwrite))
    return written
