"""Tests of synergy.bundle (files, registries), synergy.fit / synergy.postures (readers, fitting) and of
the ``synergy`` CLI."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

from conftest import ROOT, SHARED_DATA

import numpy as np
import pytest
from typer.testing import CliRunner

from synergy.bundle import (
    ARRAY_NAMES,
    Bundle,
    arrays_sha256,
    load_bundle,
    manifest_sha256,
    read_bundle,
    save_bundle,
    select_bundle,
)
from synergy.cli import app
from synergy.errors import BundleError, SynergyError
from synergy.fit import fit_trials, read_trial
from handmodel import HandModel
from handmodel.dofs import POSE_DOF_NAMES, POSTURE_DOF_NAMES
from handmodel.subspace import Subspace
from synergy.pca import SynergyModel
from synergy.registry import list_bundles, registry_paths

DATA = SHARED_DATA
FINGERFIST = DATA / "htrack_schroeder" / "fingerfist.txt"


@pytest.fixture(autouse=True)
def _no_env_registries(monkeypatch):
    monkeypatch.delenv("SYNERGY_PATH", raising=False)


def postures(n=400, seed=0):
    rng = np.random.default_rng(seed)
    latent = rng.normal(size=(n, 3)) * [0.6, 0.3, 0.1]
    return latent @ rng.normal(size=(3, 20)) + 0.02 * rng.normal(size=(n, 20)) - 0.4


@pytest.fixture
def model():
    return SynergyModel(n_components=0.95).fit(postures())


@pytest.fixture
def reg(tmp_path):
    d = tmp_path / "registry"
    d.mkdir()
    return d


def rewrite(path, out=None, **changes):
    """Re-save a bundle's npz with some arrays (or the manifest) replaced."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays.update(changes)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    Path(out or path).write_bytes(buf.getvalue())
    return Path(out or path)


# ----------------------------------------------------------------------------- round trip
def test_save_load_round_trip_exact(model, reg):
    path = save_bundle(model, "grip", registry=reg, tasks=["grasp"], n_trials=3)
    assert path == reg / "grip-1.0.0.npz"
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == {*ARRAY_NAMES, "manifest"}
        assert z["dof_names"].dtype.kind == "U" and z["manifest"].dtype.kind == "U"
        assert z["manifest"].shape == () and z["components"].shape == (20, 20)
    for spec in ("grip", "grip@1.0.0", str(path)):
        b = load_bundle(spec, registries=[reg])
        assert isinstance(b, Bundle) and b.path == path and b.dof_names == POSTURE_DOF_NAMES
        m = b.model
        for a in ("all_components_", "mean_", "all_explained_variance_", "all_explained_variance_ratio_",
                  "pc_min_", "pc_max_", "joint_min_", "joint_max_", "components_", "explained_variance_"):
            np.testing.assert_array_equal(getattr(m, a), getattr(model, a), err_msg=a)
        assert m.n_components_ == model.n_components_ and m.n_samples_ == 400
        X = postures(50, seed=1)
        np.testing.assert_array_equal(m.transform(X), model.transform(X))
    man = b.manifest
    assert man["name"] == "grip" and man["version"] == "1.0.0" and man["tasks"] == ["grasp"]
    assert man["n_samples"] == 400 and man["n_trials"] == 3 and man["variance"] == 0.95
    assert man["created"].endswith("Z") and man["generator"]["name"] == "synergistic-hand-tracking"
    assert man["hand_model"]["name"] == "default"
    hand = ROOT / "models" / "hands" / "default.yaml"
    assert (man["hand_model"]["sha256"] is None) == (not hand.is_file())


