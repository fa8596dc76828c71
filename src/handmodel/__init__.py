"""Kinematic hand model, DoF names and limit sets, geometry and the shared damped Gauss-Newton IK solver.

Everything is imported lazily (``--help`` of the CLIs must not pay for numpy or numba).
"""
from .errors import HandModelError, SolverError, ToolkitError

__all__ = ["ANATOMICAL_LIMITS", "DOF_NAMES", "HandModel", "HandModelError", "POSE_DOF_NAMES", "POSTURE_DOF_NAMES",
           "SolveReport", "SolverError", "SolverSettings", "Subspace", "ToolkitError", "anatomical_limits",
           "fit_keypoints", "hierarchical_schedule", "solve"]

_LAZY = {"HandModel": "model", "fit_keypoints": "solver", "solve": "solver", "SolverSettings": "solver",
         "SolveReport": "solver", "Subspace": "subspace", "hierarchical_schedule": "subspace",
         "DOF_NAMES": "dofs", "POSE_DOF_NAMES": "dofs", "POSTURE_DOF_NAMES": "dofs", "ANATOMICAL_LIMITS": "dofs",
         "anatomical_limits": "dofs"}


def __getattr__(name):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(name)
