"""Pictures of synergies: the hand at μ − 2σ, μ and μ + 2σ along the first principal components
(the paper's Fig. 6)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def synergy_hands(bundle, path, n_pcs=3, sigmas=(-2.0, 0.0, 2.0), hand_model="default"):
    """A grid of shaded hand meshes: one row per PC, one column per multiple of σ."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from handmodel import HandModel
    from handmodel.fileio import atomic_write_bytes
    from handmodel.plots import draw_mesh

    hand = HandModel.load(hand_model)
    m = bundle.model
    k = min(n_pcs, m.all_components_.shape[0])
    mesh = hand.mesh()
    fig = plt.figure(figsize=(2.6 * len(sigmas), 2.5 * k))
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
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    plt.close(fig)
    return atomic_write_bytes(Path(path), buf.getvalue())
