"""`riskplan sweep`: a Hydra multirun over a grid of overrides, through a Hydra launcher plugin.

What riskplan adds around Hydra's own multirun (which does the expanding, the launching and the job folders):
- before anything runs: the overrides are parsed and every combination is composed against the schema (a
  malformed override, an unknown key or a badly typed value is bad input, exit 2) and checked by the model; a
  combination the model rejects fails alone when it runs, unless every combination is rejected (exit 2);
- a sweep may hold at most RISKPLAN_MAX_JOBS combinations (default 10,000), counted before they are expanded;
  two combinations that compose to the same config are bad input;
- a fresh sweep directory per command (`outputs/sweeps/<timestamp>[_n]`, claimed with mkdir, so two sweeps
  started in the same second never share one), or `hydra.sweep.dir=DIR` to resume a sweep; the driver holds the
  sweep directory's lock for the whole launch, so two drivers never run in one directory;
- job folders named by what varies, with anything that is not [A-Za-z0-9._=,+-] percent-encoded
  (`riskplan.experiments.sweep_worker.folder_name`), so they are always direct children of the sweep directory;
- jobs that already finished with the same config are skipped (`riskplan.experiments.sweep_worker`), killed ones resume; local
  workers die with the driver;
- one live view of the sweep on the terminal, while Hydra's messages go to `sweep.log` and each job's output
  to its own `job.log`;
- `summary.parquet`: one row per job, with the overrides as columns, the final figures with their 95%
  intervals, the wall time, the status and the error.

An optimising sweeper (hydra/sweeper=optuna) chooses the jobs as it goes (`plan_optimiser`): its search space is
checked with sample values instead of every combination, each trial runs as a sweep job in a numbered folder and
returns its CVaR (None when it failed, which optuna records as a failed trial), and summary.parquet has one row
per trial.

Modules: jobs (what a job is and where it is) -> grid (checks and expansion), launcher_settings (the launcher's
workers and Ray's init arguments) -> launch, summary, view -> search (optimising sweepers) -> plan -> run.
"""

from __future__ import annotations

from riskplan.experiments.sweeping.execute import run_sweep
from riskplan.experiments.sweeping.grid import as_job, constant_keys, expand, sweep_size
from riskplan.experiments.sweeping.jobs import SUMMARY, SWEEPS_ROOT, Job, Outcome, Plan
from riskplan.experiments.sweeping.launch import warm_workers
from riskplan.experiments.sweeping.plan import plan_sweep
from riskplan.experiments.sweeping.summary import report_outcome, summarize

__all__ = [
    "SUMMARY",
    "SWEEPS_ROOT",
    "Job",
    "Outcome",
    "Plan",
    "as_job",
    "constant_keys",
    "expand",
    "plan_sweep",
    "report_outcome",
    "run_sweep",
    "summarize",
    "sweep_size",
    "warm_workers",
]
