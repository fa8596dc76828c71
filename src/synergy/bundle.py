"""Synergy bundles: immutable, versioned ``<name>-<version>.npz`` files, and their registries.

A bundle holds the full PCA of a training set (arrays listed in :data:`ARRAY_NAMES`)
plus a JSON ``manifest`` (``data_schema/synergy-bundle.schema.json``) with provenance,
a hash of the arrays and a hash of the manifest itself (so neither can be edited unnoticed). A registry
is a folder of bundles (:mod:`synergy.registry`); lookups search the folders given by the caller, then
``SYNERGY_PATH`` (``os.pathsep``-separated), then the shipped ``models/synergies``.

Examples
--------
>>> import numpy as np, tempfile
>>> from synergy.pca import SynergyModel
>>> X = np.random.default_rng(0).normal(size=(200, 20)) * 0.1
>>> reg = tempfile.mkdtemp()
>>> p = save_bundle(SynergyModel(2).fit(X), "demo", registry=reg)
>>> p.name
'demo-1.0.0.npz'
>>> b = load_bundle("demo", registries=[reg])
>>> sp = b.subspace()                       # handmodel.Subspace: 6 pose DoF + 2 PCs
>>> sp.dim, sp.M.shape
(8, (26, 8))
"""
from __future__ import annotations

import io
import json
import os
import zipfile
from dataclasses import dataclass
from datetime import datetime, timezone
from functools import lru_cache
from importlib.metadata import PackageNotFoundError, version as _dist_version
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import jsonschema
import numpy as np

from handmodel.dofs import POSTURE_DOF_NAMES
from handmodel.errors import HandModelError
from handmodel import fileio
from handmodel.fileio import (atomic_write_bytes, first_non_finite, load_npz, manifest_sha256, models_dir,
                             schema_path, sha256_file)
from handmodel.model import HandModel
from handmodel.subspace import Subspace
from synergy.errors import BundleError, SynergyError
from synergy.registry import (FILE_RE, VERSION_RE, BundleRef, check_name_version, list_bundles, next_version,
                              registry_paths, target_registry, version_taken, version_tuple)

if TYPE_CHECKING:  # the annotations only; see read_bundle
    from synergy.pca import SynergyModel

__all__ = [
    "ARRAY_NAMES", "Bundle", "arrays_sha256", "hand_model_ref", "load_bundle", "manifest_sha256", "read_bundle",
    "save_bundle", "ranked_bundles", "select_bundle", "selection_key",
]

#: Arrays of a bundle, in the canonical order used by :func:`arrays_sha256`.
ARRAY_NAMES = (
    "components", "mean", "explained_variance", "explained_variance_ratio",
    "pc_min", "pc_max", "joint_min", "joint_max", "dof_names",
)
SCHEMA_VERSION = 2  # 2: the manifest carries manifest_sha256
GENERATOR = "synergistic-hand-tracking"


# ----------------------------------------------------------------------------- manifest helpers
@lru_cache(maxsize=1)
def _validator():
    with open(schema_path("synergy-bundle"), encoding="utf-8") as fh:
        return jsonschema.Draft202012Validator(json.load(fh))


def _check_manifest(manifest, where) -> None:
    if bad := first_non_finite(manifest):  # json.loads reads NaN/Infinity, and no schema bound catches NaN
        raise BundleError(where, f"malformed manifest: {'.'.join(map(str, bad[0]))}: {bad[1]} is not a finite number")
    errors = sorted(_validator().iter_errors(manifest), key=lambda e: list(map(str, e.absolute_path)))
    if errors:
        err = errors[0]
        field = ".".join(str(p) for p in err.absolute_path) or "manifest"
        raise BundleError(where, f"malformed manifest: {field}: {err.message}")


def arrays_sha256(arrays: dict[str, np.ndarray]) -> str:
    """The bundle arrays' seal: :func:`handmodel.fileio.arrays_sha256` over :data:`ARRAY_NAMES`."""
    return fileio.arrays_sha256(arrays, ARRAY_NAMES)


def hand_model_ref(name: str = "default", sha256: str | None = None) -> dict:
    """``{name, sha256}`` of a hand model; the hash defaults to ``models/hands/<name>.yaml``'s."""
    if sha256 is None:
        f = models_dir() / "hands" / f"{name}.yaml"
        sha256 = sha256_file(f) if f.is_file() else None
    return {"name": name, "sha256": sha256}


