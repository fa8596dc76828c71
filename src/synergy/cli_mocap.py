"""``synergy simulate``, ``synergy calibrate`` and ``synergy angles``: mocap trials in; C3D, a subject
calibration or joint-angle tables out.

Library modules (and numpy, pandas) are imported inside the commands so that ``synergy --help`` answers at once.
"""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer


def _console(stderr: bool = False):
    from rich.console import Console

    return Console(stderr=stderr)


def register(app, errors_exit_2) -> None:
    """Add the commands to the ``synergy`` typer app (works when cli.py runs as __main__ too)."""
    app.command()(errors_exit_2(simulate))
    app.command()(errors_exit_2(calibrate))
    app.command()(errors_exit_2(angles))


class _Name:
    """A trial's name on one line, cut in the middle when its column is narrower ("ART-Human…no6dof.c3d"):
    folded, a name took three lines of a 100-column table, and the names of one session differ at the
    end (``trial_01``, ``trial_02``), which a cut at the end would hide. Plain text, never markup."""

    def __init__(self, text: str):
        self.text = text

    def __rich_measure__(self, console, options):
        from rich.cells import cell_len
        from rich.measure import Measurement

        n = cell_len(self.text)
        return Measurement(min(n, 8), n)

    def __rich_console__(self, console, options):
        from rich.text import Text

        yield Text(cut_middle(self.text, options.max_width), no_wrap=True, overflow="crop")


def cut_middle(text: str, width: int) -> str:
    """``text`` in at most ``width`` terminal cells: its start and end around "…" (the end, with the
    distinguishing part of a trial's name, gets the odd cell).

    >>> cut_middle("power_grasp_session_2026_trial_01.c3d", 20)
    'power_gra…ial_01.c3d'
    >>> cut_middle("short.c3d", 20)
    'short.c3d'
    """
    from rich.cells import cell_len

    if cell_len(text) <= width:
        return text
    if width < 3:
        return "…"[:width]
    head_room = (width - 1) // 2
    tail_room = width - 1 - head_room
    head, tail = "", ""
    for ch in text:  # cell by cell: a wide character takes two
        if cell_len(head + ch) > head_room:
            break
        head += ch
    for ch in reversed(text):
        if cell_len(ch + tail) > tail_room:
            break
        tail = ch + tail
    return f"{head}…{tail}"


def fit_table(title, columns, rows, *, names_first=True):
    """A rich table that fits the terminal (80 columns at least): numbers are never cut; the
    first column (names) takes the room left and stays on one line, cut in the middle if it must
    be (:func:`cut_middle`; the files written keep full paths)."""
    from rich.markup import escape
    from rich.table import Table

    table = Table(title=escape(title), title_justify="left", pad_edge=False, collapse_padding=True)
    for i, c in enumerate(columns):
        if i == 0 and names_first:  # wrappable for rich, so that this column is the one narrowed
            table.add_column(c, overflow="crop", ratio=1, min_width=8)
        else:
            table.add_column(c, justify="right", no_wrap=True)
    for r in rows:
        # file names are shown as typed, not read as markup
        table.add_row(*(_Name(str(x)) if i == 0 and names_first else escape(str(x)) for i, x in enumerate(r)))
    return table


#: What the tables' "med mm" and "95th mm" are: the one residual every message gives (the calibration's
#: held-out check, :func:`synergy.calibrate.held_out_line`, is the same median on its frames).
RESIDUAL_COLUMNS = "med/95th mm: median marker residual over frames and its 95th percentile"


