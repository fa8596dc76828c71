"""Errors of the tracker package: each names the file (or object) and the reason."""
from handmodel.errors import ToolkitError


class TrackerError(ToolkitError):
    """Base of the tracker package's bad-input errors."""


class RecordingError(TrackerError):
    """A recording folder, its metadata or one of its frames is invalid."""
