"""What every settings object of the tracker shares: a frozen dataclass that changes by
:meth:`SettingsGroup.replace` (nested groups by a dict), checks itself (:meth:`SettingsGroup.check`)
and has the paper's values (:meth:`SettingsGroup.paper`).

>>> from dataclasses import dataclass, field
>>> @dataclass(frozen=True)
... class Inner(SettingsGroup):
...     mm: float = 1.0
>>> @dataclass(frozen=True)
... class Outer(SettingsGroup):
...     n: int = 2
...     inner: Inner = field(default_factory=Inner)
>>> Outer().replace(n=3, inner=dict(mm=0.5))
Outer(n=3, inner=Inner(mm=0.5))
>>> Outer().replace(inner=Inner(mm=2.0)).inner.mm
2.0
>>> Outer().replace(size=1)
Traceback (most recent call last):
...
tracker.errors.TrackerError: settings: Outer has no field 'size' (it has n, inner)
"""
from __future__ import annotations

import dataclasses

from .errors import TrackerError


class SettingsGroup:
    """Base of the frozen settings dataclasses: ``replace``, ``check`` and ``paper``."""

    def replace(self, **changes):
        """A copy with fields changed by name; a nested group's field takes a dict of its own
        changes (``icp=dict(robust_mm=0.0)``) or a whole group (``icp=IcpSettings(…)``)."""
        names = [f.name for f in dataclasses.fields(self)]
        out = {}
        for k, v in changes.items():
            if k not in names:
                raise TrackerError("settings", f"{type(self).__name__} has no field {k!r} (it has {', '.join(names)})")
            now = getattr(self, k)
            out[k] = now.replace(**v) if isinstance(v, dict) and isinstance(now, SettingsGroup) else v
        return dataclasses.replace(self, **out)

    def check(self):
        """Raise :class:`tracker.errors.TrackerError` (``where``: the field) when a value is out of range."""

    @classmethod
    def paper(cls):
        """The paper's values (Schröder et al. 2014): the defaults unless a group says otherwise."""
        return cls()