def describe_trial(name, df) -> list:
    """Lines a user reads under the summary table: calibration as estimated, the worst markers,
    joints on limits, the handedness check, warnings."""
    import numpy as np
    from rich.markup import escape

    from synergy.calibrate import held_out_line

    d = df.attrs.get("diagnostics", {})
    cal = df.attrs.get("calibration", {})
    out = [f"[bold]{escape(name)}[/bold] ({d.get('verdict', '?')}): noise floor (median marker residual) "
           f"{d.get('noise_floor_mm', float('nan')):.2f} mm, a frame poor above {d.get('poor_threshold_mm', float('nan')):.2f} mm"]
    line = f"  calibration: {cal.get('method', 'none')}, hand scale {cal.get('scale', 1.0):.3f}"
    if cal.get("bone_scales"):
        f = np.array([v * cal.get("scale", 1.0) for v in cal["bone_scales"].values()])
        line += f", bones {f.min():.2f}–{f.max():.2f}× the model"
    h = cal.get("held_out") or {}
    if h.get("frames"):
        # one residual everywhere: the median marker residual (the table's "med mm"), here on the
        # calibration's held-out frames, for both hands it compared
        used = "hand scale only" if "not used" in cal.get("method", "") else "calibrated"
        line += f"; {held_out_line(h)}; the table's hand: {used}"
    out.append(line)
    pp = df.attrs.get("posture_prior")
    sd = d.get("posterior_sd_deg") or {}
    if pp:
        out.append(f"  posture prior: {escape(pp['name'])} (floor {pp['floor_deg']:g}°), against a marker noise of "
                   f"{df.attrs.get('marker_noise_mm') or float('nan'):.2f} mm")
    if d.get("prior_driven"):
        out.append("  weakly observed: prior-driven: " + ", ".join(
            f"{escape(k)} SD {v[0]:.1f}° (markers alone {v[1]:.0f}°)" for k, v in d["prior_driven"].items()))
    elif sd:
        worst = max(sd.items(), key=lambda kv: kv[1][0] if kv[1][0] is not None else -1)
        out.append(f"  every joint observed by the markers on the calibrated hand (largest posterior SD: "
                   f"{escape(worst[0])} {worst[1][0]:.1f}°)")
    if d.get("calibration_open_zeros"):
        # a constant offset of the whole trial, which no per-frame SD shows: the calibration could not fix
        # where these joints' zeros are (no static trial or open-hand frames), only its priors did
        out.append("  weakly observed: calibration-driven zeros (SD of the trial's mean angle): " + ", ".join(
            f"{escape(k)} {v:.0f}°" for k, v in sorted(d["calibration_open_zeros"].items(), key=lambda kv: -kv[1])))
    mr = d.get("marker_residuals_mm", {})
    if mr:
        worst = sorted(mr.items(), key=lambda kv: -(kv[1][0] or 0))[:4]
        out.append("  worst markers (median/95th mm): " + ", ".join(f"{k} {v[0]:.1f}/{v[1]:.1f}" for k, v in worst))
    hc = d.get("handedness")
    if hc:
        out.append(f"  hand check (median marker residual, hand scale only): {hc['chosen']} {hc['residual_mm']:.2f} mm, "
                   f"other hand {hc['other_residual_mm']:.2f} mm"
                   f" ({hc['verdict']})")
    for w in d.get("warnings", []):
        out.append(f"  [yellow]warning:[/yellow] {escape(w)}")
    return out


def simulate(
    out: Path = typer.Option(..., "-o", "--out", help="Output folder for the C3D files (created)."),
    motions: str = typer.Option("all", "--motions", help="Comma-separated motions, or 'all'."),
    trials: int = typer.Option(2, "--trials", help="Trials per motion (different seeds)."),
    markers: str = typer.Option("hand16", "--markers", help="Marker set to simulate."),
    hand: str = typer.Option("left", "--hand", help="left or right."),
    duration: float = typer.Option(4.0, "--duration", help="Seconds per trial."),
    rate: float = typer.Option(100.0, "--rate", help="Frame rate (Hz)."),
    noise_mm: float = typer.Option(0.3, "--noise-mm", help="Marker noise σ (mm)."),
    gaps: float = typer.Option(0.02, "--gaps", help="Fraction of each marker's samples lost in occlusion gaps."),
    scale: float = typer.Option(1.0, "--scale", help="Subject's hand size relative to the default hand."),
    bone_range: float = typer.Option(0.0, "--bone-range", help="Each bone × a random factor in 1 ± this."),
    marker_shift_mm: float = typer.Option(0.0, "--marker-shift-mm", help="Move each marker up to this far (mm, per axis) from its nominal place."),
    units: str = typer.Option("mm", "--units", help="C3D length unit: mm, cm or m."),
    prefix: str = typer.Option("Sim", "--prefix", help="Subject prefix of the labels ('' for none)."),
    seed: int = typer.Option(0, "--seed"),
):
    """Simulate mocap trials of procedural hand motions (C3D + ground-truth angles + task map)."""
    from handmodel.fileio import check_output

    check_output(out, folder=True)  # a read-only or full disk fails before anything is simulated
    from rich.progress import Progress

    from synergy.errors import SynergyError
    from synergy.simulate import CALIBRATION_MOTIONS, MOTIONS, random_subject, write_trials

    known = {**MOTIONS, **CALIBRATION_MOTIONS}
    names = list(MOTIONS) if motions == "all" else [m.strip() for m in motions.split(",") if m.strip()]
    for n in names:
        if n not in known:
            raise SynergyError(n, f"unknown motion (known: {', '.join(known)})")
    bones, shift = (random_subject(markers, bone_range=bone_range, marker_shift_mm=marker_shift_mm, seed=seed)
                    if bone_range or marker_shift_mm else (None, None))
    if units not in ("mm", "cm", "m"):
        raise SynergyError("--units", f"must be mm, cm or m, got {units!r}")
    if trials < 1 or duration <= 0 or rate <= 0:
        raise SynergyError("simulate", "--trials, --duration and --rate must be positive")
    with Progress(console=(c := _console(stderr=True)), transient=True, disable=not c.is_terminal) as progress:
        bar = progress.add_task("simulating", total=len(names) * trials)
        rows = write_trials(out, names, trials=trials, markers=markers, hand=hand, duration=duration, rate=rate,
                            noise_mm=noise_mm, gaps=gaps, scale=scale, bone_scales=bones, marker_shift=shift,
                            units=units, prefix=prefix, seed=seed, on_trial=lambda: progress.advance(bar))
    _console().print(fit_table(f"simulated {len(rows)} trials → {out}", ("file", "motion", "task", "frames", "gap %"),
                               rows))


