"""One job of a sweep, as it runs inside a launcher's worker (joblib, submitit, ray).

Kept apart from `riskplan.experiments.sweeping` (the command side) so that workers import only what a job needs.

A job's `status.json` says where it stands: "running" while it trains, then "done" or "failed" (with the error
and the traceback). It also holds `config_sha`, a fingerprint of the job's resolved config and its map's files: a
re-run of the sweep recognises a finished job by that fingerprint and its output files, never by its job number,
and skips it. Its config part is `run_identity`, riskplan's one rule for when two runs are the same sample (the same
config and seed, wherever they were written): the report, the export and the sweep summary count each once.
A job that was killed while "running" resumes from its checkpoint when its config is unchanged.

One writer per job folder: a job holds the folder's lock (`riskplan.util.lock`) before it reads, deletes or writes
anything there; a job whose folder is held by another process fails alone and leaves the folder as it was. Under the
lock it checks the folder by the rule the sweep's plan applies (`foreign_run`): one that holds a run of another config
that did not fail (another launch's, in use when this one was planned) fails the job alone, every file left as it is.
Job by job, Hydra writes no `.hydra/` before the job runs (OWN_FILES): the job writes it then, under the lock, once the
folder is its own.

A local worker (joblib's, submitit_local's, a local Ray instance's) ends with the `riskplan sweep` driver, however
it died, and writes nothing after it (`riskplan.experiments.driver_watch`), so a killed sweep leaves no training
behind; the checkpoints make the next run of the sweep resume those jobs. SLURM jobs and jobs on a Ray cluster
started apart from the driver outlive it, as they should.

Job folders are named by `folder_name` (registered as the OmegaConf resolver `riskplan.folder`, which
`riskplan sweep` puts in `hydra.sweep.subdir`): Hydra's `override_dirname` with every character outside
[A-Za-z0-9._=,+-] percent-encoded, so a swept value never nests or escapes the sweep directory. Under an
optimising sweeper (optuna) `riskplan.trial` names them `trial_007,<override_dirname>` the same way.

A job returns its CVaR to the sweeper, or None when it failed or another process holds its folder: the optuna
sweeper records a None as a failed trial and goes on (a number such as -inf would be taken as measured).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import json
import math
import os
import socket
import string
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numba
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, read_write

from riskplan.config.hydra_safety import OUTPUT_SUBDIR
from riskplan.config.typed import typed
from riskplan.engine.step import NumericalTrouble
from riskplan.experiments.driver_watch import arrive, exit_if_orphaned, take_interrupts, working
from riskplan.run.build import build_planned
from riskplan.run.compose import compose
from riskplan.run.maps import map_record
from riskplan.run.run_files import CHECKPOINT, JOB_LOG, STATUS, has_finished, hydra_intact, remove_stale
from riskplan.run.training import prepare_resume, train_summary
from riskplan.util import lock
from riskplan.util.errors import BadInput, one_line
from riskplan.util.interrupt import Interrupted
from riskplan.util.paths import write_atomic

T = TypeVar("T")
THREADS_ENV = "RISKPLAN_JOB_THREADS"  # numba threads per job, set by `riskplan sweep` for parallel local jobs
RESOLVER = "riskplan.folder"  # ${riskplan.folder:${hydra.job.override_dirname}}: a safe job folder name
SUBDIR = "${" + RESOLVER + ":${hydra.job.override_dirname}}"
TRIAL_RESOLVER = "riskplan.trial"  # the same for the trials of an optimising sweeper, numbered
TRIAL_SUBDIR = "${" + TRIAL_RESOLVER + ":${hydra.job.num},${hydra.job.override_dirname}}"
SAFE = frozenset(string.ascii_letters + string.digits + "._=,+-")  # kept as they are in folder names
NAME_MAX = 255  # bytes in a file name (ext4, xfs, NFS)
JOB_OWN = (lock.LOCK, JOB_LOG, OUTPUT_SUBDIR)  # a job's folder before its status.json (a launch killed early)
# Each job's key in a job-by-job launch: Hydra's run_job writes no .hydra/, which would go over the files of another
# config's run before the job could refuse its folder; the job writes them once the folder is its own (hydra_files).
OWN_FILES = "hydra.output_subdir=null"
SAME_CONFIGS = "a sweep goes on in its directory only with the same configs"


OUTPUT_KEYS = ("hydra",)  # where a run was written (hydra.run.dir, hydra.sweep.dir and subdir, ...), never what ran
HOW_KEYS = ("engine",)  # how a run computed (engine.device), never what: the same numbers on every device


def run_identity(config: DictConfig | dict) -> str:
    """What makes two runs one sample: a fingerprint of the resolved config, its seed included and its output paths
    (the hydra node) and how it computed (the engine node: the device) left out. Two runs with the same identity draw
    the same numbers, wherever and on whatever device they ran.

    The one rule for it: a sweep job records it in status.json as `config_sha` (a re-run skips the finished job),
    and the report, the export and the sweep summary count each identity once (`distinct`)."""
    if isinstance(config, DictConfig):
        config = OmegaConf.to_container(config, resolve=True)
    config = {k: v for k, v in config.items() if k not in OUTPUT_KEYS and k not in HOW_KEYS}
    text = json.dumps(config, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def config_sha(config: DictConfig | dict, map_files: list[dict] | None = None) -> str:
    """A sweep job's fingerprint, status.json's `config_sha`: its run_identity and, when world.map names a map, the
    contents of the map's files (`map_files`: riskplan.run.maps.map_record's records; read now when not given). A
    map edited in place leaves the config as it was, so without them a re-run of the sweep would take the jobs
    trained in the old world as finished and train the rest in the new one. A map that cannot be read leaves the
    config's part alone: the job fails in its training, naming world.map, and a failed job is never matched."""
    identity = run_identity(config)
    if (config.get("world") or {}).get("map") is None:
        return identity
    if map_files is None:
        try:
            map_files = map_record(typed(config).world) or []
        except BadInput:
            return identity
    digests = [str(record.get("sha256")) for record in map_files]
    return hashlib.sha256(json.dumps([identity, digests]).encode()).hexdigest()[:16]


