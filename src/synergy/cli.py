"""``synergy`` command line: fit, list, inspect, select, compare and plot synergy bundles.

The commands only parse, call the library (``synergy.fit``, ``synergy.bundle``, ``synergy.plots``),
print and draw progress. Library modules (and numpy, scikit-learn, pandas, matplotlib) are imported
inside the commands so that ``synergy --help`` answers at once.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

app = typer.Typer(
    name="synergy",
    help="Hand synergies (PCA of posture angles) from motion capture: fit and manage bundles.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,
)

REGISTRY_HELP = "Extra registry folder to search (repeatable); SYNERGY_PATH and the shipped models/synergies follow."


from handmodel.cliutil import errors_exit_2 as _errors_exit_2  # noqa: E402


def _console(stderr: bool = False):
    from rich.console import Console

    return Console(stderr=stderr, markup=False)  # names, paths and reasons are shown as typed, never as markup


def _warn_same_version(name, version, target) -> None:
    """Warn when ``name@version`` is already in another registry that lookups search: two bundles under
    one name@version, and ``--synergies name@version`` takes whichever registry comes first (a new
    user's own ``fingerfist@1.0.0`` replaced the shipped one in every lookup without a word)."""
    if version is None:
        return
    from synergy.registry import list_bundles

    others = [r.path.parent for r in list_bundles([target])
              if r.name == name and r.version == version and r.path.parent.resolve() != Path(target).resolve()]
    if others:
        # the target is searched first (list_bundles([target]): it leads the registries), so it wins
        _console(stderr=True).print(f"warning: {name}@{version} is also in {others[0]}: a lookup by name takes the one in "
                                    f"{target}; give another version to keep both", markup=False)


def _check_variance(variance: float) -> None:
    from synergy.errors import SynergyError

    if not 0.0 < variance < 1.0:
        raise SynergyError("--variance", f"must be a fraction in (0, 1), got {variance}")


def _check_new_file(path: Path, overwrite: bool) -> None:
    """An output file that exists is refused, with the option that replaces it, before the work."""
    from handmodel.fileio import check_output
    from synergy.errors import SynergyError

    if not overwrite and path.exists() and not path.is_dir():  # a folder is check_output's error
        raise SynergyError(path, "exists and is never overwritten (use --overwrite)")
    check_output(path, overwrite=overwrite)


def _pct(x: float) -> str:
    return f"{100 * x:.1f} %"


# ----------------------------------------------------------------------------- fit
@app.command()
@_errors_exit_2
def fit(
    files: List[Path] = typer.Argument(None, help="Input files: angle tables, or C3D (marker set and hand chosen from the labels unless given)."),
    angles: List[Path] = typer.Option(None, "--angles", help="Joint-angle file (repeatable; further files may follow as arguments)."),
    name: str = typer.Option(..., "--name", help="Bundle name."),
    task: Optional[str] = typer.Option(None, "--task", help="Task label of all inputs."),
    tasks: Optional[Path] = typer.Option(None, "--tasks", help="Task-map YAML (glob -> task)."),
    per_task: bool = typer.Option(False, "--per-task", help="With --tasks: one bundle per task, named NAME-TASK."),
    variance: float = typer.Option(0.99, "--variance", help="Variance fraction that sets the default number of PCs."),
    fmt: str = typer.Option("auto", "--format", help="Input format: auto (by suffix), csv, schroeder26."),
    markers: Optional[str] = typer.Option(None, "--markers", help="C3D input: marker set name or YAML (default: the shipped set the labels fit)."),
    markersets: List[Path] = typer.Option(None, "--markersets", help="C3D input: folder of your own marker-set YAMLs, matched beside the shipped sets (repeatable; also $SYNERGY_MARKERSETS, ~/.config/synergy/markersets)."),
    hand: Optional[str] = typer.Option(None, "--hand", help="C3D input: left or right (default: from the labels, else the handedness check)."),
    subject: Optional[Path] = typer.Option(None, "--subject", help="C3D input: subject calibration from 'synergy calibrate'."),
    accept_poor: bool = typer.Option(False, "--accept-poor", help="C3D input: fit trials whose conversion is judged poor."),
    no_hand_check: bool = typer.Option(False, "--no-hand-check", help="C3D input: skip the handedness check."),
    smooth_hz: Optional[float] = typer.Option(None, "--smooth-hz", help="C3D input: low-pass the markers (Hz) before IK."),
    dip_prior_sd: Optional[float] = typer.Option(None, "--dip-prior-sd", help="C3D input: SD (degrees) of the weak DIP = 2/3 PIP prior that decides DIPs the markers leave open (default 10; 0: off; recorded in the manifest)."),
    prior: str = typer.Option("auto", "--prior", help="C3D input: posture prior of the marker IK: auto (the fingerfist bundle where the markers leave a joint weakly observed, and in the calibration of a trial without open-hand frames), none, or a bundle NAME / path (recorded in the manifest)."),
    registry: Optional[Path] = typer.Option(None, "-o", "--registry", help="Output registry folder (default: first SYNERGY_PATH folder)."),
    dask: Optional[str] = typer.Option(None, "--dask", help="Convert files and compute statistics as Dask tasks: local, local:N or a scheduler address."),
    version: Optional[str] = typer.Option(None, "--version", help="Bundle version X.Y.Z (default: next patch)."),
    hand_model: str = typer.Option("default", "--hand-model", help="Hand model the angles refer to."),
    hand_model_sha256: Optional[str] = typer.Option(None, "--hand-model-sha256", help="Its hash (default: hash of models/hands/NAME.yaml)."),
):
    """Fit synergies on posture files and save a new bundle version."""
    from handmodel.fileio import check_output
    from synergy.registry import check_new_bundle

    # Everything that would refuse the bundle at the end is checked first: the conversion takes minutes.
    target = check_new_bundle(name, None, registry)  # the name, and a registry given or in SYNERGY_PATH
    check_output(target, folder=True)  # a read-only or full registry fails before the files are read
    from rich.progress import Progress

    from synergy.errors import SynergyError
    from synergy.calibrate import load_calibration
    from synergy.fit import bundle_from_trials, check_inputs, group_by_task, quality_problems, read_trial, task_labels
    from synergy.prior import prior_option
    from synergy.tasks import load_task_map

    _check_variance(variance)
    if dip_prior_sd is not None and not dip_prior_sd >= 0:
        raise SynergyError("--dip-prior-sd", f"must be 0 (off) or a positive SD in degrees, got {dip_prior_sd}")
    inputs = [*(angles or []), *(files or [])]
    if not inputs:
        raise SynergyError("fit", "no input files (give --angles FILE... or files)")
    if task and tasks:
        raise SynergyError("fit", "give either --task or --tasks, not both")
    task_map = load_task_map(tasks) if tasks else None
    labels = task_labels(inputs, task, task_map)
    # the bundles known now (--per-task: by the labels given; a C3D's own task event is read with it)
    for bname in [f"{name}-{t}" for t in dict.fromkeys(labels.values()) if t] if per_task else [name]:
        check_new_bundle(bname, version, target)
        _warn_same_version(bname, version, target)
    read_kw = dict(markers=markers, hand=hand, smooth_hz=smooth_hz, check_hand=not no_hand_check,
                   calibration=load_calibration(subject) if subject is not None else "trial")
    if dip_prior_sd is not None:  # otherwise read_trial's default, the same as synergy angles'
        read_kw["dip_prior_sd"] = dip_prior_sd
    read_kw["prior"] = prior_option(prior)
    if markersets:  # user folders named here join the shipped sets and $SYNERGY_MARKERSETS
        from synergy.markers import available_markersets, load_markerset, user_markerset_dirs

        read_kw["markersets"] = available_markersets(markersets)
        if markers:
            read_kw["markers"] = load_markerset(markers, user_markerset_dirs(markersets))

    # a missing, truncated or unreadable file, or one --per-task cannot place, fails before any is converted
    check_inputs(inputs, fmt, labels=labels if per_task else None)

    trials = []
    stats_of = {}
    err_console = _console(stderr=True)
    if dask:
        from synergy.scale import read_trials_dask

        with err_console.status(f"converting {len(inputs)} file(s) on Dask ({dask})"):
            trials, stats = read_trials_dask(inputs, fmt, labels, address=dask, **read_kw)
        stats_of = {id(t): s for t, s in zip(trials, stats)}
    else:
        with Progress(console=err_console, transient=True, disable=not err_console.is_terminal) as progress:
            bar = progress.add_task("reading", total=len(inputs))
            for f in inputs:
                progress.update(bar, description=f"reading {f.name}")
                trials.append(read_trial(f, fmt, task=labels[f], **read_kw))
                progress.advance(bar)
    console = _console()
    _print_conversions(console, trials, accept_poor)
    problems = quality_problems(trials)
    if problems and not accept_poor:
        from handmodel.cliutil import print_error

        for err in problems:  # after the table, one line each, nothing printed after them
            print_error(err)
        raise typer.Exit(2)

    groups = group_by_task(trials, name, per_task=per_task, order=task_map.tasks if task_map is not None else None)
    for bname, group in groups.items():
        bundle = bundle_from_trials(
            group, bname, n_components=variance, registry=target, version=version,
            hand_model=hand_model, hand_model_sha256=hand_model_sha256,
            stats=[stats_of[id(t)] for t in group] if stats_of else None,
        )
        console.print(_summary_table(bundle, variance))


def _print_conversions(console, trials, accept_poor: bool) -> None:
    """C3D trials: the marker set and hand chosen from the labels (one line per choice), the
    per-trial conversion quality (a table that fits 80 columns), warnings and poor trials fitted."""
    from rich.text import Text

    from synergy.cli_mocap import RESIDUAL_COLUMNS, fit_table

    conv = [(Path(t.path).name, t.conversion) for t in trials if t.conversion]
    if not conv:
        return
    chosen = {}
    for f, c in conv:
        if c["chosen"] == "labels" or c["hand_from"] in ("labels", "handedness check"):
            how = {"handedness check": " by the handedness check", "subject": " of the subject calibration"}.get(
                c["hand_from"], "")
            key = (f"marker set {c['markerset']}, hand {c['hand']}{how} ({c['matched']} of {c['total']} labels matched)"
                   + "".join(f"; the file also carries the {o['hand']} hand (--hand {o['hand']})"
                             if o["name"] == c["markerset"] else f"; the labels also fit {o['name']}"
                             for o in c["others"]))
            chosen.setdefault(key, []).append(f)
    for key, names in chosen.items():
        console.print(Text(f"{key}: {', '.join(names) if len(names) <= 3 else f'{len(names)} files'}"), soft_wrap=True)
    mm = lambda x: "-" if x is None else f"{x:.2f}"  # noqa: E731
    rows = [(f, f"{c['markerset']} {c['hand'][0].upper()}", mm(c["residual_median_mm"]), mm(c["residual_p95_mm"]),
             f"{100 * c['ok_share']:.1f}", c["verdict"]) for f, c in conv]
    console.print(fit_table(f"C3D conversion ({RESIDUAL_COLUMNS})", ("trial", "set, hand", "med mm", "95th mm", "ok %",
                                                                  "verdict"), rows))
    for f, c in conv:
        for w in c["warnings"] if c["verdict"] != "good" else ():
            console.print(Text(f"{f}: warning: {w}"), soft_wrap=True)
        if c["verdict"] == "poor" and accept_poor:
            console.print(Text(f"{f}: fitted despite a poor conversion (--accept-poor): {'; '.join(c['reasons'])}"),
                          soft_wrap=True)


def _summary_table(bundle, variance: float):
    import numpy as np
    from rich.table import Table

    m, man = bundle.model, bundle.manifest
    cum = np.cumsum(m.all_explained_variance_ratio_)
    t = Table(title=f"synergy bundle {bundle.spec}", show_header=False)
    t.add_column("", style="bold")
    t.add_column("", overflow="fold")
    t.add_row("trials", str(man["n_trials"]))
    t.add_row("frames", str(man["n_samples"]))
    t.add_row("tasks", ", ".join(man["tasks"]) or "-")
    for k in (1, 2, 3, 6):
        if k <= cum.size:
            t.add_row(f"variance, {k} PC{'s' if k > 1 else ''}", _pct(cum[k - 1]))
    t.add_row(f"PCs for {_pct(variance)}", str(m.n_components_))
    if "heldout" in man:
        rms = np.degrees(man["heldout"]["rms_rad"][m.n_components_])
        t.add_row(f"held-out RMS at {m.n_components_} PCs", f"{rms:.2f}° ({man['heldout']['method']})")
    t.add_row("file", str(bundle.path))
    return t


# ----------------------------------------------------------------------------- registry views
@app.command("list")
@_errors_exit_2
def list_(registry: List[Path] = typer.Option(None, "-r", "--registry", help=REGISTRY_HELP)):
    """List the bundles in all registries."""
    from rich.table import Table
    from rich.text import Text

    from synergy.bundle import verified_manifest
    from synergy.registry import list_bundles
    from synergy.errors import BundleError

    t = Table(title="synergy bundles")
    for col in ("name", "version", "tasks", "frames", "PCs", "path"):
        t.add_column(col, overflow="fold")
    for ref in list_bundles(registry):
        try:
            man = verified_manifest(ref.path)
            t.add_row(ref.name, ref.version, ", ".join(man["tasks"]) or "-", str(man["n_samples"]),
                      str(man["n_components"]), str(ref.path))
        except BundleError as err:
            t.add_row(ref.name, ref.version, Text(f"invalid: {err.reason}", style="red"), "", "", str(ref.path))
    _console().print(t)


@app.command()
@_errors_exit_2
def info(
    spec: str = typer.Argument(..., help="NAME, NAME@VERSION or path to a .npz."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help=REGISTRY_HELP),
):
    """Show a bundle's manifest and spectrum."""
    import numpy as np
    from rich.table import Table

    from synergy.bundle import load_bundle

    b = load_bundle(spec, registry)
    man, m = b.manifest, b.model
    console = _console()
    head = Table(title=f"{b.spec}", show_header=False)
    head.add_column("", style="bold")
    head.add_column("", overflow="fold")
    for key in ("created", "tasks", "n_samples", "n_trials", "n_components", "variance", "units"):
        val = man[key]
        head.add_row(key, ", ".join(val) if isinstance(val, list) else str(val))
    head.add_row("generator", f"{man['generator']['name']} {man['generator']['version']}")
    head.add_row("hand model", f"{man['hand_model']['name']} ({man['hand_model']['sha256'] or 'no hash'})")
    head.add_row("arrays sha256", man["arrays_sha256"])
    head.add_row("file", str(b.path))
    console.print(head)
    cum = np.cumsum(m.all_explained_variance_ratio_)
    spec_t = Table(title="spectrum")
    for col in ("PC", "variance", "cumulative", "PC min", "PC max", "held-out RMS"):
        spec_t.add_column(col, justify="right")
    ho = man.get("heldout", {}).get("rms_rad")
    for i in range(cum.size):
        spec_t.add_row(str(i + 1), _pct(m.all_explained_variance_ratio_[i]), _pct(cum[i]),
                       f"{m.pc_min_[i]:.3f}", f"{m.pc_max_[i]:.3f}",
                       f"{np.degrees(ho[i + 1]):.2f}°" if ho else "-")
    console.print(spec_t)
    src = Table(title="sources")
    for col in ("path", "task", "frames", "sha256"):
        src.add_column(col, overflow="fold")
    for s in man["sources"]:
        src.add_row(s["path"], s["task"] or "-", str(s["frames"]), (s["sha256"] or "-")[:16])
    console.print(src)


@app.command()
@_errors_exit_2
def select(
    task: str = typer.Option(..., "--task", help="Task label."),
    variance: float = typer.Option(0.99, "--variance", help="Variance fraction to reach."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help=REGISTRY_HELP),
):
    """Which bundle serves a task, and how many PCs reach the variance."""
    import numpy as np

    from synergy.bundle import ranked_bundles, selection_key

    _check_variance(variance)
    ranked = ranked_bundles(task, registry)
    b = ranked[0]
    k = b.model.n_components_for(variance)
    got = float(np.cumsum(b.model.all_explained_variance_ratio_)[k - 1])
    typer.echo(f"{b.spec}\t{k} PC{'s' * (k != 1)} ({_pct(got)} variance)\t{b.path}")
    tied = [o.spec for o in ranked[1:] if selection_key(o)[:2] == selection_key(b)[:2]]
    if tied:
        # the name broke the tie: say so, the choice is the user's to make with NAME
        _console(stderr=True).print(f"note: {b.spec} ties with {', '.join(tied)} ({len(b.tasks)} task"
                                    f"{'s' * (len(b.tasks) != 1)}, {b.manifest['n_samples']} samples each): "
                                    "chosen by name; give the bundle by name to choose another")


@app.command()
@_errors_exit_2
def compare(
    a: str = typer.Argument(..., help="First bundle (NAME, NAME@VERSION or path)."),
    b: str = typer.Argument(..., help="Second bundle."),
    max_k: int = typer.Option(6, "--max-k", help="Largest subspace dimension."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help=REGISTRY_HELP),
):
    """Principal angles (degrees) between the first k PCs of two bundles, k = 1..max-k."""
    import numpy as np
    from rich.table import Table

    from synergy.bundle import load_bundle
    from synergy.errors import BundleError
    from synergy.pca_analysis import principal_angles

    ba, bb = load_bundle(a, registry), load_bundle(b, registry)
    if ba.dof_names != bb.dof_names:
        raise BundleError(f"{ba.spec} vs {bb.spec}", "the bundles have different DoF names")
    kmax = min(max_k, ba.model.all_components_.shape[0], bb.model.all_components_.shape[0])
    t = Table(title=f"principal angles: {ba.spec} vs {bb.spec}")
    for col in ("k", "largest", "all angles (deg)"):
        t.add_column(col, justify="right" if col != "all angles (deg)" else "left")
    for k in range(1, kmax + 1):
        ang = np.degrees(principal_angles(ba.model, bb.model, k))
        t.add_row(str(k), f"{ang[-1]:.2f}", " ".join(f"{x:.2f}" for x in ang))
    _console().print(t)


# ----------------------------------------------------------------------------- plots
@app.command()
@_errors_exit_2
def plot(
    spec: str = typer.Argument(..., help="NAME, NAME@VERSION or path to a .npz."),
    out: Optional[Path] = typer.Option(None, "-o", "--out", help="Output folder for the PNGs [figs; with --rerun, only when given]."),
    heldout: List[Path] = typer.Option(None, "--heldout", help="Held-out posture file(s) for the reconstruction curve (repeatable)."),
    fmt: str = typer.Option("auto", "--format", help="Format of --heldout files."),
    registry: List[Path] = typer.Option(None, "-r", "--registry", help=REGISTRY_HELP),
    rerun: Optional[Path] = typer.Option(None, "--rerun", help="Write a Rerun recording (.rrd): the hand swept from −2σ to +2σ along each PC on the 'sweep' timeline (extra [viz])."),
    pcs: int = typer.Option(3, "--pcs", help="PCs in the --rerun sweep."),
    steps: int = typer.Option(21, "--steps", help="Steps of the --rerun sweep."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace existing output PNGs (named NAME-VERSION-KIND.png) and an existing --rerun file."),
):
    """Scree/cumulative-variance PNG, the hand at μ ± 2σ along PC1–3 (paper Fig. 6), and reconstruction
    error vs PCs if held-out data exist; with --rerun, the synergies in the 3-D viewer. Existing
    outputs are kept unless --overwrite."""
    from handmodel.fileio import check_output

    if out is None and rerun is None:
        out = Path("figs")
    if out is not None:
        check_output(out, folder=True)  # before the bundle and held-out files are read
    if rerun is not None:
        _check_new_file(rerun, overwrite)
    import numpy as np

    from synergy.bundle import load_bundle
    from synergy.fit import read_trial
    from synergy.plots import bundle_figures, figure_paths

    b = load_bundle(spec, registry)
    if out is not None:
        for p in figure_paths(b, out, heldout=bool(heldout)):  # the PNGs' names need the bundle's version
            _check_new_file(p, overwrite)
        X = np.vstack([read_trial(f, fmt).postures for f in heldout]) if heldout else None
        for p in bundle_figures(b, out, heldout=X, overwrite=overwrite):
            typer.echo(str(p))
    if rerun is not None:
        from synergy.viewer import write_synergy_rrd  # an optional extra ([viz]): loaded only when asked for

        typer.echo(str(write_synergy_rrd(b, rerun, n_pcs=pcs, steps=steps, overwrite=overwrite)))


from synergy import cli_mocap  # noqa: E402

cli_mocap.register(app, _errors_exit_2)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":
    main()