def calibrate(
    trial: Path = typer.Argument(..., help="Range-of-motion trial (C3D) to calibrate on (or the trial itself)."),
    markers: str = typer.Option(..., "--markers", help="Marker set name or YAML file."),
    hand: str = typer.Option("left", "--hand", help="left or right."),
    out: Path = typer.Option(..., "-o", "--out", help="Subject calibration YAML (never overwritten)."),
    static: Optional[Path] = typer.Option(None, "--static", help="Static trial in the flat-hand posture, fitted together with TRIAL."),
    frames: int = typer.Option(150, "--frames", help="Calibration frames sampled from the trial."),
    held_out: float = typer.Option(0.25, "--held-out", help="Share of frames held out to check the calibration."),
    force: bool = typer.Option(False, "--force", help="Write the calibration even if the held-out check fails."),
    smooth_hz: float = typer.Option(6.0, "--smooth-hz", help="Low-pass the markers (Hz) before calibrating (0: raw markers)."),
):
    """Estimate the subject's bone lengths, finger bases and marker places (synergy angles/fit --subject)."""
    from handmodel.fileio import check_output
    from synergy.errors import SynergyError

    if out.exists() and not out.is_dir():
        raise SynergyError(out, "exists and is never overwritten (choose another -o)")
    check_output(out)  # a read-only or full disk fails before the calibration, not after it
    from rich.markup import escape

    from handmodel import HandModel
    from synergy.c3d import read_c3d
    from synergy.angles import OPEN_ZERO_DEG
    from synergy.calibrate import calibrate as run, held_out_line, save_calibration
    from synergy.markers import load_markerset

    ms = load_markerset(markers)
    msh = ms.for_hand(hand)
    base = HandModel.load(ms.hand_model, right=hand == "right")
    data = read_c3d(trial)
    st = read_c3d(static) if static is not None else None
    with _console(stderr=True).status("calibrating"):
        cal = run(data, msh, base, right=hand == "right", frames=frames, held_out=held_out, static=st,
                  smooth_hz=smooth_hz or None, neutral=st is None)
    con = _console()
    con.print(f"[bold]{escape(trial.name)}[/bold]: {cal.method}")
    rows = [("hand scale", f"{cal.scale:.3f}", "")]
    unc = cal.uncertainty
    for k, v in cal.bone_scales.items():
        sd = unc.get("bone_scales", {}).get(k)
        rows.append((f"bone to {k}", f"{v * cal.scale:.3f}", f"{sd * cal.scale:.3f}" if sd is not None else ""))
    for k, v in cal.joint_positions.items():
        sd = unc.get("joint_positions_mm", {}).get(k)
        rows.append((f"{k} on palm (mm)", " ".join(f"{1000 * x:.1f}" for x in v),
                     f"{max(sd):.1f}" if sd else ""))
    for k, v in cal.marker_shift_mm.items():
        sd = unc.get("offsets_mm", {}).get(k)
        rows.append((f"marker {k} moved (mm)", f"{v:.1f}", f"{max(sd):.1f}" if sd else ""))
    for k, v in sorted(unc.get("joint_zero_deg", {}).items(), key=lambda kv: -kv[1]):
        if v > OPEN_ZERO_DEG:  # left to the priors: the trials' angles of this joint may be off by a constant
            rows.append((f"{k} zero (°), open", "–", f"{v:.1f}"))
    con.print(fit_table("estimated (× the model; SD)", ("what", "estimate", "SD"), rows))
    if cal.held_out.get("frames"):
        con.print(held_out_line(cal.held_out))
    for w in cal.warnings:
        _console(stderr=True).print(f"warning: {escape(w)}")
    if cal.overfit and not force:
        raise SynergyError(trial, "calibration failed its held-out check (not written; record a longer range "
                                  "of motion, add --static, or --force)")
    save_calibration(cal, out)
    con.print(f"wrote {escape(str(out))}")


