"""Exact covariance PCA of hand postures from mergeable sufficient statistics.

The statistics of a chunk are its row count, mean, centred scatter matrix and per-DoF
min/max. Chunks merge with Chan et al.'s parallel update, so the fitted model does not
depend on how the data were split (files, processes, Dask partitions), and no raw
``Σxxᵀ`` is ever formed (it loses precision when the mean is large against the spread).
Checks of a fitted model (held-out reconstruction, principal angles): :mod:`synergy.pca_analysis`.

Examples
--------
>>> import numpy as np
>>> rng = np.random.default_rng(0)
>>> X = rng.normal(size=(500, 4)) @ np.diag([3.0, 2.0, 1.0, 0.5])
>>> a = SynergyModel(n_components=2).fit(X)
>>> s = SufficientStats.from_array(X[:123]).merge(SufficientStats.from_array(X[123:]))
>>> b = s.finalize(n_components=2).update_limits(X[:123]).update_limits(X[123:])
>>> bool(np.allclose(a.components_, b.components_) and np.allclose(a.pc_max_, b.pc_max_))
True
"""
from __future__ import annotations

from dataclasses import dataclass
from numbers import Integral, Real
from typing import Iterable, Mapping

import numpy as np
from sklearn.base import BaseEstimator, ClassNamePrefixFeaturesOutMixin, TransformerMixin
from sklearn.utils.validation import check_is_fitted

from synergy.errors import SynergyError

try:
    from sklearn.utils.validation import validate_data as _sk_validate_data
except ImportError:  # scikit-learn < 1.6

    def _sk_validate_data(est, X, **kw):
        return est._validate_data(X, **kw)


_CHUNK_ROWS = 1 << 16  # bounds the temporary centred copy to a few MB


