"""Errors of the synergy package: each names the file (or object) and the reason."""
from handmodel.errors import ToolkitError


class SynergyError(ToolkitError):
    """Base of the synergy package's bad-input errors."""


class C3DError(SynergyError):
    """A C3D file cannot be read or holds no usable marker data."""


class MarkerSetError(SynergyError):
    """A marker-set file is invalid, or a trial lacks the markers a set requires."""


class BundleError(SynergyError):
    """A synergy bundle is missing, malformed, tampered with, or would be overwritten."""


class TaskMapError(SynergyError):
    """A task map file is invalid."""