def angles(
    files: List[Path] = typer.Argument(..., help="C3D trials."),
    markers: Optional[str] = typer.Option(None, "--markers", help="Marker set name or YAML file [chosen from each trial's labels, as synergy fit]."),
    hand: Optional[str] = typer.Option(None, "--hand", help="left or right [from the labels, else the hand whose fit explains the markers, as synergy fit]."),
    out: Path = typer.Option(..., "-o", "--out", help="Output folder: one CSV per trial (never overwritten)."),
    smooth_hz: Optional[float] = typer.Option(None, "--smooth-hz", help="Low-pass the markers (Hz) before IK."),
    subject: Optional[Path] = typer.Option(None, "--subject", help="Subject calibration from 'synergy calibrate'."),
    static: Optional[Path] = typer.Option(None, "--static", help="Calibrate (hand scale) on this static trial instead of each trial."),
    no_calibration: bool = typer.Option(False, "--no-calibration", help="Use the model as it is."),
    plot: bool = typer.Option(False, "--plot", help="Also write a PNG per trial: angles with their posterior SD band and per-marker residuals."),
    no_hand_check: bool = typer.Option(False, "--no-hand-check", help="Convert even if the other hand fits clearly better."),
    dip_prior_sd: Optional[float] = typer.Option(None, "--dip-prior-sd", help="SD (degrees) of the weak DIP = 2/3 PIP prior that decides DIPs the markers leave open (default 10; 0: off)."),
    prior: str = typer.Option("auto", "--prior", help="Posture prior: auto (the fingerfist bundle where the markers leave a joint weakly observed, and in the calibration of a trial without a static trial or open-hand frames), none, or a bundle NAME / path (recorded in the CSV)."),
):
    """Convert C3D trials to joint-angle tables (marker IK), with a summary per trial."""
    from handmodel.fileio import check_output

    check_output(out, folder=True)  # a read-only or full disk fails before any trial is converted
    import time

    import numpy as np
    from rich.progress import Progress

    from handmodel import HandModel
    from synergy.angles import markers_to_angles, write_angles_csv
    from synergy.c3d import read_c3d
    from synergy.calibrate import calibrate as run, load_calibration
    from synergy.errors import SynergyError
    from synergy.fit import _choose
    from synergy.markers import load_markerset

    if dip_prior_sd is not None and not dip_prior_sd >= 0:
        raise SynergyError("--dip-prior-sd", f"must be 0 (off) or a positive SD in degrees, got {dip_prior_sd}")
    if hand is not None and hand not in ("left", "right"):
        raise SynergyError("--hand", f"must be left or right, got {hand!r}")
    coupling = {} if dip_prior_sd is None else {"ip_coupling_sd_deg": dip_prior_sd or None}
    from synergy.prior import prior_option

    coupling["prior"] = prior_option(prior)
    ms = load_markerset(markers) if markers is not None else None
    targets = [(f, out / f"{f.stem}.csv") for f in files]
    for f, dst in targets:
        if dst.exists():
            raise SynergyError(dst, "exists and is never overwritten (choose another -o)")
    if sum(x is not None for x in (subject, static)) + no_calibration > 1:
        raise SynergyError("angles", "give at most one of --subject, --static and --no-calibration")
    cal = "trial"
    if no_calibration:
        cal = None
    elif subject is not None:
        cal = load_calibration(subject)
    elif static is not None:
        # the static trial decides the set and hand of every trial it calibrates
        sdata = read_c3d(static)
        ms, hand, _ = _choose(sdata, static, ms, hand, None, not no_hand_check, None)
        cal = run(sdata, ms.for_hand(hand), HandModel.load(ms.hand_model, right=hand == "right"),
                  right=hand == "right", subject=False)
        cal.source = str(static)
    rows, notes, chosen = [], [], set()
    failed = []
    with Progress(console=(c := _console(stderr=True)), transient=True, disable=not c.is_terminal) as progress:
        bar = progress.add_task("converting", total=len(files))
        for f, dst in targets:
            progress.update(bar, description=f"{f.name}")
            try:
                data = read_c3d(f)
                # as synergy fit reads it: the set the labels fit, the hand they name or whose fit explains them
                ms_f, hand_f, _ = _choose(data, f, ms, hand, cal, not no_hand_check, None)
                chosen.add((ms_f.name, hand_f))
                t0 = time.perf_counter()
                df = markers_to_angles(data, ms_f, hand=hand_f, calibration=cal, smooth_hz=smooth_hz,
                                       check_hand=None if no_hand_check else "stop", **coupling)
                dt = time.perf_counter() - t0
                write_angles_csv(df, dst)
                if plot:
                    plot_trial(df, dst.with_suffix(".png"))
            except SynergyError as err:  # one bad trial does not stop the others; its error ends the output
                failed.append(err)
                progress.advance(bar)
                continue
            r = df["residual_mm"].to_numpy()
            d = df.attrs["diagnostics"]
            rows.append((f.name, len(df), f"{100 * df.attrs['gap_fraction']:.1f}", f"{np.nanmedian(r):.2f}",
                         f"{np.nanpercentile(r, 95):.2f}", f"{100 * (df['quality'] == 'ok').mean():.1f}",
                         d["verdict"], f"{len(df) / dt:,.0f}"))
            notes += describe_trial(f.name, df)
            progress.advance(bar)
    con = _console()
    if rows:  # every trial failed: only their errors, no empty table headed by a guess
        sets = "/".join(sorted({m for m, _ in chosen}))
        hands = "/".join(sorted({h for _, h in chosen}))
        con.print(fit_table(f"marker IK ({sets}, {hands} hand; {RESIDUAL_COLUMNS}) → {out}",
                            ("trial", "frames", "gap %", "med mm", "95th mm", "ok %", "verdict", "frames/s"), rows))
    for line in notes:
        con.print(line)
    if failed:
        from handmodel.cliutil import print_error

        for err in failed:  # last, plainly, one line each: nothing printed after an error
            print_error(err)
        raise typer.Exit(2)