def generator_version() -> str:
    """The installed toolchain's version (``unknown`` in a source tree run without installing)."""
    try:
        return _dist_version(GENERATOR)
    except PackageNotFoundError:
        return "unknown"


# ----------------------------------------------------------------------------- bundle object
@dataclass(frozen=True, eq=False)
class Bundle:
    """A loaded bundle: fitted ``model``, ``manifest`` dict, ``path`` and ``dof_names``."""

    model: SynergyModel
    manifest: dict
    path: Path
    dof_names: tuple[str, ...]

    @property
    def name(self) -> str:
        return self.manifest["name"]

    @property
    def version(self) -> str:
        return self.manifest["version"]

    @property
    def tasks(self) -> list[str]:
        return list(self.manifest["tasks"])

    @property
    def spec(self) -> str:
        return f"{self.name}@{self.version}"

    def subspace(self, n_components=None, hand=None) -> Subspace:
        """The parameter subspace of the first PCs (pose DoF + PCs, with the PC limits) for the solver.

        ``n_components``: int, variance fraction in (0, 1), or ``None`` for the bundle's default.
        ``hand``: the :class:`~handmodel.HandModel` whose θ it spans (default: the bundle's hand model).
        """
        m = self.model
        try:
            k = m.n_components_ if n_components is None else m.n_components_for(n_components)
        except SynergyError as exc:
            raise BundleError(self.path, exc.reason) from None
        hand = self.hand_model() if hand is None else hand
        if tuple(hand.posture_names) != self.dof_names:
            raise BundleError(self.path, f"the bundle's DoF names are not the posture DoF of hand model {hand.name!r}")
        return Subspace.from_synergies(hand, m.all_components_, m.mean_, m.pc_min_, m.pc_max_, n_components=k)

    def hand_model(self) -> HandModel:
        """The hand model the bundle's angles refer to (by the name in its manifest)."""
        name = self.manifest["hand_model"]["name"]
        try:
            return _load_hand(name)
        except HandModelError as exc:
            raise BundleError(self.path, f"hand model {name!r}: {exc.reason}") from None


@lru_cache(maxsize=4)
def _load_hand(name: str) -> HandModel:
    return HandModel.load(name)


def _arrays_of(model: SynergyModel, dof_names: Sequence[str]) -> dict[str, np.ndarray]:
    return {
        "components": np.asarray(model.all_components_, dtype="<f8"),
        "mean": np.asarray(model.mean_, dtype="<f8"),
        "explained_variance": np.asarray(model.all_explained_variance_, dtype="<f8"),
        "explained_variance_ratio": np.asarray(model.all_explained_variance_ratio_, dtype="<f8"),
        "pc_min": np.asarray(model.pc_min_, dtype="<f8"),
        "pc_max": np.asarray(model.pc_max_, dtype="<f8"),
        "joint_min": np.asarray(model.joint_min_, dtype="<f8"),
        "joint_max": np.asarray(model.joint_max_, dtype="<f8"),
        "dof_names": np.array([str(n) for n in dof_names], dtype=str),
    }