def test_subspace(model, reg):
    b = load_bundle(save_bundle(model, "grip", registry=reg))
    sp = b.subspace()
    assert isinstance(sp, Subspace) and sp.dim == 6 + model.n_components_
    sp2 = b.subspace(2)
    assert sp2.dim == 8 and sp2.M.shape == (26, 8) and list(sp2.pose) == [True] * 6 + [False] * 2
    np.testing.assert_array_equal(sp2.M[6:, 6:], model.all_components_[:2].T)
    np.testing.assert_array_equal(sp2.mu[6:], model.mean_)
    np.testing.assert_array_equal(sp2.lo[6:], model.pc_min_[:2])
    np.testing.assert_array_equal(sp2.hi[6:], model.pc_max_[:2])
    assert np.all(np.isinf(sp2.lo[:6])) and np.all(np.isinf(sp2.hi[:6]))
    theta = np.zeros((400, 26))
    theta[:, 6:] = postures()
    Z = sp2.to_alpha(theta)[:, 6:]
    assert np.all((Z >= sp2.lo[6:]) & (Z <= sp2.hi[6:]))
    assert b.subspace(0.5).dim == 6 + model.n_components_for(0.5)
    right = HandModel.load(right=True)
    assert b.subspace(2, hand=right).dim == 8
    with pytest.raises(BundleError, match="1..20"):
        b.subspace(21)
    other = load_bundle(save_bundle(SynergyModel(2).fit(postures()[:, :5]), "five", registry=reg,
                                    dof_names=list("abcde")))
    with pytest.raises(BundleError, match="posture DoF of hand model") as info:
        other.subspace()
    assert str(info.value).startswith(str(other.path))


def test_loaded_model_can_be_extended(reg):
    X, more = postures(400, seed=0), postures(100, seed=5)
    b = load_bundle(save_bundle(SynergyModel().fit(X), "grip", registry=reg))
    ext = b.model.partial_fit(more).update_limits(X).update_limits(more)
    ref = SynergyModel().fit(np.vstack([X, more]))
    np.testing.assert_allclose(ext.all_explained_variance_, ref.all_explained_variance_, rtol=1e-9, atol=1e-13)
    np.testing.assert_allclose(ext.components_[:3], ref.components_[:3], atol=1e-8)
    np.testing.assert_allclose(ext.pc_max_[:3], ref.pc_max_[:3], atol=1e-8)
    assert ext.n_samples_ == 500


def test_versions_are_immutable_and_bump(model, reg):
    p1 = save_bundle(model, "grip", registry=reg)
    before = p1.read_bytes()
    p2 = save_bundle(model, "grip", registry=reg)
    assert p2.name == "grip-1.0.1.npz"
    save_bundle(model, "grip", "2.3.9", registry=reg)
    assert save_bundle(model, "grip", registry=reg).name == "grip-2.3.10.npz"
    with pytest.raises(BundleError, match="immutable") as info:
        save_bundle(model, "grip", "1.0.0", registry=reg)
    assert str(p1) in str(info.value)
    assert p1.read_bytes() == before
    assert load_bundle("grip", registries=[reg]).version == "2.3.10"
    assert [r.version for r in list_bundles([reg]) if r.name == "grip"] == ["1.0.0", "1.0.1", "2.3.9", "2.3.10"]
    assert not [f for f in reg.iterdir() if f.name.startswith(".")]  # no temp files left


def test_tampered_bundle_is_rejected(model, reg):
    path = save_bundle(model, "grip", registry=reg)
    with np.load(path, allow_pickle=False) as z:
        comps = z["components"].copy()
    comps[3, 7] += 1e-12
    rewrite(path, components=comps)
    with pytest.raises(BundleError, match="arrays_sha256") as info:
        load_bundle(str(path))
    assert str(info.value).startswith(f"{path}: ")


def test_verified_manifest_makes_every_check_of_read_bundle(model, reg, tmp_path):
    """``synergy list`` verifies bundles without building the model: the same manifest on a good file,
    the same refusal of a tampered or renamed one."""
    from synergy.bundle import verified_manifest

    path = save_bundle(model, "grip", registry=reg)
    assert verified_manifest(path) == read_bundle(path).manifest
    renamed = tmp_path / "other-2.0.0.npz"
    renamed.write_bytes(path.read_bytes())
    with pytest.raises(BundleError, match="file name says"):
        verified_manifest(renamed)
    with np.load(path, allow_pickle=False) as z:
        comps = z["components"].copy()
    comps[0, 0] += 1e-12
    rewrite(path, components=comps)
    with pytest.raises(BundleError, match="arrays_sha256"):
        verified_manifest(path)


