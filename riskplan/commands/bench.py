"""`riskplan bench`: the speed and memory targets, each printed with its baseline (the measures are the
riskplan.experiments.bench_* modules')."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import typer

from riskplan.commands.common import bad_input_exits
from riskplan.util.errors import BadInput

SCALING_PLOT = "outputs/bench/scaling.png"
PLOT_TYPES = (".png", ".pdf", ".svg")  # what the scaling plot's writer takes (with its metadata)


def register(app: typer.Typer) -> None:
    """Add `riskplan bench` to the CLI."""
    app.command("bench")(bad_input_exits(bench))


def _instead(flag: str, text: str):
    """A switch that runs another benchmark instead of the targets (--scaling, --sweep, --threads, --reproduce)."""
    return typer.Option(False, flag, help=f"Instead: {text}")


def bench(
    quick: bool = typer.Option(
        False,
        "--quick",
        help="Fewer repeats and a shorter training run (about 45 s on 2 cores, most of it the cold-cache compiles it times).",
    ),
    json_out: str | None = typer.Option(None, "--json", help="Also write the figures to this JSON file."),
    scaling: bool = _instead(
        "--scaling",
        "trajectory-steps/s and bytes per sample against grid size, horizon, sources, source motion and robots, "
        "each against the paper world (about 1 minute, 30 s with --quick).",
    ),
    plot: str | None = typer.Option(
        None,
        "--plot",
        metavar="PNG",
        show_default=False,
        help=f"With --scaling: the plot's file [default: {SCALING_PLOT}].",
    ),
    csv_out: str | None = typer.Option(None, "--csv", help="With --scaling: also write the rows as CSV."),
    sweep: bool = _instead(
        "--sweep",
        "beta x seed sweeps of the paper world (200 iterations, W = 6000): 24 runs batched against --jobs (a worker "
        "per job), 64 runs batched against the bare loops of their trainings, and 256 runs batched against the "
        "time of their episode kernels, replayed, in the same run (about 4 minutes on 2 cores; 12, 16 and 64 runs "
        "of 50 iterations with --quick).",
    ),
    reproduce: bool = _instead(
        "--reproduce",
        "riskplan reproduce --quick batched (the default) against job by job (--jobs, a worker per core), each in a "
        "process of its own, and whether both left the same numbers; then the whole reproduce against the time of "
        "the episode and bootstrap kernels its runs ran, replayed (about 5 minutes on 2 cores; the first row alone "
        "with --quick).",
    ),
    threads: bool = _instead(
        "--threads",
        "the rollout kernel and the training iteration at 1, 2, 4, ... threads up to the cores "
        "(numba.set_num_threads), at W = 6000 and W = 600,000, each against 1 thread (about 20 s on 2 cores).",
    ),
) -> None:
    """Speed, memory, JIT, start-up and team-scaling targets, each with a baseline measured in the same run."""
    import numba
    from rich.console import Console

    _check_modes({"--scaling": scaling, "--sweep": sweep, "--reproduce": reproduce, "--threads": threads})
    if not scaling:
        for flag, given in (("--plot", plot), ("--csv", csv_out)):
            if given is not None:
                raise BadInput(
                    flag, f"got {given}; it applies with --scaling only (riskplan bench --scaling {flag} ...)"
                )
    json_out, csv_out, plot = _check_outputs(json_out, csv_out, (plot or SCALING_PLOT) if scaling else None)

    console = Console(soft_wrap=True)  # one line per figure, also in a log file
    console.print(
        f"numba {numba.__version__}, {numba.get_num_threads()} threads "
        f"({numba.config.THREADING_LAYER} layer), {os.cpu_count()} cores, load average {_load():.2f}"
    )
    if _busy():
        console.print(f"warning: {_busy()}", style="yellow")
    if scaling:
        _scaling(console, quick, json_out, plot, csv_out)
        return
    rows: list[dict] = []
    for section in _sections(console, quick, sweep, threads, reproduce):
        for row in section():  # printed as each section ends, not all at the end of a long benchmark
            _print_row(console, row)
            rows.append({**row, "quick": quick, "load_average": _load()})  # what the JSON says it was measured at
    met = sum(bool(row["ok"]) for row in rows)
    console.print(f"{met} of {len(rows)} targets met (load average {_load():.2f} at the end, {os.cpu_count()} cores)")
    if met < len(rows) and _busy():
        console.print(f"warning: {_busy()}", style="yellow")
    if json_out:  # "ok" as JSON's true or false, whichever type its measure gave
        json_out.write_text(json.dumps([{**row, "ok": bool(row["ok"])} for row in rows], indent=2, default=float))


def _check_modes(modes: dict[str, bool]) -> None:
    """BadInput for two benchmarks asked at once: each runs instead of the targets, one per run."""
    chosen = [flag for flag, on in modes.items() if on]
    if len(chosen) > 1:
        raise BadInput(
            chosen[1], f"given with {chosen[0]}; each runs instead of the targets: give one of {', '.join(modes)}"
        )


def _check_outputs(json_out: str | None, csv_out: str | None, plot: str | None) -> tuple[Path | None, ...]:
    """The files the bench will write, as paths: each in a writable folder and not a folder itself, and the plot a
    type its writer takes. BadInput (one line, exit 2) naming the option otherwise."""
    from riskplan.util.paths import check_output_dir, check_output_file, file_path

    json_path = None if json_out is None else check_output_file(json_out, "--json", ".json")
    csv_path = None if csv_out is None else check_output_file(csv_out, "--csv", ".csv")
    if plot is None:
        return json_path, csv_path, None
    plot_path = file_path(plot, "--plot", ", ".join(PLOT_TYPES))
    if plot_path.suffix.lower() not in PLOT_TYPES or plot_path.is_dir():  # its folder is made when it is written
        raise BadInput("--plot", f"got {plot}; give a file path ending {', '.join(PLOT_TYPES)}")
    check_output_dir(plot_path.parent if str(plot_path.parent) else Path("."), "--plot")
    return json_path, csv_path, plot_path


def _sections(console, quick: bool, sweep: bool, threads: bool, reproduce: bool = False) -> tuple:
    """The benchmarks to run, each a function returning its rows: --sweep's, --threads', --reproduce's, or every
    target's."""
    if reproduce:
        from riskplan.experiments.bench_reproduce import bench_reproduce

        return (lambda: bench_reproduce(quick),)
    if sweep:
        from riskplan.experiments.bench_kernel_share import bench_kernel_share
        from riskplan.experiments.bench_sweep import bench_sweep

        return (lambda: bench_sweep(quick), lambda: bench_kernel_share(quick))
    if threads:
        from riskplan.experiments.bench_threads import bench_threads

        return (lambda: bench_threads(quick),)
    from riskplan.experiments.bench_first_run import bench_first_run
    from riskplan.experiments.bench_loop import bench_loop
    from riskplan.experiments.bench_rollout import bench_rollout
    from riskplan.experiments.bench_startup import bench_jit, bench_startup
    from riskplan.experiments.bench_training import bench_checkpoints, bench_measures, bench_team, bench_training

    return (
        lambda: bench_rollout(quick),
        lambda: _gpu_rows(console, quick),
        lambda: bench_training(quick),
        lambda: bench_loop(quick),
        lambda: bench_measures(quick),
        lambda: bench_checkpoints(quick),
        bench_jit,
        lambda: bench_first_run(quick),
        lambda: bench_startup(quick),
        lambda: bench_team(quick),
    )