def save_bundle(
    model: SynergyModel,
    name: str,
    version: str | None = None,
    *,
    registry: str | os.PathLike | None = None,
    dof_names: Sequence[str] | None = None,
    tasks: Sequence[str] = (),
    sources: Sequence[dict] = (),
    n_trials: int | None = None,
    hand_model: str = "default",
    hand_model_sha256: str | None = None,
    heldout: dict | None = None,
) -> Path:
    """Write ``model`` as ``<registry>/<name>-<version>.npz``; never overwrites.

    ``version=None`` takes the next patch after the highest ``name`` in the registry;
    ``registry=None`` takes the first ``SYNERGY_PATH`` folder. ``sources`` are
    ``{path, sha256, task, frames}`` dicts; ``heldout`` is ``{method, rms_rad}``.
    Returns the path written.
    """
    if not hasattr(model, "all_components_"):
        raise BundleError(name, "model is not fitted")
    if not (np.isfinite(model.pc_min_).all() and np.isfinite(model.pc_max_).all()):
        raise BundleError(name, "PC limits are missing: call model.update_limits(X) on the training data")
    check_name_version(name, version)
    d = model.mean_.shape[0]
    if dof_names is None:
        dof_names = getattr(model, "feature_names_in_", None)
        if dof_names is None:
            if d != len(POSTURE_DOF_NAMES):
                raise BundleError(name, f"dof_names needed for a {d}-DoF model")
            dof_names = POSTURE_DOF_NAMES
    if len(dof_names) != d:
        raise BundleError(name, f"{len(dof_names)} dof_names for a {d}-DoF model")
    folder = target_registry(registry, name)
    arrays = _arrays_of(model, dof_names)
    variance = model.n_components if isinstance(model.n_components, float) else None
    manifest = {
        "schema_version": SCHEMA_VERSION,
        "name": name,
        "version": None,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds").replace("+00:00", "Z"),
        "generator": {"name": GENERATOR, "version": generator_version()},
        "hand_model": hand_model_ref(hand_model, hand_model_sha256),
        "units": "rad",
        "tasks": list(dict.fromkeys(tasks)),
        "n_samples": int(model.n_samples_),
        "n_trials": int(n_trials if n_trials is not None else max(len(sources), 1)),
        "n_components": int(model.n_components_),
        "variance": variance,
        "sources": [dict(s) for s in sources],
        "arrays_sha256": arrays_sha256(arrays),
    }
    if heldout is not None:
        manifest["heldout"] = {"method": heldout["method"], "rms_rad": [float(x) for x in heldout["rms_rad"]]}
    for attempt in range(20):
        ver = version or next_version(name, folder)
        manifest["version"] = ver
        manifest["manifest_sha256"] = manifest_sha256(manifest)
        _check_manifest(manifest, name)
        buf = io.BytesIO()
        np.savez(buf, **arrays, manifest=np.array(json.dumps(manifest, indent=1)))
        path = folder / f"{name}-{ver}.npz"
        try:
            return atomic_write_bytes(path, buf.getvalue(), overwrite=False)
        except FileExistsError:
            if version is not None:
                raise version_taken(path, ver) from None
            # A concurrent writer took this version: take the next one.
        except OSError as exc:
            raise BundleError(path, f"cannot write ({exc.strerror or exc})") from None
    raise BundleError(folder, f"could not find a free version for {name!r}")


def read_bundle(path: str | os.PathLike) -> Bundle:
    """Load and verify one bundle file (schema, manifest hash, shapes, arrays hash)."""
    path = Path(path)
    arrays, manifest = _verified(path)
    # imported here: scikit-learn takes seconds to import, and listing bundles needs no model
    from synergy.pca import SynergyModel

    model = SynergyModel.from_arrays(
        **{k: arrays[k] for k in ARRAY_NAMES if k != "dof_names"},
        n_samples=manifest["n_samples"],
        n_components=manifest["n_components"],
    )
    return Bundle(model, manifest, path, tuple(str(s) for s in arrays["dof_names"]))


def verified_manifest(path: str | os.PathLike) -> dict:
    """The manifest of a bundle file after every check :func:`read_bundle` makes (``synergy list``
    shows it without building the model)."""
    return _verified(Path(path))[1]


def _verified(path: Path) -> tuple[dict, dict]:
    """``(arrays, manifest)`` of a bundle file, verified (schema, manifest hash, shapes, arrays hash,
    the file's name against the manifest)."""
    if not path.is_file():
        raise BundleError(path, "no such bundle file")
    try:
        with load_npz(path, BundleError, what="bundle .npz") as z:  # bounded: declared sizes checked before unpacking
            missing = [n for n in (*ARRAY_NAMES, "manifest") if n not in z.files]
            if missing:
                raise BundleError(path, f"missing array(s): {', '.join(missing)}")
            arrays = {n: z[n] for n in ARRAY_NAMES}
            raw = z["manifest"]
    except BundleError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise BundleError(path, f"not a readable bundle .npz ({exc})") from None
    if raw.ndim != 0 or raw.dtype.kind != "U":
        raise BundleError(path, "manifest must be a 0-d unicode array (JSON string)")
    try:
        manifest = json.loads(str(raw[()]))
    except json.JSONDecodeError as exc:
        raise BundleError(path, f"malformed manifest: not JSON ({exc.msg} at char {exc.pos})") from None
    if isinstance(manifest, dict) and manifest.get("schema_version") == 1:
        raise BundleError(path, "schema_version 1 bundle: its manifest is not hashed; refit it with this version "
                                "of synergy (the sources are listed in its manifest)")
    _check_manifest(manifest, path)
    if manifest_sha256(manifest) != manifest["manifest_sha256"]:
        raise BundleError(path, "manifest does not match its manifest_sha256 (manifest edited?)")
    _check_arrays(arrays, manifest, path)
    if arrays_sha256(arrays) != manifest["arrays_sha256"]:
        raise BundleError(path, "arrays do not match the manifest's arrays_sha256 (file modified?)")
    m = FILE_RE.match(path.name)
    if m and (m["name"], m["version"]) != (manifest["name"], manifest["version"]):
        raise BundleError(
            path, f"file name says {m['name']}@{m['version']} but manifest says "
            f"{manifest['name']}@{manifest['version']}"
        )
    return arrays, manifest


