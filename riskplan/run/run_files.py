"""The files of a run directory, named in one place: the manifest `FILES`, one `RunFile` each.

Every part that writes, reads, checks or removes a run's files takes the names and the lists from here: the writer
(`run_directory`, `checkpoint`, `record`, `foxglove_layout`), the reader (`results.load_run`), the finish check
(`has_finished`: resume, and a sweep's skip of a finished job) and a sweep job's fresh start, which removes the
`STALE` files an older config left. A new per-run file is one `RunFile` here, and its writer. Hydra's own files
beside the config (.hydra/hydra.yaml and overrides.yaml, app.log under `riskplan train`) are Hydra's, not listed.

No pandas here: `riskplan train` checks its directory with these before it starts.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import yaml

from riskplan.util.lock import LOCK
from riskplan.util.paths import temp_name


@dataclass(frozen=True)
class RunFile:
    """One file of a run directory, as its path there, and what the run does with it."""

    name: str
    what: str
    output: bool = False  # the run leaves it in its directory (riskplan.train / train_summary)
    finished: bool = False  # a finished run has it: the finish check wants it
    ends: bool = False  # written as the run ends (summary.json last); a resume removes it until it ends again
    stale: bool = False  # a fresh start of a sweep job removes it: an older config's, never to be mixed with this one's
    table: bool = False  # one of the run's tables, <table>.parquet

    @property
    def stem(self) -> str:
        """A table's name: metrics for metrics.parquet."""
        return Path(self.name).stem


CONFIG = ".hydra/config.yaml"
RUN_LOG = "run.mcap"
RESUMING = ".resume-tmp"  # run.mcap cut back to a checkpoint is written beside it under this suffix, then renamed
CHECKPOINT = "checkpoint"
CHECKPOINT_TMP = f"{CHECKPOINT}.tmp"  # the next checkpoint until it is whole and renamed over the last one
SUMMARY = "summary.json"
LAYOUT = "foxglove_layout.json"
STATUS = "status.json"
JOB_LOG = "job.log"
# How riskplan report and landscape own their --out (riskplan.experiments.output_manifest): never in a run's folder,
# though a landscape's holds a .hydra/config.yaml
OUTPUT_MANIFEST = ".riskplan-manifest.json"

FILES = (  # a fresh start removes the checkpoint first: a job cut short there never resumes half a run
    RunFile(CONFIG, "the run's config (Hydra writes it for the CLI, the run for the Python API)", output=True),
    RunFile(LOCK, "the file one writer locks (riskplan.util.lock), left behind", output=True),
    RunFile(CHECKPOINT, "what resume needs: the next iteration, the thetas, the consensus", output=True, stale=True),
    RunFile(CHECKPOINT_TMP, "the next checkpoint, before it is whole", stale=True),
    RunFile(RUN_LOG, "the log of record: header, iterations, evaluation", output=True, finished=True, stale=True),
    RunFile(RUN_LOG + RESUMING, "run.mcap cut back to a checkpoint, before it replaces the log", stale=True),
    *(
        RunFile(f"{table}.parquet", what, output=True, finished=True, ends=True, stale=True, table=True)
        for table, what in (
            ("metrics", "one row per iteration and robot (and the team average)"),
            ("eval", "the final policies on fresh episodes"),
            ("trajectories", "sampled paths"),
        )
    ),
    RunFile(LAYOUT, "a Foxglove layout for run.mcap (older runs may lack it)", output=True, ends=True, stale=True),
    RunFile(
        SUMMARY,
        "the headline figures, written last: the run is done",
        output=True,
        finished=True,
        ends=True,
        stale=True,
    ),
    RunFile(STATUS, "a job's state (riskplan train, a sweep job): running, done, failed or interrupted"),
    RunFile(JOB_LOG, "everything a sweep job prints, every attempt's"),
)

