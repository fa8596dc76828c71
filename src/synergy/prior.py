"""A Gaussian posture prior for the marker IK (issue 40): the 20 posture angles ~ N(μ, Σ) from posture
data (a synergy bundle holds μ and every PC with its variance, so Σ = Cᵀ diag(σ²) C), widened by an
isotropic floor so that no direction the data happened not to vary is held rigid.

The IK adds the whitened rows ``L (θ_posture − μ)`` (``LᵀL = Σ⁻¹``) beside the marker residuals
divided by the trial's noise: where the markers fix a joint they outweigh the prior; where they leave
a direction flat (an MCP/PIP split seen through a marker on a 10 mm lever) the prior decides.

>>> p = PosturePrior.from_bundle("fingerfist")
>>> p.name, p.mean.shape, bool(p.sd_deg.min() >= p.floor_deg)
('fingerfist@1.0.0', (20,), True)
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import SynergyError

#: SD (degrees) added in quadrature to every direction of the posture data's covariance: the
#: fingerfist bundle's last PCs have SDs of 0.7-2.4°, which, held as they are, would bend every
#: well-observed joint of a posture the data did not hold (measured: docs/experiments/marker-prior.md).
FLOOR_DEG = 10.0


@dataclass
class PosturePrior:
    """N(``mean``, ``cov``) over the posture angles (radians, the hand model's posture order).

    ``cov`` is the posture data's covariance with ``floor_deg``² added on its diagonal; ``name``
    says where it came from (a bundle's ``name@version``)."""

    mean: np.ndarray
    cov: np.ndarray
    name: str = ""
    floor_deg: float = FLOOR_DEG
    samples: int = 0

    @classmethod
    def from_model(cls, model, *, name="", floor_deg=FLOOR_DEG, samples=0) -> "PosturePrior":
        """From a fitted :class:`~synergy.pca.SynergyModel` (every component, not only the kept ones)."""
        C = np.asarray(model.all_components_, float)
        ev = np.asarray(model.all_explained_variance_, float)
        cov = C.T @ np.diag(ev) @ C + np.radians(floor_deg) ** 2 * np.eye(C.shape[1])
        return cls(mean=np.asarray(model.mean_, float), cov=cov, name=name, floor_deg=float(floor_deg),
                   samples=int(samples))

    @classmethod
    def from_bundle(cls, spec, *, floor_deg=FLOOR_DEG, registries=None) -> "PosturePrior":
        """From a bundle by name (``fingerfist``, ``name@version``) or path."""
        from .bundle import load_bundle

        b = load_bundle(spec, registries)
        return cls.from_model(b.model, name=b.spec, floor_deg=floor_deg,
                              samples=int(b.manifest.get("n_samples", 0) or 0))

    @classmethod
    def from_postures(cls, X, *, name="postures", floor_deg=FLOOR_DEG) -> "PosturePrior":
        """From posture rows ``(N, 20)`` (radians)."""
        X = np.asarray(X, float)
        if X.ndim != 2 or len(X) < 2:
            raise SynergyError(name, f"a prior needs at least 2 posture rows, got shape {X.shape}")
        cov = np.cov(X, rowvar=False) + np.radians(floor_deg) ** 2 * np.eye(X.shape[1])
        return cls(mean=X.mean(0), cov=cov, name=name, floor_deg=float(floor_deg), samples=len(X))

    @property
    def sd_deg(self) -> np.ndarray:
        """Marginal SD of each posture angle (degrees)."""
        return np.degrees(np.sqrt(np.diag(self.cov)))

    def rows(self, hand):
        """``(P, c)``: the prior's residual rows over the hand's ``n_dofs`` coordinates,
        ``r = P θ − c`` with ``‖r‖² = (θ_posture − μ)ᵀ Σ⁻¹ (θ_posture − μ)``."""
        post = np.flatnonzero(~hand.pose_mask)
        if len(post) != len(self.mean):
            raise SynergyError(self.name or "prior", f"{len(self.mean)} posture angles, the hand model has "
                                                     f"{len(post)}")
        s, U = np.linalg.eigh(self.cov)
        L = (U / np.sqrt(s)).T
        P = np.zeros((len(s), hand.n_dofs))
        P[:, post] = L
        return P, L @ self.mean

    def to_dict(self) -> dict:
        """What the angles CSV and a bundle's manifest record about the prior."""
        return {"name": self.name, "floor_deg": self.floor_deg, "samples": self.samples,
                "sd_deg": [round(float(x), 2) for x in self.sd_deg]}


def resolve_prior(prior, *, floor_deg=FLOOR_DEG):
    """``None`` / ``'none'`` → None; a :class:`PosturePrior` as is; else a bundle name or path."""
    if prior is None or isinstance(prior, PosturePrior):
        return prior
    if isinstance(prior, str) and prior.lower() in ("none", "off", ""):
        return None
    return PosturePrior.from_bundle(prior, floor_deg=floor_deg)


def prior_option(text):
    """The ``--prior`` option of ``synergy angles`` / ``synergy fit``: ``'auto'``, None for
    ``none``, else the named bundle's prior, loaded now so that a wrong name stops before the work."""
    if text is None or text.lower() == "auto":
        return "auto"
    return resolve_prior(text)
