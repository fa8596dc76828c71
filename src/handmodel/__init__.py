"""Kinematic hand model, geometry and the shared damped Gauss-Newton IK solver.

Heavy modules (numba kernels, trimesh) are imported lazily on first use.
"""
from .errors import HandModelError, SolverError, ToolkitError
from .model import HandModel

__all__ = ["HandModel", "HandModelError", "SolverError", "ToolkitError", "fit_keypoints", "solve", "Subspace",
           "SolverSettings", "hierarchical_schedule"]


def __getattr__(name):
    if name in ("fit_keypoints", "solve", "SolverSettings", "SolveReport"):
        from . import solver

        return getattr(solver, name)
    if name in ("Subspace", "hierarchical_schedule"):
        from . import subspace

        return getattr(subspace, name)
    raise AttributeError(name)