def _check_arrays(a: dict[str, np.ndarray], manifest: dict, path: Path) -> None:
    names = a["dof_names"]
    if names.dtype.kind != "U" or names.ndim != 1 or names.size == 0:
        raise BundleError(path, f"dof_names must be a 1-D unicode array, got {names.dtype} {names.shape}")
    d = names.size
    p = a["components"].shape[0] if a["components"].ndim == 2 else -1
    want = {
        "components": (p, d), "mean": (d,), "explained_variance": (p,),
        "explained_variance_ratio": (p,), "pc_min": (p,), "pc_max": (p,),
        "joint_min": (d,), "joint_max": (d,),
    }
    for k, shape in want.items():
        arr = a[k]
        if arr.dtype.kind != "f" or arr.shape != shape or not 1 <= p <= d:
            raise BundleError(
                path, f"array {k} has shape {arr.shape} ({arr.dtype}); expected "
                f"{('PCs', d) if k == 'components' else shape} float for {d} DoF"
            )
        if not np.isfinite(arr).all():
            raise BundleError(path, f"array {k} holds NaN or infinity")
    if manifest["n_components"] > p:
        raise BundleError(path, f"manifest n_components {manifest['n_components']} > {p} stored PCs")


def load_bundle(spec: str | os.PathLike, registries: Sequence[str | os.PathLike] | None = None) -> Bundle:
    """Load a bundle by ``NAME`` (highest version), ``NAME@VERSION`` or path to a ``.npz``."""
    s = os.fspath(spec)
    if s.endswith(".npz") or os.sep in s or "/" in s or (os.altsep and os.altsep in s):
        return read_bundle(s)
    name, _, version = s.partition("@")
    if version and not VERSION_RE.match(version):
        raise BundleError(s, f"bad version {version!r}: expected NAME@MAJOR.MINOR.PATCH")
    refs = list_bundles(registries)
    hits = [r for r in refs if r.name == name and (not version or r.version == version)]
    if not hits:
        where = ", ".join(str(p) for p in registry_paths(registries))
        same = sorted({r.version for r in refs if r.name == name}, key=version_tuple)
        hint = f" (versions: {', '.join(same)})" if same else f" (bundles: {', '.join(sorted({r.name for r in refs})) or 'none'})"
        raise BundleError(s, f"no such bundle in registries {where}{hint}")
    best = max(hits, key=lambda r: r.version_key)  # max keeps the first (earlier registry) on ties
    return read_bundle(best.path)


def select_bundle(task: str, registries: Sequence[str | os.PathLike] | None = None) -> Bundle:
    """The bundle for ``task``: labelled with it, fewest tasks (most specific), then most samples, then
    the name (:func:`ranked_bundles`' first).

    Only the highest version of each name counts; unreadable bundles are passed over.
    """
    return ranked_bundles(task, registries)[0]


def selection_key(b: Bundle) -> tuple:
    """How :func:`select_bundle` ranks the bundles of a task: fewest tasks, most samples, then name."""
    return (len(b.tasks), -b.manifest["n_samples"], b.name)


def ranked_bundles(task: str, registries: Sequence[str | os.PathLike] | None = None) -> list[Bundle]:
    """Every bundle labelled with ``task`` (the highest version of each name), best first by
    :func:`selection_key`; a task no bundle carries is an error naming the tasks there are."""
    latest: dict[str, BundleRef] = {}
    for r in list_bundles(registries):
        if r.name not in latest or r.version_key > latest[r.name].version_key:
            latest[r.name] = r
    cands, known = [], set()
    for ref in latest.values():
        try:
            b = read_bundle(ref.path)
        except BundleError:
            continue
        known.update(b.tasks)
        if task in b.tasks:
            cands.append(b)
    if not cands:
        raise BundleError(
            f"task {task}", f"no bundle is labelled with this task (tasks: {', '.join(sorted(known)) or 'none'})"
        )
    return sorted(cands, key=selection_key)
