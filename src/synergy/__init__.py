"""Hand synergies from motion capture: C3D → marker IK → joint angles → PCA → versioned bundles.

The user-facing names, imported lazily (``synergy --help`` must not pay for numpy or numba):

>>> import synergy
>>> [n for n in synergy.__all__ if getattr(synergy, n, None) is None]
[]
"""
from .errors import SynergyError

# name -> the module (under synergy) that owns it
_LAZY = {
    "SynergyModel": "pca", "SufficientStats": "pca",
    "Bundle": "bundle", "load_bundle": "bundle", "read_bundle": "bundle", "save_bundle": "bundle",
    "select_bundle": "bundle", "list_bundles": "registry",
    "read_c3d": "c3d",
    "markers_to_angles": "angles", "read_angles_csv": "angles", "write_angles_csv": "angles",
    "read_trial": "fit", "fit_trials": "fit", "bundle_from_trials": "fit",
    "PosturePrior": "prior",
}

__all__ = sorted(["SynergyError", *_LAZY])


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module 'synergy' has no attribute {name!r}")


def __dir__():
    return __all__