def distinct(items: Iterable[T], config_of: Callable[[T], DictConfig | dict]) -> tuple[list[T], list[tuple[T, T]]]:
    """Items (runs) in the order given, each identity once: the first item of each identity, and each later one
    as (the repeat, the item it repeats)."""
    first: dict[str, T] = {}
    kept: list[T] = []
    repeats: list[tuple[T, T]] = []
    for item in items:
        identity = run_identity(config_of(item))
        if identity in first:
            repeats.append((item, first[identity]))
        else:
            first[identity] = item
            kept.append(item)
    return kept, repeats


def repeats_line(count: int, where: str, what: str = "run") -> str:
    """The one warning line for `count` repeats: '2 runs repeat another run's config and seed (the same sample);
    each is counted once (<where>)'."""
    plural = count != 1
    return (
        f"{count} {what}{'s' if plural else ''} repeat{'' if plural else 's'} another {what}'s config and seed "
        f"(the same sample); each is counted once ({where})"
    )


def folder_name(dirname: str) -> str:
    """A job folder name from Hydra's override_dirname: a single path component, injective, at most 255 bytes.

    Every character outside [A-Za-z0-9._=,+-] (so '/', '%', NUL, spaces, quotes, brackets, non-ASCII) becomes
    %XX of its UTF-8 bytes; a leading '.' becomes %2E (no hidden folders, never '.' or '..'). A name longer than
    255 bytes keeps its first part and ends with %h and a hash of the whole name ('%h' is never produced by the
    encoding, so a shortened name never equals another name).
    """
    dirname = str(dirname)
    data = dirname.encode("utf-8", "surrogatepass")
    encoded = "".join(
        c if c in SAFE else "".join(f"%{b:02X}" for b in c.encode("utf-8", "surrogatepass")) for c in dirname
    )
    if encoded.startswith("."):
        encoded = "%2E" + encoded[1:]
    if not encoded:
        return "%empty"
    if len(encoded) > NAME_MAX:
        digest = hashlib.sha256(data).hexdigest()[:16]
        head = encoded[: NAME_MAX - 2 - len(digest)]
        cut = head.find("%", len(head) - 2)  # do not cut an escape in half
        encoded = f"{head[:cut] if cut >= 0 else head}%h{digest}"
    return encoded