def test_listing_bundles_does_not_import_scikit_learn(model, reg):
    """``synergy list`` answers without scikit-learn (seconds of import for a listing; checked by the
    modules loaded, not by a wall clock)."""
    save_bundle(model, "grip", registry=reg)
    code = ("import sys; from typer.testing import CliRunner; from synergy.cli import app; "
            f"r = CliRunner().invoke(app, ['list', '-r', {str(reg)!r}]); "
            "print(r.exit_code, 'grip' in r.output, 'sklearn' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["0", "True", "False"], out.stdout + out.stderr


def test_arrays_hash_covers_every_array(model, reg):
    path = save_bundle(model, "grip", registry=reg)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in ARRAY_NAMES}
    ref = arrays_sha256(arrays)
    for k in ARRAY_NAMES:
        changed = dict(arrays)
        if k == "dof_names":
            changed[k] = np.array(["x", *arrays[k][1:]])
        else:
            changed[k] = arrays[k].copy()
            changed[k].flat[0] = np.nextafter(changed[k].flat[0], np.inf)
        assert arrays_sha256(changed) != ref, k


def _manifest(path):
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["manifest"][()]))


@pytest.mark.parametrize(
    "change, fragment",
    [
        (lambda m: "{not json", "not JSON"),
        (lambda m: {k: v for k, v in m.items() if k != "arrays_sha256"}, "'arrays_sha256' is a required property"),
        (lambda m: {**m, "n_samples": "many"}, "n_samples"),
        (lambda m: {**m, "version": "1.0"}, "version"),
        (lambda m: {**m, "sources": [{"path": "a.csv"}]}, "sources.0"),
        (lambda m: {**m, "schema_version": 99}, "schema_version"),
    ],
    ids=["not-json", "missing-field", "wrong-type", "bad-version", "bad-source", "schema-version"],
)
def test_malformed_manifest(model, reg, change, fragment):
    path = save_bundle(model, "grip", registry=reg)
    new = change(_manifest(path))
    rewrite(path, manifest=np.array(new if isinstance(new, str) else json.dumps(new)))
    with pytest.raises(BundleError, match="malformed manifest") as info:
        load_bundle(path)
    assert fragment in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(
    "change",
    [
        lambda m: {**m, "tasks": [*m["tasks"], "sign"]},
        lambda m: {**m, "tasks": []},
        lambda m: {**m, "n_components": m["n_components"] + 1},
        lambda m: {**m, "sources": [{**m["sources"][0], "sha256": "0" * 64}]},
        lambda m: {**m, "heldout": {**m["heldout"], "rms_rad": [x * 0.5 for x in m["heldout"]["rms_rad"]]}},
        lambda m: {**m, "manifest_sha256": "0" * 64},
    ],
    ids=["add-task", "drop-tasks", "n-components", "source-hash", "heldout", "hash-itself"],
)
def test_edited_manifest_is_refused(model, reg, change):
    src = {"path": "a.csv", "sha256": "a" * 64, "task": "grasp", "frames": 400}
    path = save_bundle(model, "grip", registry=reg, tasks=["grasp"], sources=[src],
                       heldout={"method": "x", "rms_rad": [0.2, 0.1]})
    assert read_bundle(path).manifest["manifest_sha256"] == manifest_sha256(_manifest(path))
    rewrite(path, manifest=np.array(json.dumps(change(_manifest(path)), indent=1)))
    with pytest.raises(BundleError, match="manifest_sha256") as info:
        read_bundle(path)
    msg = str(info.value)
    assert msg.startswith(f"{path}: manifest does not match") and "\n" not in msg
    # the registry views skip or flag it; the CLI names the file on one line and exits 2
    with pytest.raises(BundleError, match="no bundle is labelled"):
        select_bundle("grasp", [reg])
    r = run("list", "-r", reg, env={"COLUMNS": "400"})  # wide enough that no cell wraps
    assert r.exit_code == 0 and "invalid: manifest does not match its manifest_sha256" in r.stdout
    assert_one_line_error(run("info", path), f"{path}: manifest does not match its manifest_sha256")
    assert_one_line_error(run("info", "grip", "-r", reg), "manifest_sha256")


def test_manifest_hash_is_canonical(model, reg):
    man = _manifest(save_bundle(model, "grip", registry=reg, tasks=["grasp"]))
    reordered = dict(reversed(list(man.items())))
    assert manifest_sha256(reordered) == manifest_sha256(man) == man["manifest_sha256"]
    assert manifest_sha256({**man, "manifest_sha256": "f" * 64}) == man["manifest_sha256"]  # the field itself is out
    assert manifest_sha256({**man, "tasks": ["grasp "]}) != man["manifest_sha256"]


