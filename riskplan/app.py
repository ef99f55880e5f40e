"""The Hydra application: one task function serves `riskplan train` (a run) and `riskplan sweep` (a multirun).

Going through Hydra's own main gives users what they expect of a Hydra app: `.hydra/` in every run directory,
`--cfg job`, `hydra.run.dir`, sweepers and launchers (joblib, submitit, ray).
"""

from __future__ import annotations

import json
import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from riskplan import schema
from riskplan.errors import BadInput

CONF_DIR = str(Path(__file__).resolve().parent / "conf")  # absolute: conf/ is a symlinked data dir, not a package
STATUS = "status.json"  # written in every job directory: {"status": "done" | "failed", "error": ...}


@hydra.main(config_path=CONF_DIR, config_name="config", version_base="1.3")
def task(cfg: DictConfig) -> float | None:
    """Train one job in Hydra's output directory; record success or failure in status.json."""
    from riskplan.training import NumericalTrouble, train

    out = Path(HydraConfig.get().runtime.output_dir)
    single = HydraConfig.get().mode == RunMode.RUN
    if not single:  # a sweep job: skips itself when finished, resumes when killed, logs to its own folder
        from riskplan.sweepjob import sweep_job

        return sweep_job(cfg, out)
    (out / STATUS).unlink(missing_ok=True)
    try:
        with _progress(single) as progress:
            run = train(cfg, out, progress=progress)
    except (BadInput, NumericalTrouble) as err:
        _status(out, "failed", str(err))
        return None
    except Exception as err:  # a job that raises fails alone; its status records why, the others go on
        _status(out, "failed", f"{type(err).__name__}: {err}", traceback.format_exc())
        return None
    _status(out, "done", None)
    return run.summary["cvar"]["value"]


def run_hydra(args: list[str]) -> None:
    """Call the Hydra app as if `riskplan <args>` were its command line."""
    schema.register()
    GlobalHydra.instance().clear()
    argv = sys.argv
    sys.argv = ["riskplan", *args]
    try:
        task()
    finally:
        sys.argv = argv
        GlobalHydra.instance().clear()


def _status(out: Path, status: str, error: str | None, trace: str | None = None) -> None:
    """Write the job's status file."""
    record = {"status": status, "error": error}
    if trace:
        record["traceback"] = trace
    (out / STATUS).write_text(json.dumps(record, indent=2))


def _progress(enabled: bool):
    """A rich progress bar for a single run; silent inside sweeps (the sweep shows its own view)."""
    from riskplan.progress import TrainingBar, silent

    return TrainingBar() if enabled else silent()