def plot_trial(df, path: Path) -> Path:
    """PNG of a converted trial: the 20 joint angles over time (one panel per digit) with a band of
    ±1 posterior SD, and each marker's residual (median and 95th percentile); written atomically,
    never overwritten."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from handmodel.fileio import atomic_path
    from synergy.errors import SynergyError

    if path.exists():
        raise SynergyError(path, "exists and is never overwritten (choose another -o)")
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    t = df["time_s"].to_numpy()
    for ax, f in zip(axes.flat[:5], ("thumb", "index", "middle", "ring", "pinky")):
        for c in ("1_abd", "1_flex", "2_flex", "3_flex"):
            y = np.degrees(df[f"{f}{c}"].to_numpy())
            (line,) = ax.plot(t, y, lw=1, label=c)
            if f"{f}{c}_sd" in df:  # ±1 posterior SD (tables written before issue 40 have none)
                sd = np.degrees(df[f"{f}{c}_sd"].to_numpy())
                ax.fill_between(t, y - sd, y + sd, color=line.get_color(), alpha=0.2, lw=0)
        poor = df["quality"].to_numpy() != "ok"
        if poor.any():
            ax.plot(t[poor], np.zeros(poor.sum()), "|", color="red", ms=8, label="poor/gap")
        ax.set_title(f)
        ax.set_xlabel("time (s)")
        ax.set_ylabel("angle (°)")
        ax.legend(fontsize=7, loc="lower left")
    ax = axes.flat[5]
    mr = df.attrs.get("diagnostics", {}).get("marker_residuals_mm", {})
    labels = list(mr)
    ax.bar(range(len(labels)), [mr[k][1] for k in labels], color="0.8", label="95th percentile")
    ax.bar(range(len(labels)), [mr[k][0] for k in labels], color="C0", label="median")
    ax.set_xticks(range(len(labels)), labels, rotation=90, fontsize=7)
    ax.set_ylabel("marker residual (mm)")
    ax.legend(fontsize=7)
    d = df.attrs.get("diagnostics", {})
    pp = (df.attrs.get("posture_prior") or {}).get("name") or "none"
    fig.suptitle(f"{Path(df.attrs.get('source', '')).name}: {d.get('verdict', '')}, noise floor "
                 f"{d.get('noise_floor_mm') or float('nan'):.2f} mm; bands ±1 posterior SD (posture prior: {pp})")
    with atomic_path(path, overwrite=False) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)
    return path