def test_old_schema_bundle_is_refused_with_a_reason(model, reg):
    path = save_bundle(model, "grip", registry=reg)
    old = {k: v for k, v in _manifest(path).items() if k != "manifest_sha256"}
    rewrite(path, manifest=np.array(json.dumps({**old, "schema_version": 1})))
    with pytest.raises(BundleError, match=r"schema_version 1 bundle: its manifest is not hashed; refit"):
        read_bundle(path)


def test_wrong_array_shapes(model, reg):
    path = save_bundle(model, "grip", registry=reg)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in ARRAY_NAMES}
    arrays["pc_min"] = arrays["pc_min"][:5]
    man = _manifest(path)
    man["arrays_sha256"] = arrays_sha256(arrays)  # only the shape is wrong
    man["manifest_sha256"] = manifest_sha256(man)
    rewrite(path, pc_min=arrays["pc_min"], manifest=np.array(json.dumps(man)))
    with pytest.raises(BundleError, match=r"array pc_min has shape \(5,\)"):
        load_bundle(path)


def test_object_arrays_and_garbage_are_rejected(model, reg, tmp_path):
    path = save_bundle(model, "grip", registry=reg)
    bad = rewrite(path, tmp_path / "obj.npz", dof_names=np.array(list(POSTURE_DOF_NAMES), dtype=object))
    with pytest.raises(BundleError, match="not a readable bundle"):
        load_bundle(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip")
    with pytest.raises(BundleError, match="not a readable bundle"):
        load_bundle(junk)
    with pytest.raises(BundleError, match="missing array"):
        load_bundle(_drop(path, tmp_path / "few.npz", "pc_max"))


def _drop(path, out, name):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != name}
    np.savez(out, **arrays)
    return out


def test_renamed_file_is_caught(model, reg, tmp_path):
    path = save_bundle(model, "grip", registry=reg)
    other = reg / "grip-9.9.9.npz"
    other.write_bytes(path.read_bytes())
    with pytest.raises(BundleError, match="file name says grip@9.9.9"):
        load_bundle("grip", registries=[reg])


def test_unknown_specifier(model, reg):
    save_bundle(model, "grip", registry=reg)
    with pytest.raises(BundleError, match=r"no such bundle.*bundles: .*grip") as info:
        load_bundle("nope", registries=[reg])
    assert str(info.value).startswith("nope: ")
    with pytest.raises(BundleError, match=r"versions: 1.0.0"):
        load_bundle("grip@3.0.0", registries=[reg])
    with pytest.raises(BundleError, match="bad version"):
        load_bundle("grip@latest", registries=[reg])
    with pytest.raises(BundleError, match="no such bundle file"):
        load_bundle(str(reg / "missing.npz"))


def test_registries_env_and_precedence(model, tmp_path, monkeypatch):
    a, b, c = (tmp_path / n for n in "abc")
    save_bundle(model, "grip", "1.0.0", registry=a)
    save_bundle(model, "grip", "1.2.0", registry=b)
    save_bundle(model, "grip", "1.2.0", registry=c)
    save_bundle(model, "other", registry=c)
    monkeypatch.setenv("SYNERGY_PATH", os.pathsep.join([str(b), str(c)]))
    paths = registry_paths([a])
    assert paths[:3] == [a, b, c] and paths[-1].parts[-2:] == ("models", "synergies")
    got = load_bundle("grip", registries=[a])
    assert got.version == "1.2.0" and got.path.parent == b  # highest version; ties → earlier registry
    assert load_bundle("grip@1.0.0", registries=[a]).path.parent == a
    assert load_bundle("other").path.parent == c
    # save without a registry goes to the first SYNERGY_PATH folder
    assert save_bundle(model, "fresh").parent == b
    monkeypatch.delenv("SYNERGY_PATH")
    with pytest.raises(BundleError, match="no target registry"):
        save_bundle(model, "fresh")


def test_save_rejects_incomplete_models(reg):
    X = postures()
    streamed = SynergyModel().partial_fit(X[:200]).partial_fit(X[200:])
    with pytest.raises(BundleError, match="update_limits"):
        save_bundle(streamed, "s", registry=reg)
    with pytest.raises(BundleError, match="not fitted"):
        save_bundle(SynergyModel(), "s", registry=reg)
    small = SynergyModel().fit(X[:, :5])
    with pytest.raises(BundleError, match="dof_names"):
        save_bundle(small, "s", registry=reg)
    assert save_bundle(small, "s", registry=reg, dof_names=list("abcde")).is_file()
    with pytest.raises(BundleError, match="bad bundle name"):
        save_bundle(small, "bad name", registry=reg, dof_names=list("abcde"))