def trial_folder(num, dirname) -> str:
    """A trial's folder under an optimising sweeper (optuna): its number first, so two trials that drew the same
    values get folders of their own, then what it drew (`trial_007,risk.beta=0.31`)."""
    return folder_name(f"trial_{int(num):03d},{dirname}" if str(dirname) else f"trial_{int(num):03d}")


OmegaConf.register_new_resolver(RESOLVER, folder_name, replace=True)
OmegaConf.register_new_resolver(TRIAL_RESOLVER, trial_folder, replace=True)


class FolderNames(Callback):
    """A Hydra callback that does nothing but travel: the launcher pickles it with every job, so unpickling it
    imports this module in the job's process (joblib, submitit, ray) and registers the `riskplan.folder` resolver
    before Hydra resolves hydra.sweep.subdir there; and, before Hydra writes the job's folder, it makes a local
    worker end with its driver (`driver_watch.arrive`)."""

    def __reduce__(self):
        return _arrived, ()


def _arrived() -> FolderNames:
    """A FolderNames unpickled in a job's process: the job has arrived."""
    arrive()
    return FolderNames()


def read_status(out: Path) -> dict | None:
    """The job's status.json, or None when missing or unreadable."""
    try:
        return json.loads((Path(out) / STATUS).read_text())
    except (OSError, ValueError):
        return None


def recorded_sha(out: Path, config: dict) -> str:
    """A run's fingerprint as it was trained: a sweep job's from its status.json (it covers the map's files as they
    were then); a run trained alone has none, and its config's identity stands for it."""
    recorded = (read_status(out) or {}).get("config_sha")
    return recorded if isinstance(recorded, str) else run_identity(config)


def is_finished(out: Path, sha: str, status: dict | None = None) -> bool:
    """Whether the job in `out` finished with this config and still has its outputs and readable .hydra/ files."""
    status = read_status(out) if status is None else status
    return (
        status is not None
        and status.get("status") == "done"
        and status.get("config_sha") == sha
        and has_finished(Path(out))
        and hydra_intact(Path(out))
    )


def foreign_run(out: Path, sha: str, status: dict | None) -> str | None:
    """What makes the job folder `out` not the job's (of config `sha`) to write over, as the sweep's line says it
    ('holds a done run of another config'): a run of another config that did not fail (its status.json names
    another config_sha, or none: a run of riskplan train), or files of no job's beside a missing status.json. None:
    the folder is new, its own job's, or a failed run's, which the job replaces. `status`: its status.json, read.

    The one rule of the plan's check (sweeping.jobs.check_job_folders) and of a job's start under its folder's lock
    (`begin_job`): a folder another process held when the sweep was planned, or a task of an earlier launch that
    starts after a later one, meets it there."""
    if status is None:
        if Path(out).is_dir() and any(entry.name not in JOB_OWN for entry in Path(out).iterdir()):
            return "holds files that are not a sweep job's"
        return None
    if status.get("config_sha") == sha or status.get("status") == "failed":
        return None
    state = status.get("status")
    if not (isinstance(state, str) and state.isidentifier()):
        return "holds a run of another config"
    return f"holds {'an' if state[0] in 'aeiouAEIOU' else 'a'} {state} run of another config"


def holds_another_run(out: Path, config: DictConfig | dict) -> bool:
    """Whether the job folder `out` holds a run of another config that did not fail (foreign_run), for the job of
    `config`: a folder in use when the sweep was planned, whose files the job's set-up must leave as they are. The
    config's fingerprint is taken only where a status.json may name another."""
    if not Path(out).is_dir():
        return False
    status = read_status(out)
    differs = status is not None and status.get("status") != "failed"
    return foreign_run(out, config_sha(config) if differs else "", status) is not None