def _gpu_rows(console, quick: bool) -> list[dict]:
    """The GPU rows where a GPU is present; elsewhere one line saying why they were skipped."""
    from rich.markup import escape

    from riskplan.experiments.bench_gpu import Skipped, bench_gpu

    try:
        return bench_gpu(quick)
    except Skipped as why:
        why = escape(str(why))  # its pip install names [cuda], which is no style tag
        console.print(f"[bold]GPU rollout kernel[/bold]: skipped; {why}")
        return []


def _print_row(console, row: dict) -> None:
    """One target: its value against the target, then its baseline and note."""
    mark = "met" if row["ok"] else "NOT MET"
    console.print(f"[bold]{row['measure']}[/bold]: {row['value']:.4g} {row['unit']}  (target {row['target']}: {mark})")
    console.print(f"    baseline {row['baseline']:.4g}, ratio {row['ratio']:.3g}; {row['note']}", markup=False)


def _load() -> float:
    """The one-minute load average (0 where the system does not say)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return 0.0


def _busy() -> str:
    """Why timings on this machine are slower now than idle, or "" when it looks idle (load under half a core per
    core)."""
    cores = os.cpu_count() or 1
    load = _load()
    if load < 0.5 * cores:
        return ""
    return (
        f"the machine is busy (load average {load:.2f} on {cores} cores): timings are slower than on an idle "
        "machine, and a target may be missed for that reason alone; run it again when the machine is idle"
    )


def _scaling(console, quick: bool, json_out: Path | None, plot: Path, csv_out: Path | None) -> None:
    """`riskplan bench --scaling`: the table, the slopes beyond the cache, the plot and the files."""
    from riskplan.experiments.bench_scaling import (
        bench_scaling,
        cache_bytes,
        plot_scaling,
        scaling_slopes,
        scaling_table,
    )

    console.print("building every world, then timing each once per round (the best round is kept) ...")
    rows = bench_scaling(quick)
    cache = cache_bytes()
    console.print(scaling_table(rows), markup=False, highlight=False)
    console.print(f"ratios: against the paper world (first row) in this run; L2 cache {cache / 2**20:g} MB per core")
    for dimension, slope in scaling_slopes(rows, cache).items():

        def show(value):
            return "n/a" if value is None else f"{value:+.2f}"

        beyond = (
            ""
            if slope["first_beyond"] is None
            else f"; beyond the L2 cache (from {slope['first_beyond']:g}"
            f"{' cells' if dimension == 'grid' else ''}): iteration {show(slope['beyond_cache'])}, "
            f"kernel {show(slope['kernel_beyond_cache'])}"
        )
        console.print(
            f"slope of log steps/s against log {'cells' if dimension == 'grid' else dimension}: "
            f"iteration {show(slope['all'])}, kernel {show(slope['kernel_all'])}{beyond}"
        )
    console.print(f"plot: {plot_scaling(rows, plot, cache)}")
    if json_out:
        json_out.write_text(json.dumps({"rows": rows, "slopes": scaling_slopes(rows, cache)}, indent=2, default=float))
        console.print(f"json: {json_out}")
    if csv_out:
        with open(csv_out, "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows([{**r, "overrides": " ".join(r["overrides"])} for r in rows])
        console.print(f"csv: {csv_out}")