def test_select_prefers_specific_bundle(model, reg):
    save_bundle(model, "all", registry=reg, tasks=["grasp", "general", "sign"])
    save_bundle(model, "grasp-only", registry=reg, tasks=["grasp"])
    assert select_bundle("grasp", [reg]).name == "grasp-only"
    assert select_bundle("sign", [reg]).name == "all"
    with pytest.raises(BundleError, match="tasks: general, grasp, sign"):
        select_bundle("juggle", [reg])
    # a tie on tasks and samples goes to the name, and the command says it broke one
    save_bundle(model, "a-grasp", registry=reg, tasks=["grasp"])
    assert select_bundle("grasp", [reg]).name == "a-grasp"
    r = run("select", "--task", "grasp", "-r", reg)
    assert r.exit_code == 0 and r.stdout.startswith("a-grasp@1.0.0\t")
    note = " ".join(r.stderr.split())
    assert "note: a-grasp@1.0.0 ties with grasp-only@1.0.0 (1 task," in note and "chosen by name" in note
    r = run("select", "--task", "sign", "-r", reg)
    assert r.exit_code == 0 and r.stderr == ""


# ----------------------------------------------------------------------------- readers
def write_csv(path, X, meta=True, extra_cols=True):
    lines = ["# source: synthetic", "# units: rad"] if meta else []
    cols = (["time_s", *POSE_DOF_NAMES] if extra_cols else []) + list(POSTURE_DOF_NAMES) + (
        ["residual_mm"] if extra_cols else [])
    lines.append(",".join(cols))
    for i, row in enumerate(X):
        vals = ([i / 100, *([0.0] * 6)] if extra_cols else []) + list(row) + ([0.5] if extra_cols else [])
        lines.append(",".join(repr(float(v)) for v in vals))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_read_csv_and_schroeder26(tmp_path):
    X = postures(30)
    X[4, 2] = np.nan  # a frame where marker IK failed
    t = read_trial(write_csv(tmp_path / "t.csv", X), task="grasp")
    assert t.frames == 29 and t.task == "grasp" and len(t.sha256) == 64
    np.testing.assert_array_equal(t.postures, np.delete(X, 4, axis=0))
    full = np.hstack([np.ones((30, 6)), postures(30)])
    np.savetxt(tmp_path / "p.txt", full)
    np.testing.assert_array_equal(read_trial(tmp_path / "p.txt").postures, full[:, 6:])


@pytest.mark.parametrize(
    "name, content, fmt, fragment",
    [
        ("a.csv", "thumb1_abd,x\n1,2\n", "auto", "missing posture column(s): thumb1_flex"),
        ("a.txt", "1 2 3\n", "auto", "expected rows of 26 values"),
        ("a.txt", "1 2 x\n", "schroeder26", "cannot read"),
        ("a.c3d", "", "auto", "empty file"),
        ("a.bin", "", "auto", "unknown file type"),
        ("a.csv", "", "xlsx", "unknown format"),
    ],
)
def test_reader_errors(tmp_path, name, content, fmt, fragment):
    p = tmp_path / name
    p.write_text(content)
    with pytest.raises(SynergyError) as info:
        read_trial(p, fmt)
    assert fragment in str(info.value) and str(info.value).startswith(str(p))


def test_fit_trials_equals_fit_on_concatenation(tmp_path):
    parts = [postures(n, seed=s) for s, n in enumerate((50, 120, 7))]
    trials = [read_trial(write_csv(tmp_path / f"t{i}.csv", X)) for i, X in enumerate(parts)]
    a = fit_trials(trials)
    b = SynergyModel().fit(np.vstack(parts))
    np.testing.assert_allclose(a.all_components_, b.all_components_, atol=1e-10)
    np.testing.assert_allclose(a.pc_min_, b.pc_min_, atol=1e-10)


# ----------------------------------------------------------------------------- CLI
runner = CliRunner()


def run(*args, **kw):
    return runner.invoke(app, [str(a) for a in args], **kw)


def assert_one_line_error(result, fragment=""):
    assert result.exit_code == 2, (result.exit_code, result.output)
    err = result.stderr.strip()
    assert err.startswith("error: ") and "\n" not in err and fragment in err, err
    assert "Traceback" not in result.output