def hydra_files(cfg: DictConfig) -> dict[str, str]:
    """The .hydra/ files of a job that Hydra set up with OWN_FILES, byte for byte as its run_job writes them (the
    job's config, Hydra's node, the job's overrides), with the output_subdir the user meant (riskplan takes no other
    than OUTPUT_SUBDIR) and without OWN_FILES among Hydra's overrides; none for any other job (Hydra wrote them)."""
    if not HydraConfig.initialized() or OWN_FILES not in HydraConfig.get().overrides.hydra:
        return {}
    node = copy.deepcopy(HydraConfig.instance().cfg)  # {"hydra": ...}, as run_job saves it
    with read_write(node.hydra):  # set_config made it read-only
        node.hydra.output_subdir = OUTPUT_SUBDIR
        node.hydra.overrides.hydra.remove(OWN_FILES)  # once: hydra_safety refuses the user's
    return {  # in run_job's order
        f"{OUTPUT_SUBDIR}/config.yaml": OmegaConf.to_yaml(cfg),
        f"{OUTPUT_SUBDIR}/hydra.yaml": OmegaConf.to_yaml(node),
        f"{OUTPUT_SUBDIR}/overrides.yaml": OmegaConf.to_yaml(node.hydra.overrides.task),
    }


def write_files(out: Path, files: dict[str, str]) -> None:
    """A job's files (hydra_files), each whole or not at all; never from a worker whose sweep driver is gone. Not
    synced to disk: run_job does not sync them either, and a re-run writes them."""
    if files:
        exit_if_orphaned()
    for name, text in files.items():
        (out / name).parent.mkdir(exist_ok=True)
        write_atomic(out / name, text, durable=False)


def refusal(out: Path, problem: str) -> str:
    """A job's one line for a folder it leaves to another config's run (`problem`: foreign_run's)."""
    return (
        f"{out} {problem}; the job left it as it was: {SAME_CONFIGS}, so give a new hydra.sweep.dir "
        f"(or remove that folder and run the sweep again)"
    )


