"""The user's own marker sets: `synergy fit` on C3D files without --markers matches their labels
against the shipped sets and the user's folders (--markersets DIR, $SYNERGY_MARKERSETS, the user
config folder), says which set and hand it chose, and refuses ambiguous or missing folders."""
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from synergy.c3d_write import write_c3d
from synergy.cli import app
from synergy.errors import MarkerSetError
from synergy.markers import (
    MARKERSETS_ENV,
    available_markersets,
    choose_markerset,
    load_markerset,
    markerset_from_dict,
    user_markerset_dirs,
)
from synergy.simulate import motion, simulate_markers

runner = CliRunner()


def lab_set(name="lab19"):
    """hand19 under a lab's own labels (``LAB_<label>``, no aliases): no shipped set matches them."""
    doc = yaml.safe_load(Path(load_markerset("hand19").path).read_text())
    doc["name"] = name
    for m in doc["markers"]:
        m["label"] = "LAB_" + m["label"]
        m.pop("aliases", None)
    return doc


@pytest.fixture()
def user_dir(tmp_path, monkeypatch):
    monkeypatch.delenv(MARKERSETS_ENV, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))  # no real user config leaks in
    d = tmp_path / "sets"
    d.mkdir()
    (d / "lab19.yaml").write_text(yaml.safe_dump(lab_set()))
    return d


@pytest.fixture()
def lab_trial(tmp_path):
    ms = markerset_from_dict(lab_set())
    th, _ = motion("power_grasp", duration_s=0.5, seed=3)
    tr = simulate_markers(th, ms, noise_mm=0.3, seed=4)
    return write_c3d(tmp_path / "lab_grasp.c3d", tr.points, tr.labels, tr.rate)


def test_user_folder_joins_the_automatic_choice(user_dir, lab_trial, tmp_path, monkeypatch):
    labels = ["S1:LAB_" + m.label for m in load_markerset("hand19").markers]
    with pytest.raises(MarkerSetError, match="no marker set fits"):
        choose_markerset(labels, available_markersets())
    ms, _, rep = choose_markerset(labels, available_markersets([user_dir]))
    assert (ms.name, rep["matched"], rep["total"]) == ("lab19", 19, 19)
    # the same folder through the environment variable, and by name for --markers
    monkeypatch.setenv(MARKERSETS_ENV, str(user_dir))
    assert "lab19" in [m.name for m in available_markersets()]
    assert load_markerset("lab19").name == "lab19"

    monkeypatch.delenv(MARKERSETS_ENV)
    r = runner.invoke(app, ["fit", str(lab_trial), "--name", "lab", "-o", str(tmp_path / "reg"), "--no-hand-check"])
    assert r.exit_code == 2 and "no marker set fits" in r.output
    r = runner.invoke(app, ["fit", str(lab_trial), "--markersets", str(user_dir), "--name", "lab",
                            "-o", str(tmp_path / "reg"), "--no-hand-check"])
    assert r.exit_code == 0, r.output
    assert "marker set lab19, hand left (19 of 19 labels matched): lab_grasp.c3d" in r.output
    assert (tmp_path / "reg" / "lab-1.0.0.npz").exists()


def test_user_config_folder(user_dir, tmp_path, monkeypatch):
    cfg = tmp_path / "config" / "synergy" / "markersets"
    cfg.mkdir(parents=True)
    (cfg / "lab19.yaml").write_text((user_dir / "lab19.yaml").read_text())
    assert user_markerset_dirs() == [cfg]
    assert [m.name for m in available_markersets()][-1] == "lab19"


def test_name_clashes_and_missing_folders_are_errors(user_dir, tmp_path, monkeypatch):
    other = tmp_path / "other"
    other.mkdir()
    (other / "copy.yaml").write_text((user_dir / "lab19.yaml").read_text())
    with pytest.raises(MarkerSetError, match="'lab19' is also defined in .*lab19.yaml"):
        available_markersets([user_dir, other])
    (other / "copy.yaml").write_text(yaml.safe_dump(lab_set("hand16")))
    with pytest.raises(MarkerSetError, match="'hand16' is also defined in .*models/markersets/hand16.yaml"):
        available_markersets([other])
    monkeypatch.setenv(MARKERSETS_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(MarkerSetError, match="marker-set folder not found"):
        available_markersets()
    r = runner.invoke(app, ["fit", str(tmp_path / "x.c3d"), "--markersets", str(tmp_path / "nowhere"),
                            "--name", "x", "-o", str(tmp_path / "reg")])
    assert r.exit_code == 2 and len(r.output.strip().splitlines()) == 1 and "nowhere" in r.output
    # an unknown name lists the user's sets beside the shipped ones
    monkeypatch.setenv(MARKERSETS_ENV, str(user_dir))
    with pytest.raises(MarkerSetError, match=r"no such marker set \(known: .*lab19"):
        load_markerset("lab20")


def test_bad_user_file_is_named(user_dir):
    (user_dir / "broken.yaml").write_text("name: broken\nmarkers: 3\n")
    with pytest.raises(MarkerSetError) as e:
        available_markersets([user_dir])
    assert "broken.yaml" in str(e.value)
    np.testing.assert_equal(len([m for m in available_markersets() if m.name == "lab19"]), 0)
