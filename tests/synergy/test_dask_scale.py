"""Dask scale-out: conversion + sufficient statistics as tasks on a LocalCluster give the local result."""
import numpy as np
import pytest
from typer.testing import CliRunner

from synergy.bundle import load_bundle
from synergy.cli import app
from synergy.fit import fit_trials, read_trial

distributed = pytest.importorskip("distributed", reason="the optional dask extra is not installed")


@pytest.mark.slow
def test_dask_local_cluster_equals_local_fit(tmp_path):
    runner = CliRunner()
    mocap = tmp_path / "mocap"
    r = runner.invoke(app, ["simulate", "-o", str(mocap), "--motions", "open_close,power_grasp", "--trials", "1",
                            "--duration", "1"])
    assert r.exit_code == 0, r.output
    files = sorted(mocap.glob("*.c3d"))
    from synergy.scale import read_trials_dask

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        trials, stats = read_trials_dask(files, "c3d", {}, markers="hand16", client=client)
    local = [read_trial(f, "c3d", markers="hand16") for f in files]
    for a, b in zip(trials, local):
        np.testing.assert_array_equal(a.postures, b.postures)
        assert a.task == b.task == ("grasp" if "grasp" in a.path else "general")
    m_dask = fit_trials(trials, 0.99, stats)
    m_local = fit_trials(local, 0.99)
    np.testing.assert_allclose(m_dask.mean_, m_local.mean_, atol=1e-10)
    np.testing.assert_allclose(m_dask.all_explained_variance_, m_local.all_explained_variance_, atol=1e-10)
    np.testing.assert_allclose(np.abs(m_dask.all_components_), np.abs(m_local.all_components_), atol=1e-8)
    np.testing.assert_allclose(m_dask.pc_min_, m_local.pc_min_, atol=1e-10)
    # the CLI path with a real LocalCluster of worker processes
    r = runner.invoke(app, ["fit", *map(str, files), "--markers", "hand16", "--name", "dk", "--dask", "local:2",
                            "-o", str(tmp_path / "reg")])
    assert r.exit_code == 0, r.output
    b = load_bundle("dk", [tmp_path / "reg"])
    np.testing.assert_allclose(b.model.explained_variance_ratio_[:5], m_local.explained_variance_ratio_[:5], atol=1e-9)
