"""Registries of synergy bundles: folders of immutable ``<name>-<version>.npz`` files, searched in
order — the folders the caller gives, then ``SYNERGY_PATH`` (``os.pathsep``-separated), then the shipped
``models/synergies`` — and the names and versions a new bundle may take. The files themselves (save,
read, verify, load by name, select by task): :mod:`synergy.bundle`.

Examples
--------
>>> import tempfile
>>> reg = tempfile.mkdtemp()
>>> next_version("demo", reg), version_tuple("2.3.10") > version_tuple("2.3.9")
('1.0.0', True)
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from handmodel.fileio import models_dir
from synergy.errors import BundleError

__all__ = [
    "BundleRef", "FILE_RE", "VERSION_RE", "check_name_version", "check_new_bundle", "list_bundles", "next_version",
    "registry_paths", "target_registry", "version_taken", "version_tuple",
]

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: A version (``MAJOR.MINOR.PATCH``) and a bundle's file name (``<name>-<version>.npz``).
VERSION_RE = re.compile(r"^(0|[1-9]\d*)\.(0|[1-9]\d*)\.(0|[1-9]\d*)$")
FILE_RE = re.compile(r"^(?P<name>.+)-(?P<version>(?:0|[1-9]\d*)\.(?:0|[1-9]\d*)\.(?:0|[1-9]\d*))\.npz$")


@dataclass(frozen=True)
class BundleRef:
    """A bundle file found in a registry (from its file name only)."""

    name: str
    version: str
    path: Path

    @property
    def version_key(self) -> tuple[int, int, int]:
        return version_tuple(self.version)


def version_tuple(version: str) -> tuple[int, int, int]:
    """``MAJOR.MINOR.PATCH`` as integers, the order of versions."""
    return tuple(int(x) for x in version.split("."))  # type: ignore[return-value]


def registry_paths(registries: Sequence[str | os.PathLike] | None = None) -> list[Path]:
    """Registry folders in search order: ``registries``, ``SYNERGY_PATH``, shipped."""
    env = [p for p in os.environ.get("SYNERGY_PATH", "").split(os.pathsep) if p.strip()]
    out: list[Path] = []
    seen = set()
    for p in [*(registries or []), *env, models_dir() / "synergies"]:
        p = Path(p).expanduser()
        key = os.path.normcase(os.path.abspath(p))
        if key not in seen:
            seen.add(key)
            out.append(p)
    return out


def list_bundles(registries: Sequence[str | os.PathLike] | None = None) -> list[BundleRef]:
    """Bundle files in all registries, in search order (a name@version may appear twice)."""
    refs = []
    for folder in registry_paths(registries):
        if not folder.is_dir():
            continue
        found = [(FILE_RE.match(f.name), f) for f in folder.iterdir() if f.is_file()]
        found = [BundleRef(m["name"], m["version"], f) for m, f in found if m]
        refs += sorted(found, key=lambda r: (r.name, r.version_key))
    return refs


def next_version(name: str, folder: str | os.PathLike) -> str:
    """Next patch version after the highest ``name`` in ``folder`` (``1.0.0`` if none)."""
    versions = [
        version_tuple(m["version"])
        for f in (Path(folder).iterdir() if Path(folder).is_dir() else ())
        if (m := FILE_RE.match(f.name)) and m["name"] == name
    ]
    if not versions:
        return "1.0.0"
    a, b, c = max(versions)
    return f"{a}.{b}.{c + 1}"


def target_registry(registry: str | os.PathLike | None, name: str) -> Path:
    """The folder a new bundle ``name`` goes into: ``registry``, else the first ``SYNERGY_PATH`` folder.

    Raises
    ------
    BundleError
        Naming the bundle, when neither is given.
    """
    if registry is None:
        env = [p for p in os.environ.get("SYNERGY_PATH", "").split(os.pathsep) if p.strip()]
        if not env:
            raise BundleError(name, "no target registry: pass one (CLI: -o DIR) or set SYNERGY_PATH")
        registry = env[0]
    return Path(registry)


def check_name_version(name: str, version: str | None) -> None:
    """Raise :class:`~synergy.errors.BundleError` for a bundle name or version a file may not carry."""
    if not _NAME_RE.match(name):
        raise BundleError(name, "bad bundle name: use letters, digits, '_', '.', '-'")
    if version is not None and not VERSION_RE.match(version):
        raise BundleError(name, f"bad version {version!r}: expected MAJOR.MINOR.PATCH")


def version_taken(path: Path, version: str) -> BundleError:
    """The error of a version that exists already (bundle versions are immutable)."""
    return BundleError(path, f"version {version} exists; bundle versions are immutable")


def check_new_bundle(name: str, version: str | None = None, registry: str | os.PathLike | None = None) -> Path:
    """Fail now, not after the trials are converted, if :func:`save_bundle` would refuse the bundle.

    Checks the name, the version's form, that there is a target registry and that an explicit
    ``version`` is not there already. :func:`save_bundle` checks all of it again when it writes (another
    writer may take the version in between). Returns the registry folder.

    Examples
    --------
    >>> import tempfile
    >>> reg = tempfile.mkdtemp()
    >>> check_new_bundle("demo", "1.0.0", reg) == Path(reg)
    True
    >>> check_new_bundle("demo", "1.0", reg)
    Traceback (most recent call last):
    ...
    synergy.errors.BundleError: demo: bad version '1.0': expected MAJOR.MINOR.PATCH
    """
    check_name_version(name, version)
    folder = target_registry(registry, name)
    if version is not None:
        path = folder / f"{name}-{version}.npz"
        if path.exists() or path.is_symlink():  # a dangling link would still make the final link fail
            raise version_taken(path, version)
    return folder
