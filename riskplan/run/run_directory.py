"""A run directory beside the training loop, the same for both backends: its config file, the refusal to write over
another run, run.mcap opened fresh (with its header) or reopened at a checkpoint, the files of a finished run, and
whether the run has finished."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import yaml
from omegaconf import OmegaConf

from riskplan.config.typed import as_dict, typed
from riskplan.engine.step import RunSetup, starts
from riskplan.engine.team.network import network_metadata
from riskplan.engine.world import world_map
from riskplan.run.columns import Columns, write_parquet
from riskplan.run.foxglove_layout import write_layout
from riskplan.run.maps import map_record
from riskplan.run.provenance import provenance
from riskplan.run.record import RunLog, log_header, resume_log
from riskplan.run.run_files import (
    CONFIG,
    ENDS,
    RECORDS,
    RUN_LOG,
    SUMMARY,
    TABLES,
    is_run_dir,
    other_output,
    remove_temps,
    table_file,
)
from riskplan.util.errors import BadInput
from riskplan.util.lock import LOCK, holder
from riskplan.util.paths import atomic_path, write_atomic


def check_new_run_dir(out: Path, key: str) -> None:
    """A run starts only in a new or empty directory: never over another run's files (resume is explicit)."""
    if not out.is_dir():
        return
    entries = [p for p in out.iterdir() if p.name != LOCK]
    if not entries:
        return
    pid = holder(out)
    if pid is not None:
        raise BadInput(
            str(out),
            f"is in use by another riskplan process (pid {pid or 'unknown'}); one process "
            f"writes a run directory at a time: wait for it to end or stop it",
        )
    other = other_output(out)
    if other is not None:
        raise BadInput(key, f"{out} holds {other}, not a run; give a new or empty directory")
    if is_run_dir(out):
        raise BadInput(
            key, f"{out} already holds a run; resume it with riskplan train --resume {out}, or give a new directory"
        )
    raise BadInput(key, f"{out} is not empty and holds no run; give a new or empty directory")


def refuse_existing_run(out: Path, setup: RunSetup) -> None:
    """A fresh run never writes over another run's files: BadInput naming --resume instead."""
    if any((out / name).exists() for name in RECORDS) or (
        (out / CONFIG).is_file() and _config_changed(out, setup.config)
    ):
        raise BadInput(
            str(out), f"already holds a run; resume it with riskplan train --resume {out}, or give a new directory"
        )


def start_log(out: Path, setup: RunSetup) -> RunLog:
    """A fresh run's run.mcap, with its header (config, provenance, policy, network, world map), after its config
    file; refuses a directory that holds another run."""
    refuse_existing_run(out, setup)
    _write_config(out, setup.config)
    log = RunLog(out / RUN_LOG)
    log.metadata("config", setup.config)
    files = map_record(setup.params.world)
    if files is not None:  # what a resume checks: world.map may name another file from another directory
        log.metadata("map", {"files": files})
    log.metadata("provenance", provenance())
    log.metadata("policy", {"kind": str(setup.policy.kind), "theta_names": list(setup.theta_names)})
    log.network(network_metadata(setup.network))
    log.world_map(world_map(setup.world, starts(setup)))
    return log


def reopen_log(out: Path, setup: RunSetup, iteration: int) -> tuple[RunLog, list[dict]]:
    """run.mcap cut back to a checkpoint at `iteration`, and its metrics rows before it. An extended run
    (`--resume ... train.iterations=N`) gets its new config written and logged, and is not finished until it
    finishes again. Every check comes before the first write."""
    check_same_map(out, setup)
    rows = logged_rows(out / RUN_LOG, iteration, setup.robots, setup.config)
    log = resume_log(out / RUN_LOG, out / RUN_LOG, iteration - 1)
    if _config_changed(out, setup.config):
        _write_config(out, setup.config, replace=True)
        log.metadata("config", setup.config)
    for name in ENDS:
        (out / name).unlink(missing_ok=True)
    remove_temps(out)  # a SIGKILL's leftovers: the files they were to become are written again
    return log, rows


def check_same_map(out: Path, setup: RunSetup, metadata: dict | None = None) -> None:
    """BadInput when the run's map files are not those run.mcap recorded as it started (`metadata`: its records,
    read here when not given): world.map=maps/x.yaml resolved from another working directory, or a map edited in
    place, would go on training the run in another world. A run recorded before riskplan kept its map's identity
    is not checked."""
    if metadata is None:
        metadata = log_header(out / RUN_LOG)[0] if (out / RUN_LOG).is_file() else {}
    recorded = metadata.get("map")
    files = recorded.get("files") if isinstance(recorded, dict) else None
    if not isinstance(files, list):
        return
    for was, now in zip(files, map_record(setup.params.world) or [], strict=False):
        if not isinstance(was, dict) or was.get("sha256") == now["sha256"]:
            continue
        if was.get("path") == now["path"]:
            what = f"{now['path']} has changed since the run started (not the content {RUN_LOG} recorded); restore it"
        else:
            what = (
                f"{now['path']} is not the file the run started with ({was.get('path')}), and its content differs; "
                f"resume from the directory the run was started in"
            )
        raise BadInput(now["key"], f"{what}, or train a new run")