def _finite(value):
    """The record with every non-finite float as None (status.json is strict JSON: no NaN, no Infinity)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if value is None or isinstance(value, (str, int, bool)):
        return value
    try:  # numpy scalars and the like
        return _finite(value.item())
    except (AttributeError, ValueError, TypeError):
        return str(value)


def write_status(out: Path, record: dict) -> None:
    """Write status.json atomically (a reader never sees half a file, a full disk leaves no temp file); never from a
    worker whose sweep driver is gone. A job's start is not synced to disk: a power cut that loses it leaves the job
    to run again, as it would anyway; its end is."""
    exit_if_orphaned()
    text = json.dumps(_finite(record), indent=2, allow_nan=False)
    write_atomic(Path(out) / STATUS, text, durable=record.get("status") != "running")


def sweep_job(cfg: DictConfig, out: Path) -> float | None:
    """Run one sweep job in `out`: skip it if finished, resume it if killed, else train from scratch.

    The whole job holds the folder's lock; when another process holds it, the job returns None at once and
    touches nothing in the folder (the sweep's summary reports it as running in that process). So does a job whose
    folder holds a run of another config that did not fail, its line on stderr (`begin_job`).
    """
    out = Path(out)
    watched = arrive()
    with working(), contextlib.ExitStack() as stack:
        if not _lock_folder(stack, out):
            return None
        try:
            take_interrupts()  # a Ctrl-C from this worker's start on stops this job's set-up
            return _locked_job(cfg, out, watched)
        except KeyboardInterrupt:  # Ctrl-C in the job's set-up, before its training's own handler took over
            _mark_interrupted(out)
            raise


def _mark_interrupted(out: Path) -> None:
    """status.json says interrupted, not running, for a job this process began and a signal stopped."""
    status = read_status(out)
    if status is not None and status.get("status") == "running" and status.get("pid") == os.getpid():
        write_status(out, {**status, "status": "interrupted", "error": "interrupted by SIGINT before its training"})


def _lock_folder(stack: contextlib.ExitStack, out: Path) -> bool:
    """Take the job folder's lock into `stack`; False when another process holds it."""
    try:
        stack.enter_context(lock.hold_lock(out, "sweep job folder"))
    except BadInput:
        return False
    return True


@dataclass
class JobStart:
    """A sweep job in its locked folder: finished already (with its CVaR), or about to train, fresh or resuming
    its checkpoint; `base` is what its status.json records from the start."""

    out: Path
    finished: bool = False
    value: float | None = None
    resume: bool = False
    base: dict = field(default_factory=dict)
    unusable: str | None = None  # why its checkpoint could not be resumed, when it starts again instead
    refused: str | None = None  # the job's one line when its folder holds another config's run: it does not run

    @property
    def opening(self) -> str:
        """job.log's first line for this start."""
        b = self.base
        how = "resumed" if self.resume else f"started again ({self.unusable})" if self.unusable else "started"
        return (
            f"=== riskplan sweep job {how} at {time.ctime(b['started'])} "
            f"on {b['host']} ({b['threads']} numba threads, pid {b['pid']}"
        )


def begin_job(cfg: DictConfig, out: Path, files: dict[str, str] | None = None) -> JobStart:
    """Where the job in `out` (whose lock the caller holds) stands: finished with this config, or a checkpoint to
    resume (it was killed, or stopped by a signal), or a fresh start with the stale files of a failed run of an
    older config removed; then status.json says running. A folder holding another config's run that did not fail
    (`foreign_run`) is refused: nothing written, the line in `refused`. `files` (hydra_files) are written once the
    folder is found to be the job's."""
    sha = config_sha(cfg)
    prior = read_status(out)
    problem = foreign_run(out, sha, prior)  # None for a run of this config, finished or not
    if problem is not None:  # checked again here: the plan's check skips a folder another process holds
        return JobStart(out, refused=refusal(out, problem))
    write_files(out, files or {})
    if is_finished(out, sha, prior):
        return JobStart(out, finished=True, value=prior.get("cvar"))
    resume = (
        prior is not None
        and prior.get("status") in ("running", "interrupted")  # killed, or stopped by a signal (preempted)
        and prior.get("config_sha") == sha
        and (out / CHECKPOINT).is_file()
    )
    unusable = _unusable_checkpoint(cfg, out) if resume else None
    if unusable is not None:  # a damaged checkpoint or log: the job trains again from scratch, to the same numbers
        resume = False
    if not resume:
        remove_stale(out)
    base = {
        "config_sha": sha,
        "started": time.time(),
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "threads": numba_threads(),
    }
    write_status(out, {"status": "running", "error": None, **base})
    return JobStart(out, resume=resume, base=base, unusable=unusable)


def _unusable_checkpoint(cfg: DictConfig, out: Path) -> str | None:
    """Why the job's checkpoint cannot be resumed (damaged, or not matching its log), or None. A run of riskplan
    train asks its user to start it again; a sweep job, whose folder is the sweep's, simply does."""
    try:
        prepare_resume(cfg, out)
    except (BadInput, OSError) as err:
        return f"its checkpoint could not be resumed: {one_line(str(err))}"
    return None


def say_refused(start: JobStart) -> None:
    """A refused job's line, on this process's stderr (the launcher's log of the job): its folder's job.log is the
    other run's, never written."""
    print(f"error: {start.refused}", file=sys.stderr, flush=True)


def end_job(start: JobStart, record: dict) -> float | None:
    """A trained (or failed) job's final status.json; its CVaR for the sweeper. `seconds` is the job's time since
    it began, or the record's own (a batched job's share of its batch: riskplan.experiments.sweeping.batched)."""
    finished = time.time()
    seconds = record.get("seconds", finished - start.base["started"])
    write_status(start.out, {**record, **start.base, "finished": finished, "seconds": seconds, "resumed": start.resume})
    return record.get("cvar")


def interrupt_job(start: JobStart, stop: Interrupted, error: str | None = None) -> None:
    """A job a signal stopped after its checkpoint (or before it trained: `error` says so): no result, so that a
    requeued or re-run job resumes it."""
    write_status(
        start.out, {"status": "interrupted", "error": error or str(stop), **start.base, "resumed": start.resume}
    )


def outcome(summary: dict) -> dict:
    """A finished job's status record."""
    return {"status": "done", "error": None, "cvar": summary["cvar"]["value"]}


def failure(err: BaseException) -> dict:
    """A failed job's status record: bad input and numerical trouble in one line, anything else with its trace."""
    if isinstance(err, (BadInput, NumericalTrouble)):
        return {"status": "failed", "error": str(err)}
    trace = "".join(traceback.format_exception(err))
    return {"status": "failed", "error": f"{type(err).__name__}: {err}", "traceback": trace}


def _locked_job(cfg: DictConfig, out: Path, watched: str | None = None) -> float | None:
    threads = job_threads()
    if threads:
        numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    start = begin_job(cfg, out, hydra_files(cfg))
    if start.refused is not None:
        say_refused(start)
        return None
    if start.finished:
        return start.value
    with job_output(out / JOB_LOG):
        print(
            start.opening + (f", ends with the sweep process {watched.split(':')[0]})" if watched else ")"),
            flush=True,
        )
        try:
            record = _train_job(cfg, out, start.resume)
        except Interrupted as stop:  # checkpointed: the job ends by the signal, leaving no result behind, so a
            # scheduler that requeues it (preemption, submitit's checkpoint) runs it again and it resumes
            print(f"=== {stop}", flush=True)
            interrupt_job(start, stop)
            stop.end()
        print(f"=== {record['status']}" + (f": {record['error']}" if record["error"] else ""), flush=True)
    return end_job(start, record)


WARM_UP = (["experiment=paper_single"],)  # loads the kernels every job runs (a team's own few load in its job)
WARM_UP_SIZE = [
    "train.iterations=2",
    "train.samples=11",
    "train.eval_episodes=8",
    "train.bootstrap=40",
    "train.paths=1",
]


def warm_up(scratch_dir: Path) -> tuple[int, float]:
    """Import what a job needs and load the compiled kernels from numba's cache, by training tiny runs in a folder
    of `scratch_dir` (the driver's, driver_watch.scratch: a worker killed mid-way leaves nothing behind):
    `riskplan reproduce` runs this on its sweep workers while it checks and plans, so that its first jobs start at
    once. Returns (this worker's pid, seconds taken)."""
    started = time.time()
    arrive()
    with working(), tempfile.TemporaryDirectory(prefix="warm-up-", dir=scratch_dir) as scratch:
        take_interrupts()
        for number, experiment in enumerate(WARM_UP):
            train_summary(compose([*experiment, *WARM_UP_SIZE]), Path(scratch) / str(number), progress=False)
    return os.getpid(), time.time() - started


def numba_threads() -> int:
    """The threads numba runs this job's kernels with (recorded in status.json and job.log)."""
    return int(numba.get_num_threads())


GRANTED = ("SLURM_CPUS_PER_TASK", "OMP_NUM_THREADS")  # CPUs a scheduler granted this job, where it says


def job_threads() -> int | None:
    """numba threads for this job: RISKPLAN_JOB_THREADS if set, else no more than the cores this process may run
    on (CPU binding), nor the CPUs SLURM granted (SLURM_CPUS_PER_TASK: a cluster that does not bind jobs to their
    CPUs would otherwise run every job on every core of the node), nor OMP_NUM_THREADS (which joblib's workers and
    Ray's tasks get); results do not depend on it."""
    explicit = os.environ.get(THREADS_ENV, "")
    if explicit.isascii() and explicit.isdigit() and int(explicit) > 0:  # '²' is a digit int() refuses
        return int(explicit)
    limits = []
    if hasattr(os, "sched_getaffinity"):
        limits.append(len(os.sched_getaffinity(0)))
    for name in GRANTED:
        value = os.environ.get(name, "")
        if value.isascii() and value.isdigit() and int(value) > 0:
            limits.append(int(value))
    return min(limits) if limits else None


def _train_job(cfg: DictConfig, out: Path, resume: bool) -> dict:
    """Train (or resume) the job; any error fails this job alone and is returned in its record."""
    try:
        setup = build_planned(cfg)
        if resume:
            try:
                summary = train_summary(setup, out, resume=True)
            except (BadInput, NumericalTrouble):
                raise
            except Exception:  # an unreadable checkpoint or log: start this job again from scratch
                traceback.print_exc()
                print("=== resume failed; training from scratch", flush=True)
                remove_stale(out)
                summary = train_summary(setup, out)
        else:
            summary = train_summary(setup, out)
    except Exception as err:  # a job that raises fails alone; the sweep goes on
        record = failure(err)
        if "traceback" in record:
            print(record["traceback"], file=sys.stderr, flush=True)
        return record
    return outcome(summary)


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