# ----------------------------------------------------------------------------- statistics
@dataclass(frozen=True, eq=False)
class SufficientStats:
    """Mergeable statistics of a set of postures; plain numpy arrays only.

    Attributes
    ----------
    n : int
        Number of rows.
    shift : ndarray (D,)
        A data row; the mean is kept as ``shift + offset`` so that a large mean does not
        swamp the differences between chunk means when merging.
    offset : ndarray (D,)
        ``mean - shift``.
    scatter : ndarray (D, D)
        Centred scatter ``Σ (x - mean)(x - mean)ᵀ``.
    min, max : ndarray (D,)
        Per-DoF extremes (``+inf``/``-inf`` when ``n == 0``).
    """

    n: int
    shift: np.ndarray
    offset: np.ndarray
    scatter: np.ndarray
    min: np.ndarray
    max: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        return self.shift + self.offset

    @property
    def n_features(self) -> int:
        return self.shift.shape[0]

    @classmethod
    def empty(cls, n_features: int) -> "SufficientStats":
        """Identity element of :meth:`merge`."""
        d = int(n_features)
        z = np.zeros(d)
        return cls(0, z, z.copy(), np.zeros((d, d)), np.full(d, np.inf), np.full(d, -np.inf))

    @classmethod
    def from_array(cls, X, chunk_rows: int = _CHUNK_ROWS) -> "SufficientStats":
        """Statistics of the rows of ``X`` (N × D, finite)."""
        X = as_2d_finite(X, "SufficientStats.from_array")
        out = cls.empty(X.shape[1])
        if X.shape[0] == 0:
            return out
        shift = X[0].copy()
        for i in range(0, X.shape[0], chunk_rows):
            out = out.merge(cls._from_chunk(X[i : i + chunk_rows], shift))
        return out

    @classmethod
    def _from_chunk(cls, X: np.ndarray, shift: np.ndarray) -> "SufficientStats":
        Y = X - shift
        m = Y.mean(axis=0)
        Y -= m
        # One refinement step removes the rounding error of the first mean (two-pass, Higham).
        corr = Y.mean(axis=0)
        Y -= corr
        return cls(X.shape[0], shift, m + corr, Y.T @ Y, X.min(axis=0), X.max(axis=0))

    def merge(self, other: "SufficientStats") -> "SufficientStats":
        """Statistics of the union of both row sets (Chan, Golub & LeVeque 1979)."""
        if self.n_features != other.n_features:
            raise SynergyError(
                "SufficientStats.merge", f"{self.n_features} vs {other.n_features} DoF"
            )
        if other.n == 0:
            return self
        if self.n == 0:
            return other
        n = self.n + other.n
        # other's mean relative to our shift; shifts are data rows, so their difference is
        # small (exact when within a factor 2) and the chunk-mean difference keeps its digits.
        other_offset = (other.shift - self.shift) + other.offset
        delta = other_offset - self.offset
        offset = self.offset + delta * (other.n / n)
        scatter = self.scatter + other.scatter + np.outer(delta, delta) * (self.n * other.n / n)
        scatter = 0.5 * (scatter + scatter.T)
        return SufficientStats(
            n, self.shift, offset, scatter,
            np.minimum(self.min, other.min), np.maximum(self.max, other.max),
        )

    @staticmethod
    def merge_all(stats: Iterable["SufficientStats"]) -> "SufficientStats":
        """Merge any number of statistics (at least one)."""
        it = iter(stats)
        try:
            acc = next(it)
        except StopIteration:
            raise SynergyError("SufficientStats.merge_all", "nothing to merge") from None
        for s in it:
            acc = acc.merge(s)
        return acc

    def covariance(self, ddof: int = 1) -> np.ndarray:
        """Covariance ``scatter / (n - ddof)``."""
        if self.n - ddof <= 0:
            raise SynergyError("SufficientStats", f"needs more than {ddof} sample(s), got {self.n}")
        return self.scatter / (self.n - ddof)

    def as_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays (e.g. for ``np.savez`` or another process)."""
        return {
            "n": np.asarray(self.n, dtype=np.int64),
            "shift": self.shift,
            "offset": self.offset,
            "scatter": self.scatter,
            "min": self.min,
            "max": self.max,
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> "SufficientStats":
        """Inverse of :meth:`as_arrays`."""
        return cls(
            int(arrays["n"]),
            np.asarray(arrays["shift"], dtype=float),
            np.asarray(arrays["offset"], dtype=float),
            np.asarray(arrays["scatter"], dtype=float),
            np.asarray(arrays["min"], dtype=float),
            np.asarray(arrays["max"], dtype=float),
        )

    def finalize(self, n_components=None) -> "SynergyModel":
        """A fitted :class:`SynergyModel`; PC limits stay empty until :meth:`SynergyModel.update_limits`."""
        model = SynergyModel(n_components=n_components)
        model._set_from_stats(self)
        model.n_features_in_ = self.n_features
        return model


def as_2d_finite(X, where: str) -> np.ndarray:
    """``X`` as a float64 (samples × DoF) array, refused (``SynergyError`` naming ``where``) unless 2-D
    and finite."""
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2:
        raise SynergyError(where, f"expected a 2-D array (samples × DoF), got shape {X.shape}")
    if not np.isfinite(X).all():
        raise SynergyError(where, "Input contains NaN or infinity")
    return X


# ----------------------------------------------------------------------------- the model
class SynergyModel(ClassNamePrefixFeaturesOutMixin, TransformerMixin, BaseEstimator):
    """Covariance PCA of posture angles (radians, centred, not scaled).

    Parameters
    ----------
    n_components : None, int or float in (0, 1)
        Number of PCs used by :meth:`transform`; a float picks the fewest PCs whose
        cumulative variance ratio reaches it; ``None`` keeps ``min(n_samples, D)``.
        The full spectrum is always kept (``all_components_``).

    Attributes
    ----------
    components_ : ndarray (n_components_, D)
        Rows are PCs; the largest-magnitude entry of each is positive.
    mean_, joint_min_, joint_max_ : ndarray (D,)
    explained_variance_, explained_variance_ratio_ : ndarray (n_components_,)
        Variances with ``ddof=1`` (as scikit-learn) and their fractions of the total.
    all_components_ : ndarray (D, D)
    all_explained_variance_, all_explained_variance_ratio_ : ndarray (D,)
    pc_min_, pc_max_ : ndarray (D,)
        Min/max of the training projections on *all* components (``±inf`` until seen).
    n_components_, n_samples_, n_features_in_ : int
    """

    def __init__(self, n_components=None):
        self.n_components = n_components

    # -- fitting
    def fit(self, X, y=None):
        """Fit components and limits from ``X`` (N × D) in two passes."""
        X = self._validate(X, reset=True, where="SynergyModel.fit")
        self._set_from_stats(SufficientStats.from_array(X))
        return self.update_limits(X)

    def partial_fit(self, X, y=None):
        """Add rows to the statistics and refit.

        The components change, so PC limits are reset; call :meth:`update_limits` on
        every chunk once all chunks have been added.
        """
        first = not hasattr(self, "stats_")
        X = self._validate(X, reset=first, where="SynergyModel.partial_fit", min_samples=1)
        stats = SufficientStats.from_array(X)
        stats = stats if first else self.stats_.merge(stats)
        if stats.n >= 2:
            self._set_from_stats(stats)
        else:  # one row so far: nothing to decompose yet
            self.stats_ = stats
        return self

    def update_limits(self, X):
        """Widen ``pc_min_``/``pc_max_`` (all components) by the projections of ``X``."""
        check_is_fitted(self, "all_components_")
        X = self._validate(X, reset=False, where="SynergyModel.update_limits", min_samples=1)
        for i in range(0, X.shape[0], _CHUNK_ROWS):
            Z = (X[i : i + _CHUNK_ROWS] - self.mean_) @ self.all_components_.T
            self.pc_min_ = np.minimum(self.pc_min_, Z.min(axis=0))
            self.pc_max_ = np.maximum(self.pc_max_, Z.max(axis=0))
        return self

    def _validate(self, X, *, reset, where, min_samples=2):
        try:
            return _sk_validate_data(
                self, X, reset=reset, dtype=np.float64, ensure_min_samples=min_samples
            )
        except ValueError as err:
            if isinstance(err, SynergyError):
                raise
            raise SynergyError(where, str(err)) from err

    def _set_from_stats(self, stats: SufficientStats) -> None:
        if stats.n < 2:
            raise SynergyError("SynergyModel", f"needs at least 2 samples, got {stats.n} sample(s)")
        comps, evals, ratio = _spectrum(stats)
        self.stats_ = stats
        self.mean_ = stats.mean.copy()
        self.joint_min_ = stats.min.copy()
        self.joint_max_ = stats.max.copy()
        self.n_samples_ = int(stats.n)
        self.all_components_ = comps
        self.all_explained_variance_ = evals
        self.all_explained_variance_ratio_ = ratio
        d = stats.n_features
        self.pc_min_ = np.full(d, np.inf)
        self.pc_max_ = np.full(d, -np.inf)
        self._select(self.n_components)

    def _select(self, n_components) -> None:
        self.n_components_ = self.n_components_for(n_components)
        k = self.n_components_
        self.components_ = self.all_components_[:k]
        self.explained_variance_ = self.all_explained_variance_[:k]
        self.explained_variance_ratio_ = self.all_explained_variance_ratio_[:k]

    # -- choosing the number of PCs without refitting
    def n_components_for(self, n_components) -> int:
        """Number of PCs meant by ``n_components`` (None, int or variance fraction in (0, 1))."""
        return _pc_count(self, n_components)

    def with_n_components(self, n_components) -> "SynergyModel":
        """A copy using ``n_components`` PCs (no refit: the full spectrum is kept)."""
        check_is_fitted(self, "all_components_")
        out = SynergyModel(n_components=n_components)
        out.__dict__.update({k: v for k, v in self.__dict__.items() if k.endswith("_")})
        out._select(n_components)
        return out

    @classmethod
    def from_arrays(
        cls, *, components, mean, explained_variance, explained_variance_ratio,
        pc_min, pc_max, joint_min, joint_max, n_samples, n_components=None,
    ) -> "SynergyModel":
        """A fitted model from stored arrays (full spectrum, as in a bundle)."""
        return _from_arrays(components, mean, explained_variance, explained_variance_ratio, pc_min, pc_max,
                            joint_min, joint_max, n_samples, n_components)

    # -- using the model
    def transform(self, X):
        """PC coordinates ``(X - mean_) @ components_.T`` (N × n_components_)."""
        check_is_fitted(self, "components_")
        X = self._validate(X, reset=False, where="SynergyModel.transform", min_samples=1)
        return (X - self.mean_) @ self.components_.T

    def inverse_transform(self, Z):
        """Postures ``Z @ components_ + mean_`` from PC coordinates."""
        check_is_fitted(self, "components_")
        Z = np.asarray(Z, dtype=float)
        return Z @ self.components_ + self.mean_

    def posture(self, coef_sd, clip: bool = False) -> np.ndarray:
        """The posture ``μ + Σᵢ aᵢ σᵢ Cᵢ``: ``aᵢ`` standard deviations along each of the first PCs.

        Parameters
        ----------
        coef_sd : array (..., k)
            Multiples ``a`` of the standard deviations σ (``sqrt(all_explained_variance_)``) of PCs 1..k.
        clip : bool
            Clip each ``aᵢσᵢ`` to the PC limits ``[pc_min_, pc_max_]`` (keeps the posture among the
            training data's extremes along each PC).

        Returns
        -------
        ndarray (..., D)

        Examples
        --------
        >>> X = np.random.default_rng(0).normal(size=(500, 3)) @ np.diag([2.0, 1.0, 0.1])
        >>> m = SynergyModel().fit(X)
        >>> sd = np.sqrt(m.all_explained_variance_)
        >>> (m.transform(m.posture([[1.5, -1.0]])) / sd).round(6) + 0.0    # back in σ units
        array([[ 1.5, -1. ,  0. ]])
        >>> bool(np.allclose(m.posture([]), m.mean_))
        True
        >>> bool(np.isclose(m.transform(m.posture([[9.0]], clip=True))[0, 0], m.pc_max_[0]))
        True
        """
        check_is_fitted(self, "all_components_")
        a = np.asarray(coef_sd, dtype=float)
        k = a.shape[-1] if a.ndim else -1
        if not 0 <= k <= self.all_components_.shape[0]:
            raise SynergyError("posture", f"coef_sd must end in an axis of 0..{self.all_components_.shape[0]} "
                                          f"PCs, got shape {a.shape}")
        z = a * np.sqrt(self.all_explained_variance_[:k])
        if clip:
            z = np.clip(z, self.pc_min_[:k], self.pc_max_[:k])
        return self.mean_ + z @ self.all_components_[:k]

    @property
    def _n_features_out(self):
        return self.n_components_

    def reconstruction_error(self, X, k: int | None = None) -> np.ndarray:
        """Per-DoF RMS error (radians) of reconstructing ``X`` from the first ``k`` PCs."""
        check_is_fitted(self, "all_components_")
        X = as_2d_finite(X, "SynergyModel.reconstruction_error")
        k = self.n_components_ if k is None else k
        d = self.all_components_.shape[0]
        if not 0 <= k <= d:
            raise SynergyError("reconstruction_error", f"k must be in 0..{d}, got {k}")
        return _rms_residual(X - self.mean_, self.all_components_[:k])

    def reconstruction_curve(self, X_heldout) -> np.ndarray:
        """Per-DoF RMS error (radians) for k = 0..D PCs, shape (D + 1, D).

        The overall RMS is ``np.sqrt((curve ** 2).mean(axis=1))``.
        """
        check_is_fitted(self, "all_components_")
        X = as_2d_finite(X_heldout, "SynergyModel.reconstruction_curve")
        return np.sqrt(sq_error_curve(self, X) / X.shape[0])


def _spectrum(stats: SufficientStats):
    """``(components, variances, variance ratios)`` of the covariance of ``stats`` (``ddof=1``): all PCs as
    rows (:func:`_orient`), largest variance first, negative round-off clipped to 0."""
    cov = stats.covariance(ddof=1)
    evals, evecs = np.linalg.eigh(cov)
    order = np.argsort(evals)[::-1]
    evals = np.clip(evals[order], 0.0, None)
    comps = _orient(evecs[:, order].T)
    total = float(np.trace(cov))
    return comps, evals, (evals / total if total > 0 else np.zeros_like(evals))


def _pc_count(model: SynergyModel, n_components) -> int:
    """See :meth:`SynergyModel.n_components_for`."""
    d = model.all_components_.shape[0]
    if n_components is None:
        return min(model.n_samples_, d)
    if isinstance(n_components, (bool, np.bool_)):
        raise SynergyError("n_components", f"must be an int or a fraction, got {n_components!r}")
    if isinstance(n_components, Integral):
        if not 1 <= n_components <= d:
            raise SynergyError("n_components", f"must be in 1..{d}, got {n_components}")
        return int(n_components)
    if isinstance(n_components, Real) and 0.0 < n_components < 1.0:
        cum = np.cumsum(model.all_explained_variance_ratio_)
        # Tolerance so that a fraction reached up to rounding counts as reached.
        return int(min(np.searchsorted(cum, n_components - 1e-12, side="left") + 1, d))
    raise SynergyError(
        "n_components", f"must be None, an int 1..{d} or a float in (0, 1), got {n_components!r}"
    )


def _rms_residual(Xc: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Per-DoF RMS of the centred rows ``Xc`` less their projection onto the orthonormal rows of ``C``."""
    R = Xc - (Xc @ C.T) @ C
    return np.sqrt(np.mean(R * R, axis=0))


def _from_arrays(components, mean, explained_variance, explained_variance_ratio, pc_min, pc_max,
                 joint_min, joint_max, n_samples, n_components) -> SynergyModel:
    """See :meth:`SynergyModel.from_arrays`."""
    model = SynergyModel(n_components=n_components)
    model.all_components_ = np.asarray(components, dtype=float)
    model.mean_ = np.asarray(mean, dtype=float)
    model.all_explained_variance_ = np.asarray(explained_variance, dtype=float)
    model.all_explained_variance_ratio_ = np.asarray(explained_variance_ratio, dtype=float)
    model.pc_min_ = np.asarray(pc_min, dtype=float)
    model.pc_max_ = np.asarray(pc_max, dtype=float)
    model.joint_min_ = np.asarray(joint_min, dtype=float)
    model.joint_max_ = np.asarray(joint_max, dtype=float)
    model.n_samples_ = int(n_samples)
    model.n_features_in_ = model.mean_.shape[0]
    # Statistics rebuilt from the spectrum, so that partial_fit can extend a stored model.
    C, ev = model.all_components_, model.all_explained_variance_
    if C.shape[0] == C.shape[1]:
        model.stats_ = SufficientStats(
            model.n_samples_, model.mean_.copy(), np.zeros_like(model.mean_),
            (model.n_samples_ - 1) * (C.T * ev) @ C, model.joint_min_.copy(), model.joint_max_.copy(),
        )
    model._select(n_components)
    return model


def _orient(comps: np.ndarray) -> np.ndarray:
    """Flip rows so the largest-magnitude entry of each is positive."""
    idx = np.argmax(np.abs(comps), axis=1)
    signs = np.sign(comps[np.arange(comps.shape[0]), idx])
    signs[signs == 0] = 1.0
    return comps * signs[:, None]


def sq_error_curve(model: SynergyModel, X: np.ndarray) -> np.ndarray:
    """Per-DoF sum of squared reconstruction errors for k = 0..D, shape (D + 1, D)."""
    C = model.all_components_
    d = C.shape[0]
    out = np.empty((d + 1, X.shape[1]))
    for i in range(0, X.shape[0], _CHUNK_ROWS):
        R = X[i : i + _CHUNK_ROWS] - model.mean_
        Z = R @ C.T
        part = np.empty_like(out)
        part[0] = np.sum(R * R, axis=0)
        for k in range(d):
            R -= np.outer(Z[:, k], C[k])
            part[k + 1] = np.sum(R * R, axis=0)
        out = part if i == 0 else out + part
    return out