def logged_rows(path: Path, iterations: int, robots: int, config: dict) -> list[dict]:
    """The metrics rows of iterations 0..iterations-1 from run.mcap: what a checkpoint no longer copies.

    Every iteration must be there with one row per robot (and the network average in a team), and the config to
    resume with must be the one the log recorded but for train.iterations; anything else means the log, the
    checkpoint and .hydra/config.yaml are not of one run, which is bad input.
    """
    from riskplan.run.log_reader import read_log  # lazy: pandas, which only a resume needs

    log = read_log(path)
    _check_logged_config(path, log.metadata.get("config"), config)
    metrics = log.metrics
    metrics = metrics[metrics.iteration < iterations]
    per_iteration = robots + (1 if robots > 1 else 0)
    counts = metrics.groupby("iteration").size()
    if len(counts) != iterations or (iterations and not bool((counts == per_iteration).all())):
        raise BadInput(
            str(path),
            f"holds rows that do not match the checkpoint (iteration {iterations}, "
            f"{per_iteration} rows per iteration); start the run again",
        )
    return metrics.to_dict("records")


def _check_logged_config(path: Path, logged: Any, config: dict) -> None:
    """BadInput when the config to resume with differs from the one run.mcap recorded in any key but
    train.iterations: a hand-edited .hydra/config.yaml (another seed, another beta) would otherwise go on training
    the run under another config, a result of neither."""
    if not isinstance(logged, dict):
        return
    changed = [key for key in differing(logged, config) if key != "train.iterations"]
    if changed:
        more = f" and {len(changed) - 1} more" if len(changed) > 1 else ""
        raise BadInput(
            str(path.parent / CONFIG),
            f"differs from the config {path.name} recorded for this run in {changed[0]}{more}; restore it: a resumed "
            f"run goes on with its own config (only train.iterations=N may be given), or train a new run",
        )


def differing(logged: Any, config: Any, key: str = "") -> list[str]:
    """The dotted keys of the logged config whose values `config` does not share. A key the log lacks is one a
    later riskplan added, with the default the run had in effect: it is no difference."""
    if isinstance(logged, dict) and isinstance(config, dict):
        return [
            k
            for name in sorted(logged, key=str)
            for k in differing(logged[name], config.get(name), f"{key}.{name}".lstrip("."))
        ]
    return [] if logged == config else [key or "(the whole config)"]


def write_finished(
    out: Path,
    setup: RunSetup,
    metrics: Columns,
    evaluation: Columns,
    trajectories: Columns,
    summary: dict,
    durable: bool = True,
) -> None:
    """A finished run's files, each written atomically, summary.json last (it marks the run done). Each is synced
    to disk, unless `durable` is False: a batch syncs its file systems once for all its runs (run.batch)."""
    for name, table in zip(TABLES, (metrics, evaluation, trajectories), strict=True):
        with atomic_path(out / table_file(name), durable) as tmp:
            write_parquet(table, tmp)
    write_layout(out, setup.robots, (setup.world.width, setup.world.height), durable)
    write_atomic(out / SUMMARY, json.dumps(summary, indent=2, allow_nan=False), durable)


def _write_config(out: Path, config: dict, replace: bool = False) -> None:
    """.hydra/config.yaml for runs started from the Python API (Hydra writes it for the CLI), or `replace` it."""
    path = out / CONFIG
    if replace or not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(path, OmegaConf.to_yaml(OmegaConf.create(config)))


def _config_changed(out: Path, config: dict) -> bool:
    """Whether the run's .hydra/config.yaml differs from `config` (after `--resume ... train.iterations=N`).

    The file read as plain YAML first: equal to the config, it is this run's (what Hydra wrote for a sweep's job or
    `riskplan train`: no OmegaConf node to build, which costs a batch's every run a hundredth of a second). Anything
    else is read as OmegaConf reads it and typed, so a loader's difference only costs the quick answer."""
    text = (out / CONFIG).read_text()
    with contextlib.suppress(yaml.YAMLError):
        if yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)) == config:
            return False
    written = OmegaConf.create(text)
    if OmegaConf.to_container(written) == config:  # as typed already (Hydra wrote this run's own config)
        return False
    return as_dict(typed(written)) != config
