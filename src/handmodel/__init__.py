"""Kinematic hand model, geometry and the shared damped Gauss-Newton IK solver.

Everything is imported lazily (``--help`` of the CLIs must not pay for numpy or numba).
"""
from .errors import HandModelError, SolverError, ToolkitError

__all__ = ["HandModel", "HandModelError", "SolverError", "ToolkitError", "fit_keypoints", "solve", "Subspace",
           "SolverSettings", "hierarchical_schedule"]

_LAZY = {"HandModel": "model", "fit_keypoints": "solver", "solve": "solver", "SolverSettings": "solver",
         "SolveReport": "solver", "Subspace": "subspace", "hierarchical_schedule": "subspace"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(name)