TABLES = tuple(f.stem for f in FILES if f.table)  # <name>.parquet, in the order a run writes them
FINISHED = tuple(f.name for f in FILES if f.finished)  # what a finished run has
ENDS = tuple(f.name for f in FILES if f.ends)  # written as a run ends: removed when it resumes
OUTPUTS = tuple(f.name for f in FILES if f.output)  # what a run leaves in its directory
STALE = tuple(f.name for f in FILES if f.stale)  # what a fresh start removes (all of a run's own, and no more)
RECORDS = tuple(f.name for f in FILES if f.output and f.stale)  # a run's own: a fresh run never writes over them


def table_file(name: str) -> str:
    """A table's file: metrics.parquet for metrics."""
    return f"{name}.parquet"


def is_run_dir(path: Path) -> bool:
    """A run directory holds a run.mcap or a .hydra/config.yaml, and is not another command's output."""
    return ((path / RUN_LOG).is_file() or (path / CONFIG).is_file()) and other_output(path) is None


def output_manifest(path: Path) -> dict | None:
    """The manifest riskplan report and landscape write into their output, as read: None where there is none, {}
    where it cannot be read as a JSON object (damaged: still another command's output)."""
    file = Path(path) / OUTPUT_MANIFEST
    if not file.exists() and not file.is_symlink():
        return None
    try:
        data = json.loads(file.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def other_output(path: Path) -> str | None:
    """What `path` holds instead of a run, as a message says it ('the output of riskplan landscape'), or None."""
    manifest = output_manifest(path)
    if manifest is None:
        return None
    kind = manifest.get("kind")
    if isinstance(kind, str) and kind.isidentifier():
        return f"the output of riskplan {kind}"
    return f"the output of another riskplan command ({OUTPUT_MANIFEST})"


def remove_temps(out: Path) -> None:
    """Remove what a killed atomic write of a run's own files left (.eval.parquet.<pid>.tmp), as a fresh start or a
    resume does: the caller holds the directory's lock, so no writer is using them."""
    for name in STALE:
        for left in out.glob(temp_name(name, "*")):
            left.unlink(missing_ok=True)


def has_finished(out: Path) -> bool:
    """Whether the run's log, final tables and summary are all there."""
    return all((out / name).is_file() for name in FINISHED)


def hydra_intact(out: Path) -> bool:
    """Whether a sweep job's .hydra/ files read as Hydra writes them: its config and overrides a YAML mapping and
    list, hydra.yaml not empty. They are renamed into place unsynced, so a power cut can leave one empty or cut
    short where the run's own files (synced) are whole: the sweep then writes them again, not counting the job
    finished until it has (with libyaml, 0.7 ms a job). A verdict is kept while the files stay as they were (their
    inode, size and time): a sweep's plan, its jobs and its summary each ask, so a re-run of 10,000 finished jobs
    parsed them three times."""
    folder = out / CONFIG.split("/")[0]
    files = (out / CONFIG, folder / "overrides.yaml", folder / "hydra.yaml")
    try:
        stats = tuple((s.st_ino, s.st_size, s.st_mtime_ns) for s in (path.stat() for path in files))
    except OSError:
        return False
    known = _intact.get(str(out))
    if known is not None and known[0] == stats:
        return known[1]
    verdict = stats[2][1] > 0 and _read_intact(*files[:2])
    _intact[str(out)] = (stats, verdict)
    return verdict


_intact: dict[str, tuple[tuple, bool]] = {}  # hydra_intact's verdicts, with the files' stats they were given for


def _read_intact(config_file: Path, overrides_file: Path) -> bool:
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        config = yaml.load(config_file.read_bytes(), Loader=loader)
        overrides = yaml.load(overrides_file.read_bytes(), Loader=loader)
    except (OSError, yaml.YAMLError):
        return False
    return isinstance(config, dict) and bool(config) and isinstance(overrides, list)


def remove_stale(out: Path) -> None:
    """Remove every file of a run from `out`, and what a killed atomic write of one left, so that a fresh start
    mixes nothing of an older config's (the config, the lock, status.json and job.log stay: they are the job's, and
    rewritten or appended to)."""
    for name in STALE:
        (out / name).unlink(missing_ok=True)
    remove_temps(out)
