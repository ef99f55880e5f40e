"""One job of a sweep, as it runs inside a launcher's worker (joblib, submitit, ray).

Kept apart from `riskplan.sweep` (the command side) so that workers import only what a job needs.

A job's `status.json` says where it stands: "running" while it trains, then "done" or "failed" (with the error
and the traceback). It also holds `config_sha`, a fingerprint of the job's resolved config: a re-run of the
sweep recognises a finished job by that fingerprint and its output files, never by its job number, and skips it.
A job that was killed while "running" resumes from its checkpoint when its config is unchanged.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import socket
import sys
import time
import traceback
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

STATUS = "status.json"
JOB_LOG = "job.log"  # everything the job prints (Python and native), one file per job folder
THREADS_ENV = "RISKPLAN_JOB_THREADS"  # numba threads per job, set by `riskplan sweep` for parallel local jobs
OUTPUTS = ("summary.json", "metrics.parquet", "eval.parquet", "trajectories.parquet", "run.mcap")
STALE = ("checkpoint", "checkpoint.tmp", "run.mcap", "run.mcap.resume", "summary.json", "metrics.parquet",
         "eval.parquet", "trajectories.parquet")


def config_sha(cfg: DictConfig | dict) -> str:
    """Fingerprint of a job's resolved config (without the hydra node): what makes two jobs the same job."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    cfg = {k: v for k, v in cfg.items() if k != "hydra"}
    text = json.dumps(cfg, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def read_status(out: Path) -> dict | None:
    """The job's status.json, or None when missing or unreadable."""
    try:
        return json.loads((Path(out) / STATUS).read_text())
    except (OSError, ValueError):
        return None


def is_finished(out: Path, sha: str, status: dict | None = None) -> bool:
    """Whether the job in `out` finished with this config and still has its outputs."""
    status = read_status(out) if status is None else status
    return (status is not None and status.get("status") == "done" and status.get("config_sha") == sha
            and all((Path(out) / name).is_file() for name in OUTPUTS))


def write_status(out: Path, record: dict) -> None:
    """Write status.json atomically, so a reader never sees half a file."""
    tmp = Path(out) / f".{STATUS}.{os.getpid()}.tmp"
    tmp.write_text(json.dumps(record, indent=2, allow_nan=True, default=str))
    os.replace(tmp, Path(out) / STATUS)


def sweep_job(cfg: DictConfig, out: Path) -> float | None:
    """Run one sweep job in `out`: skip it if finished, resume it if killed, else train from scratch."""
    out = Path(out)
    sha = config_sha(cfg)
    prior = read_status(out)
    if is_finished(out, sha, prior):
        return prior.get("cvar")
    threads = job_threads()
    if threads:
        import numba

        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    resume = (prior is not None and prior.get("status") == "running" and prior.get("config_sha") == sha
              and (out / "checkpoint").is_file())
    if not resume:
        for name in STALE:
            (out / name).unlink(missing_ok=True)
    started = time.time()
    base = {"config_sha": sha, "started": started, "host": socket.gethostname(), "pid": os.getpid()}
    write_status(out, {"status": "running", "error": None, **base})
    with job_output(out / JOB_LOG):
        print(f"=== riskplan sweep job {'resumed' if resume else 'started'} at {time.ctime(started)} "
              f"on {base['host']} (pid {base['pid']})", flush=True)
        record = _train(cfg, out, resume)
        print(f"=== {record['status']}" + (f": {record['error']}" if record["error"] else ""), flush=True)
    finished = time.time()
    write_status(out, {**record, **base, "finished": finished, "seconds": finished - started, "resumed": resume})
    return record.get("cvar")


def job_threads() -> int | None:
    """numba threads for this job: RISKPLAN_JOB_THREADS if set, else no more than the cores this process may run
    on (a SLURM allocation) nor OMP_NUM_THREADS (which joblib's workers and Ray's tasks get); results do not
    depend on it."""
    explicit = os.environ.get(THREADS_ENV, "")
    if explicit.isdigit():
        return int(explicit)
    limits = []
    if hasattr(os, "sched_getaffinity"):
        limits.append(len(os.sched_getaffinity(0)))
    omp = os.environ.get("OMP_NUM_THREADS", "")
    if omp.isdigit() and int(omp) > 0:
        limits.append(int(omp))
    return min(limits) if limits else None


def _train(cfg: DictConfig, out: Path, resume: bool) -> dict:
    """Train (or resume); any error fails this job alone and is returned in its record."""
    from riskplan.errors import BadInput
    from riskplan.training import NumericalTrouble, train

    try:
        if resume:
            try:
                run = train(cfg, out, resume=True)
            except (BadInput, NumericalTrouble):
                raise
            except Exception:  # an unreadable checkpoint or log: start this job again from scratch
                traceback.print_exc()
                print("=== resume failed; training from scratch", flush=True)
                for name in STALE:
                    (out / name).unlink(missing_ok=True)
                run = train(cfg, out)
        else:
            run = train(cfg, out)
    except (BadInput, NumericalTrouble) as err:
        return {"status": "failed", "error": str(err)}
    except Exception as err:  # a job that raises fails alone; the sweep goes on
        trace = traceback.format_exc()
        print(trace, file=sys.stderr, flush=True)
        return {"status": "failed", "error": f"{type(err).__name__}: {err}", "traceback": trace}
    return {"status": "done", "error": None, "cvar": run.summary["cvar"]["value"]}


@contextlib.contextmanager
def job_output(path: Path):
    """Send this process's stdout and stderr (file descriptors 1 and 2, so native output too) to `path`."""
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    try:
        saved = os.dup(1), os.dup(2)
    except OSError:  # no usable descriptors (an unusual worker): leave output where it goes
        yield
        return
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    log = open(path, "a", buffering=1)  # Python-level writes too, whatever sys.stdout was replaced by
    try:
        with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
            yield
    finally:
        log.close()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
