"""riskplan: risk-averse sensor planning with distributed CVaR policy gradients.

Python API (the same composition, validation and files as the CLI):
    cfg = riskplan.compose(["risk=neutral", "seed=3"])
    run = riskplan.train(cfg, "outputs/runs/my_run")
    run = riskplan.load_run("outputs/runs/my_run")   # .metrics .eval .trajectories .config .summary .complete
    done = riskplan.sweep(["risk.beta=0.05,0.1", "seed=range(0,3)"])   # .summary (DataFrame) .sweep_dir .ok
    page = riskplan.report([done.sweep_dir])           # -> <sweep_dir>/report/report.html

riskplan.BadInput is the error every bad input raises (its str() is the one line the CLI prints), and riskplan.Run
the type of a loaded run; both load when first used.
"""

from __future__ import annotations

from riskplan.version import __version__

__all__ = ["BadInput", "Run", "__version__", "compose", "load_run", "report", "sweep", "train"]
# Loaded on first use: Run's module needs pandas, which `import riskplan` does not load.
_LAZY = {"BadInput": "riskplan.util.errors", "Run": "riskplan.run.results"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'riskplan' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)


def compose(overrides=()):
    """Compose and validate a config from Hydra overrides (riskplan.run.compose.compose)."""
    from riskplan.run.compose import compose as _compose
    from riskplan.util.api_args import overrides_list

    return _compose(overrides_list(overrides))


def train(config, out_dir, progress: bool = True):
    """Train, evaluate and record one experiment into out_dir; returns its Run (riskplan.run.training.train).

    With `progress`, a live bar on a terminal or in a Jupyter notebook (nothing is printed elsewhere)."""
    from riskplan.config.hydra_safety import check_resolvers
    from riskplan.run.run_directory import check_new_run_dir
    from riskplan.run.training import train as _train
    from riskplan.util.api_args import a_flag, a_path
    from riskplan.util.errors import BadInput
    from riskplan.util.paths import check_output_dir
    from riskplan.util.progress import TrainingBar, silent

    if config is None or isinstance(config, (str, bytes, list, tuple)):
        raise BadInput("config", f"got {config!r}; give a composed config, e.g. riskplan.compose(['risk=neutral'])")
    check_resolvers(config)  # a value edited in after compose: ${oc.env:...} would not read back as it ran
    out = check_output_dir(a_path(out_dir, "out_dir"), "out_dir")
    a_flag(progress, "progress")
    check_new_run_dir(out, "out_dir")  # a run never writes among other files; `riskplan train --resume` resumes
    with TrainingBar() if progress else silent() as bar:
        return _train(config, out, progress=bar)


def load_run(path):
    """Load a run directory (tables rebuilt from run.mcap if needed) (riskplan.run.results.load_run)."""
    from riskplan.run.results import load_run as _load_run
    from riskplan.util.api_args import a_path
    from riskplan.util.errors import BadInput

    run_dir = a_path(path, "path")
    if not run_dir.exists():
        raise BadInput(str(run_dir), "does not exist; give a run directory")
    return _load_run(run_dir)


def sweep(overrides=(), jobs=None, sweep_dir=None, batch=None):
    """Run a grid of experiments (or an Optuna study) as `riskplan sweep OVERRIDES --jobs JOBS [--batch]` does, into
    a new outputs/sweeps/<timestamp>/ or `sweep_dir` (finished jobs there are skipped). Returns the outcome:
    `.summary` (the summary.parquet table), `.sweep_dir`, `.failed` [(job, error)], `.ok`
    (riskplan.experiments.sweeping.run_sweep). The jobs that share a world train as one program (batched) unless
    `batch=False` or `jobs` asks for a worker process per job."""
    from riskplan.experiments.sweeping import run_sweep
    from riskplan.util.api_args import a_path, optional_count, optional_flag, overrides_list
    from riskplan.util.paths import check_output_dir

    args, jobs, batch = overrides_list(overrides), optional_count(jobs, "jobs"), optional_flag(batch, "batch")
    if sweep_dir is not None:
        sweep_dir = check_output_dir(a_path(sweep_dir, "sweep_dir"), "sweep_dir")
    return run_sweep(args, jobs, sweep_dir, out=lambda text: None, batch=batch)


def report(paths, out_dir=None, formats=("png", "pdf")):
    """Figures, tables and report.html from the finished runs below `paths`, as `riskplan report` does; into
    `out_dir` (default: PATH/report for one path, else outputs/reports/<timestamp>/). Returns the page's path
    (riskplan.experiments.reporting.build_report)."""
    from riskplan.experiments.reporting import build_report, check_formats, default_out
    from riskplan.util.api_args import a_path, formats_list, paths_list

    inputs = paths_list(paths, "paths")
    out = a_path(out_dir, "out_dir") if out_dir is not None else default_out(inputs)
    return build_report(inputs, out, check_formats(formats_list(formats), "formats"))