@pytest.fixture
def csvs(tmp_path):
    d = tmp_path / "angles"
    (d / "grasp").mkdir(parents=True)
    (d / "free").mkdir()
    files = [write_csv(d / "grasp" / f"g{i}.csv", postures(150, seed=i)) for i in range(3)]
    files += [write_csv(d / "free" / f"f{i}.csv", postures(150, seed=10 + i)) for i in range(2)]
    return files


def test_cli_fit_list_info_select_compare_plot(csvs, reg, tmp_path):
    r = run("fit", "--angles", *csvs, "--name", "demo", "--task", "general", "-o", reg)
    assert r.exit_code == 0, r.output
    for word in ("demo@1.0.0", "trials", "5", "750", "variance, 1 PC", "variance, 6 PCs", "PCs for 99.0 %",
                 "demo-1.0.0.npz", "leave-one-trial-out"):
        assert word in r.stdout, word
    b = load_bundle("demo", [reg])
    assert b.manifest["n_trials"] == 5 and len(b.manifest["sources"]) == 5
    assert b.manifest["sources"][0]["task"] == "general" and len(b.manifest["heldout"]["rms_rad"]) == 21

    tm = tmp_path / "tasks.yaml"
    tm.write_text("- glob: 'grasp/*.csv'\n  task: grasp\n- glob: '*.csv'\n  task: free\n")
    r = run("fit", *csvs, "--name", "demo", "--tasks", tm, "--per-task", "-o", reg)
    assert r.exit_code == 0, r.output
    assert load_bundle("demo-grasp", [reg]).manifest["n_trials"] == 3
    assert load_bundle("demo-free", [reg]).manifest["tasks"] == ["free"]

    r = run("list", "-r", reg)
    assert r.exit_code == 0 and "demo-grasp" in r.stdout and "demo-free" in r.stdout
    r = run("info", "demo", "-r", reg)
    assert r.exit_code == 0 and "spectrum" in r.stdout and "sources" in r.stdout and "150" in r.stdout
    r = run("select", "--task", "grasp", "--variance", "0.9", "-r", reg)
    assert r.exit_code == 0 and r.stdout.startswith("demo-grasp@1.0.0")
    r = run("compare", "demo", "demo-grasp", "-r", reg)
    assert r.exit_code == 0 and "principal angles" in r.stdout
    assert len([ln for ln in r.stdout.splitlines() if ln.strip().startswith("│")]) == 6
    r = run("plot", "demo", "-o", tmp_path / "figs", "-r", reg, "--heldout", csvs[0])
    assert r.exit_code == 0, r.output
    pngs = sorted((tmp_path / "figs").glob("*.png"))
    assert [p.name for p in pngs] == ["demo-1.0.0-hands.png", "demo-1.0.0-reconstruction.png", "demo-1.0.0-scree.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)


def test_cli_errors_exit_2_one_line(csvs, reg, tmp_path):
    assert_one_line_error(run("info", "nope", "-r", reg), "nope: no such bundle")
    bad_map = tmp_path / "bad.yaml"
    bad_map.write_text("- glob: '*.csv'\n  task: 3\n")
    assert_one_line_error(run("fit", *csvs, "--name", "x", "--tasks", bad_map, "-o", reg), f"{bad_map}: [0].task")
    partial = tmp_path / "partial.yaml"
    partial.write_text("'grasp/*.csv': grasp\n")
    assert_one_line_error(run("fit", *csvs, "--name", "x", "--tasks", partial, "-o", reg), "no rule matches")
    assert run("fit", csvs[0], "--name", "x", "-o", reg, "--version", "1.0.0").exit_code == 0
    assert_one_line_error(run("fit", csvs[0], "--name", "x", "-o", reg, "--version", "1.0.0"), "immutable")
    assert_one_line_error(run("fit", tmp_path / "missing.csv", "--name", "x", "-o", reg), "no such file")
    # a folder given for its files (a new user's was "unknown file type", which sent them to --format)
    (tmp_path / "mocap").mkdir()
    assert_one_line_error(run("fit", tmp_path / "mocap", "--name", "x", "-o", reg), f"{tmp_path / 'mocap'}: is a folder")
    assert_one_line_error(run("fit", csvs[0], "--name", "x", "-o", reg, "--variance", "1.5"), "--variance")
    assert_one_line_error(run("fit", csvs[0], "--name", "x"), "no target registry")
    assert_one_line_error(run("fit", tmp_path / "m.c3d", "--name", "x", "-o", reg))
    assert_one_line_error(run("select", "--task", "juggle", "-r", reg), "no bundle is labelled")
    tampered = rewrite(reg / "x-1.0.0.npz", tmp_path / "t.npz", mean=np.zeros(20))
    assert_one_line_error(run("info", tampered), "arrays_sha256")


def test_cli_plot_refuses_existing_pngs_unless_overwrite(csvs, reg, tmp_path, monkeypatch):
    import synergy.plots

    assert run("fit", "--angles", *csvs, "--name", "demo", "-o", reg).exit_code == 0
    figs = tmp_path / "figs"
    figs.mkdir()
    earlier = figs / "demo-1.0.0-reconstruction.png"  # one of the three (the bundle has a held-out curve)
    earlier.write_bytes(b"an earlier figure")
    drawn = []
    real = synergy.plots.bundle_figures
    monkeypatch.setattr(synergy.plots, "bundle_figures", lambda *a, **kw: drawn.append(1) or real(*a, **kw))
    r = run("plot", "demo", "-o", figs, "-r", reg)
    assert_one_line_error(r, f"{earlier}: exists and is never overwritten (use --overwrite)")
    assert r.stdout == "" and not drawn  # refused before anything was drawn
    assert sorted(figs.iterdir()) == [earlier] and earlier.read_bytes() == b"an earlier figure"
    r = run("plot", "demo", "-o", figs, "-r", reg, "--overwrite")
    assert r.exit_code == 0, r.output
    pngs = sorted(figs.glob("*.png"))
    assert [p.name for p in pngs] == ["demo-1.0.0-hands.png", "demo-1.0.0-reconstruction.png", "demo-1.0.0-scree.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in pngs)
    # the library refuses too (a file that appears after the CLI's check is not replaced)
    scree = figs / "demo-1.0.0-scree.png"
    before = scree.read_bytes()
    with pytest.raises(FileExistsError, match="never overwritten"):
        real(load_bundle("demo", [reg]), figs)
    assert scree.read_bytes() == before
    assert "Replace existing output PNGs" in " ".join(run("plot", "--help").stdout.split())


def test_cli_help_is_fast_and_lazy():
    code = "import sys, synergy.cli; print(sorted(m for m in ('numpy', 'sklearn', 'pandas', 'matplotlib', 'scipy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    exe = Path(sys.executable).with_name("synergy")
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "synergy.cli"]
    # fast = lazy: the heavy imports are what made --help slow (checked above, not by a wall clock)
    res = subprocess.run([*cmd, "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "fit" in res.stdout


def test_shipped_bundle_command(reg):
    """The command that will produce models/synergies/fingerfist (run here into a temp registry)."""
    if not FINGERFIST.is_file():
        pytest.skip(f"fingerfist posture data not found at {FINGERFIST}")
    r = run("fit", "--angles", FINGERFIST, "--format", "schroeder26", "--name", "fingerfist",
            "--task", "general", "--variance", "0.99", "--version", "1.0.0", "-o", reg)
    assert r.exit_code == 0, r.output
    # the shipped fingerfist@1.0.0 is searched too: two bundles under one name@version, said (a new user's
    # own fingerfist@1.0.0 replaced the shipped one in every lookup without a word)
    err = " ".join(r.stderr.split())
    assert f"warning: fingerfist@1.0.0 is also in {ROOT / 'models' / 'synergies'}" in err, r.stderr
    assert f"a lookup by name takes the one in {reg}" in err, r.stderr
    r2 = run("fit", "--angles", FINGERFIST, "--format", "schroeder26", "--name", "mine", "--version", "1.0.0",
             "-o", reg, "--variance", "0.99")
    assert r2.exit_code == 0 and "warning" not in r2.stderr, r2.output
    b = read_bundle(reg / "fingerfist-1.0.0.npz")
    cum = np.cumsum(b.model.all_explained_variance_ratio_)
    np.testing.assert_allclose(cum[[0, 2, 5]], [0.713, 0.854, 0.968], atol=1e-3)
    assert b.manifest["n_samples"] == 6000 and b.model.n_components_ == 10
    assert "71.3 %" in r.stdout and "85.4 %" in r.stdout and "96.8 %" in r.stdout
    # the shipped bundle holds these arrays (sealed as schema 2 with tools/reseal_bundle.py, arrays kept
    # bit for bit; a refit reproduces them to the eigen-solver's rounding)
    shipped = read_bundle(ROOT / "models" / "synergies" / "fingerfist-1.0.0.npz")
    assert shipped.manifest["schema_version"] == 2
    assert shipped.manifest["sources"][0]["sha256"] == b.manifest["sources"][0]["sha256"]
    for a in ("all_components_", "all_explained_variance_", "pc_min_", "pc_max_", "mean_", "joint_min_", "joint_max_"):
        np.testing.assert_allclose(getattr(shipped.model, a), getattr(b.model, a), rtol=0, atol=1e-12, err_msg=a)


# ----------------------------------------------------------------------------- module boundaries
def test_bundle_module_does_not_pull_in_marker_ik():
    code = ("import sys, synergy.bundle; print(sorted(m for m in ('synergy.c3d', 'synergy.angles', 'synergy.fit', "
            "'synergy.markers', 'handmodel.solver') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_read_schroeder26_errors_name_the_file(tmp_path):
    from synergy.postures import read_schroeder26

    ok = tmp_path / "ok.txt"
    full = np.hstack([np.ones((4, 6)), postures(4)])
    np.savetxt(ok, full)
    np.testing.assert_array_equal(read_schroeder26(ok), full[:, 6:])
    cases = {"missing.txt": (None, "no such file"), "short.txt": ("1 2 3\n", "expected rows of 26 values"),
             "text.txt": ("a " * 26 + "\n", "cannot read"), "nan.txt": (" ".join(["nan"] * 26) + "\n", "NaN"),
             "empty.txt": ("", "expected rows of 26 values")}
    for name, (content, fragment) in cases.items():
        p = tmp_path / name
        if content is not None:
            p.write_text(content)
        with pytest.raises(SynergyError) as info:
            read_schroeder26(p)
        msg = str(info.value)
        assert msg.startswith(f"{p}: ") and fragment in msg and "\n" not in msg, (name, msg)


def test_task_labels_and_per_task_groups(tmp_path):
    from synergy.errors import TaskMapError
    from synergy.fit import Trial, group_by_task, task_labels
    from synergy.tasks import task_map_from_rules

    files = [Path("grasp/a.csv"), Path("free/b.csv"), Path("grasp/c.csv")]
    assert task_labels(files, "x") == dict.fromkeys(files, "x")
    tm = task_map_from_rules([{"glob": "grasp/*.csv", "task": "grasp"}, {"glob": "free/*", "task": "free"}], "m.yaml")
    assert list(task_labels(files, task_map=tm).values()) == ["grasp", "free", "grasp"]
    with pytest.raises(TaskMapError, match=r"^m.yaml: no rule matches other/d.csv"):
        task_labels([*files, Path("other/d.csv")], task_map=tm)
    trials = [Trial(str(f), postures(5), task=t) for f, t in zip(files, ["grasp", "free", "grasp"])]
    assert group_by_task(trials, "n") == {"n": trials}
    groups = group_by_task(trials, "n", per_task=True, order=["grasp", "sign", "free"])
    assert list(groups) == ["n-grasp", "n-free"] and [t.path for t in groups["n-grasp"]] == ["grasp/a.csv", "grasp/c.csv"]
    assert list(group_by_task(trials, "n", per_task=True)) == ["n-free", "n-grasp"]
    with pytest.raises(SynergyError, match="no task label"):
        group_by_task([*trials, Trial("u.csv", postures(5))], "n", per_task=True)


def test_cli_per_task_without_labels_fails_before_converting(csvs, tmp_path, monkeypatch):
    """--per-task with files that carry no task (no --tasks, no task event) failed only after every
    file was converted (40 s for two real C3D files): now before the first, naming the file."""
    import synergy.fit

    converted = []
    read_trial = synergy.fit.read_trial
    monkeypatch.setattr(synergy.fit, "read_trial", lambda *a, **k: converted.append(a[0]) or read_trial(*a, **k))
    r = run("fit", "--angles", *csvs, "--name", "demo", "--per-task", "-o", tmp_path / "reg")
    assert r.exit_code == 2
    assert f"{csvs[0]}: --per-task: no task label (give --tasks map.yaml" in " ".join(r.output.split())
    assert converted == [] and not (tmp_path / "reg").exists()
