"""Scale-out with Dask: per-file conversion (C3D → marker IK → postures, or angle tables) and the
mergeable sufficient statistics run as Dask tasks; the fit merges them exactly, so the result is the
same as a local fit (``synergy fit … --dask local[:N]|ADDRESS``). Needs the optional ``dask`` extra."""
from __future__ import annotations

from .errors import SynergyError
from .fit import read_trial
from .pca import SufficientStats


def _convert(path, fmt, task, read_kw):
    trial = read_trial(path, fmt, task=task, **read_kw)
    return trial, SufficientStats.from_array(trial.postures).as_arrays()


def client_for(address: str):
    """A ``distributed.Client`` for ``local`` / ``local:N`` (a LocalCluster of N worker processes) or a
    scheduler address; returns ``(client, cluster_or_None)``."""
    try:  # an optional extra: imported only when asked for
        from distributed import Client, LocalCluster
    except ImportError:
        raise SynergyError("--dask", "dask is not installed (pip install 'synergistic-hand-tracking[dask]')") from None
    if address == "local" or address.startswith("local:"):
        n = int(address.split(":", 1)[1]) if ":" in address else None
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None)
        return Client(cluster), cluster
    try:
        return Client(address, timeout="10s"), None
    except OSError as exc:
        raise SynergyError(address, f"cannot reach the Dask scheduler ({exc})") from None


def read_trials_dask(files, fmt, labels, *, address="local", client=None, **read_kw):
    """Convert ``files`` as Dask tasks; returns ``(trials, stats)`` in the order of ``files``.

    ``read_kw`` are :func:`synergy.fit.read_trial`'s keywords (markers, hand, smooth_hz,
    calibration, check_hand, markersets): each task converts its file exactly as a local fit would."""
    own = None
    if client is None:
        client, own = client_for(address)
    try:
        futs = [client.submit(_convert, str(f), fmt, labels.get(f), read_kw, pure=False)
                for f in files]
        results = client.gather(futs)
    finally:
        if own is not None:
            client.close()
            own.close()
    trials = [r[0] for r in results]
    stats = [SufficientStats.from_arrays(r[1]) for r in results]
    return trials, stats
