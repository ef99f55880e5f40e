"""Find the runs under some directories, load them, skip the broken ones, and group them by what differs.

A *group* is a set of runs whose configs agree on every key but `seed`: the seeds of one experimental condition.
Groups are labelled by the fewest differing keys that tell them apart (risk measure, beta, team size, graph, ...).

A *study* is one of the questions `riskplan reproduce` asks beyond the paper (risk measures, richer policies, a
heterogeneous team, faults). Its runs live in the reproduction's study folders (STUDIES); when an input directory
holds such a folder, its runs are collected apart, as a Collection of their own (`Collection.studies`), so that
they neither join nor relabel the groups of the paper's figures.

A run whose config and seed repeat another's (`riskplan.experiments.sweep_worker.run_identity`: the same config,
wherever it was written) is the same sample: the first by path is used, the others are `Collection.duplicates`,
so that no seed is counted twice. The paper's runs and each study's are pooled apart, so a study's run that repeats
one of the paper's (the measures study's CVaR and risk-neutral runs) is used by both.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from riskplan.config.keys import KEYS
from riskplan.config.schema import ScheduleConf
from riskplan.config.typed import check_schema
from riskplan.engine.measures.registry import MEASURES
from riskplan.experiments.landscape import is_landscape_dir, load_landscape
from riskplan.experiments.reporting.labels import MISSING, hashable, label_groups
from riskplan.experiments.reporting.parallel import Progress, shared_map
from riskplan.experiments.study_registry import STUDIES
from riskplan.experiments.sweep_worker import HOW_KEYS, distinct, read_status
from riskplan.run.metrics_rows import AVERAGE
from riskplan.run.results import Run, find_runs, load_run, log_cut_short, logged_config
from riskplan.run.run_directory import differing
from riskplan.run.run_files import CONFIG, RUN_LOG, STATUS, TABLES, table_file
from riskplan.util import lock
from riskplan.util.errors import BadInput

# Keys that never define a condition: the seeds of one condition are pooled.
IGNORED_KEYS = ("seed",)
# The measures' order in the studies' tables: the built-in ones (riskplan.engine.measures), then any other by name
MEASURE_ORDER = MEASURES
# Okabe-Ito palette (colour-blind safe); the paper's pair is blue (risk-neutral) and black (risk-averse).
PALETTE = ("#0072B2", "#000000", "#009E73", "#D55E00", "#CC79A7", "#56B4E9", "#E69F00", "#999999")
SCHEDULE_DEFAULTS = {f"risk.schedule.{k}": v for k, v in dataclasses.asdict(ScheduleConf()).items()}
RESUME = "resume it (riskplan train --resume DIR) or let it finish"  # what makes a run cut short reportable


@dataclass
class RunInfo:
    """A usable (complete) training run."""

    run: Run
    flat: dict[str, Any]
    rebuilt: bool  # tables were rebuilt from run.mcap
    group: Group | None = None
    log_cut: bool = False  # a finished run's run.mcap was cut short since: its tables are what is reported

    @property
    def path(self) -> Path:
        return self.run.path

    @property
    def config(self) -> dict:
        return self.run.config

    @property
    def seed(self) -> int:
        return int(self.config.get("seed", 0))

    @property
    def robots(self) -> int:
        return int(self.config.get("team", {}).get("robots", 1))

    @property
    def headline(self) -> int:
        """The robot id whose figures stand for the run: 0 (centralized) or the network average -1 (team)."""
        if self.run.summary and "headline_robot" in self.run.summary:
            return int(self.run.summary["headline_robot"])
        return AVERAGE if self.robots > 1 else 0

    def metrics_of(self, robot: int | None = None) -> pd.DataFrame:
        """Metrics rows of one robot (default: the headline), sorted by iteration."""
        robot = self.headline if robot is None else robot
        m = self.run.metrics
        return m.loc[m.robot == robot].sort_values("iteration")

    def eval_of(self, robot: int | None = None) -> pd.DataFrame:
        """Evaluation episodes of one robot (default: the headline)."""
        robot = self.headline if robot is None else robot
        e = self.run.eval
        return e.loc[e.robot == robot]

    def final_theta(self) -> list[float]:
        """The headline policy's final theta (after the last update)."""
        if self.run.summary and isinstance(self.run.summary.get("theta_final"), list):
            try:
                return [math.nan if t is None else float(t) for t in self.run.summary["theta_final"]]
            except (TypeError, ValueError):
                pass  # a summary.json not written by riskplan: the metrics table has the same theta
        last = self.metrics_of().iloc[-1]
        return [float(last[c]) for c in theta_columns(self.run.metrics)]


@dataclass
class Broken:
    """A run directory that could not be used, why, and what would make it usable ('' where the reason says)."""

    path: Path
    reason: str
    remedy: str = ""


@dataclass
class Duplicate:
    """A run whose config and seed repeat another's: the same sample, so only that other run is used."""

    path: Path
    of: RunInfo  # the run it repeats (the first of them by path), the one the report counts
    seed: int


@dataclass
class Group:
    """The runs (seeds) of one condition."""

    key: tuple
    runs: list[RunInfo]
    label: str = ""
    color: str = PALETTE[0]
    settings: dict[str, Any] = field(default_factory=dict)  # differing keys -> value

    @property
    def first(self) -> RunInfo:
        return self.runs[0]

    @property
    def config(self) -> dict:
        return self.first.config

    @property
    def measure(self) -> str:
        return str(self.config.get("risk", {}).get("measure", "cvar"))

    @property
    def beta(self) -> float:
        return float(self.config.get("risk", {}).get("beta", 0.1))

    @property
    def eta(self) -> float:
        return float(self.config.get("risk", {}).get("eta", 0.5))

    @property
    def weight(self) -> float:
        return float(self.config.get("risk", {}).get("weight", 0.5))

    @property
    def schedule(self) -> str:
        """risk.schedule.kind: none (the paper), linear or exponential."""
        return str(self.first.flat.get(KEYS.risk.schedule.kind, "none"))

    @property
    def policy_kind(self) -> str:
        """policy.kind: features (eq. 3) or tabular (runs from before policy.kind existed: features)."""
        return str((self.config.get("policy") or {}).get("kind", "features"))

    @property
    def features(self) -> list[str]:
        """policy.features of a features policy ([signals], the paper's, when absent)."""
        return [str(f) for f in ((self.config.get("policy") or {}).get("features") or ["signals"])]

    @property
    def team_conf(self) -> dict:
        return self.config.get("team") or {}

    @property
    def faults(self) -> list:
        """team.faults (a list of {robot, kind, from, ...})."""
        return list(self.team_conf.get("faults") or [])

    @property
    def heterogeneous(self) -> bool:
        """A team whose robots start apart (team.starts) or optimise their own measures (team.risk)."""
        return self.team and bool(self.team_conf.get("starts") or self.team_conf.get("risk"))

    @property
    def robots(self) -> int:
        return self.first.robots

    @property
    def team(self) -> bool:
        return self.robots > 1

    @property
    def seeds(self) -> list[int]:
        return [r.seed for r in self.runs]


@dataclass
class Collection:
    """Everything found under the report's input paths."""

    inputs: list[Path]
    runs: list[RunInfo]
    broken: list[Broken]
    landscapes: list  # riskplan.experiments.landscape.Landscape
    groups: list[Group]
    differing: list[str]  # config keys that differ between groups
    studies: list[Study] = field(default_factory=list)  # the runs of reproduce's study folders, apart
    duplicates: list[Duplicate] = field(default_factory=list)  # runs repeating another's config and seed: unused

    def paper_pair(self) -> tuple[Group | None, Group | None]:
        """The risk-neutral and risk-averse groups of Figs. 1-2: centralized if any, differing least."""
        return paper_pair(self.groups)

    def team_comparison(self) -> tuple[Group | None, list[Group]]:
        """Fig. 3: the centralized group and the distributed groups it is compared with."""
        teams = [g for g in self.groups if g.team]
        if not teams:
            return None, []
        measures = {g.measure for g in teams}
        measure = "cvar" if "cvar" in measures else sorted(measures)[0]
        teams = [g for g in teams if g.measure == measure]
        central = [g for g in self.groups if not g.team and g.measure == measure]
        if not central:
            return None, teams
        best = min(
            central,
            key=lambda c: (sum(_distance(c.first.flat, t.first.flat) for t in teams), abs(c.beta - teams[0].beta)),
        )
        return best, teams


@dataclass
class Study:
    """The runs of one of reproduce's studies (STUDIES), grouped and labelled among themselves."""

    name: str  # a key of STUDIES
    title: str
    folders: list[Path]
    collection: Collection


def schedule_pairs(groups: list[Group]) -> list[tuple[Group, Group | None]]:
    """Each soft-risk group (risk.schedule.kind other than none) with the group that differs from it only in
    risk.schedule.* (its paper-schedule comparator, e.g. reproduce's wander/ for soft_risk/), or None."""

    def rest(g: Group) -> dict:
        return {k: v for k, v in g.first.flat.items() if not k.startswith(f"{KEYS.risk.schedule}.")}

    pairs = []
    for g in groups:
        if g.schedule == "none" or g.measure != "cvar":
            continue
        same = [c for c in groups if c.schedule == "none" and c.measure == "cvar" and rest(c) == rest(g)]
        pairs.append((g, same[0] if same else None))
    return pairs


def paper_pair(groups: list[Group]) -> tuple[Group | None, Group | None]:
    """The risk-neutral and risk-averse groups of Figs. 1-2: centralized if any, differing least."""
    pool = [g for g in groups if not g.team] or list(groups)
    neutral = [g for g in pool if g.measure == "neutral"]
    # the paper's risk-averse policy is CVaR's; another measure stands in only when no CVaR group is there
    averse = [g for g in pool if g.measure == "cvar"] or [g for g in pool if g.measure != "neutral"]
    if neutral and averse:

        def distance(pair):
            a, b = pair
            return (_distance(a.first.flat, b.first.flat), abs(b.beta - a.beta), abs(b.beta - 0.1))

        return min(((a, b) for a in neutral for b in averse), key=distance)
    if averse:
        return None, min(averse, key=lambda g: (abs(g.beta - 0.1), g.label))
    return (neutral[0] if neutral else None), None


def flatten(config: Any, prefix: str = "") -> dict[str, Any]:
    """Nested dict -> {dotted.key: value}; lists become JSON strings so they compare and hash."""
    out: dict[str, Any] = {}
    if isinstance(config, dict):
        for k, v in config.items():
            out.update(flatten(v, f"{prefix}{k}."))
        if not config and prefix:
            out[prefix[:-1]] = "{}"
    elif isinstance(config, (list, tuple)):
        out[prefix[:-1]] = json.dumps(config, sort_keys=True)
    else:
        out[prefix[:-1]] = config
    return out


def theta_columns(metrics: pd.DataFrame) -> list[str]:
    """theta_0, theta_1, ... in numeric order."""
    cols = [c for c in metrics.columns if c.startswith("theta_") and c[6:].isdigit()]
    return sorted(cols, key=lambda c: int(c[6:]))


def collect(paths: list[Path], progress: Progress | None = None) -> Collection:
    """Find, load and group every run under `paths`; BadInput only for a path that holds no run at all.
    `progress(done, total)`: runs loaded so far."""
    inputs = [Path(p) for p in paths]
    found = find_runs(inputs)  # BadInput for a missing path or one without any run
    broken: list[Broken] = []
    landscapes = []
    folders = study_folders(inputs)
    loaded: list[tuple[RunInfo, str | None]] = []  # each usable run with its study (None: none), in path order
    results = _load_all([path for path in found if not is_landscape_dir(path)], progress)
    for path in found:
        if path not in results:
            try:
                landscapes.append(load_landscape(path))
            except Exception as err:
                broken.append(
                    Broken(path, f"landscape: {_reason(err, path)}", "compute it again (riskplan landscape --out DIR)")
                )
            continue
        info, problem, unfinished = results[path]
        if info is None:
            writer = lock.holder(path)  # a log cut short while its run still trains is no damage
            reason = f"is still running (pid {writer}): {problem}" if writer else problem
            broken.append(Broken(path, reason, _remedy(path) if unfinished or writer else ""))
        else:
            loaded.append((info, study_of(path, folders)))
    pools: dict[str | None, list[RunInfo]] = {}  # the paper's runs (None) and each study's, pooled apart
    for info, study in loaded:
        pools.setdefault(study, []).append(info)
    duplicates = []
    for study, members in pools.items():  # one sample per config and seed in each pool
        pools[study], repeats = distinct(members, lambda r: as_compared(r.config))
        duplicates += [Duplicate(info.path, of, info.seed) for info, of in repeats]
    duplicates.sort(key=lambda d: str(d.path))
    runs = pools.pop(None, [])
    studied: dict[str, list[RunInfo]] = pools
    groups, differing = group_runs(runs)
    studies = []
    for name, (title, _) in STUDIES.items():
        if name in studied:
            members, keys = group_runs(studied[name])
            own = Collection([p for p in folders if folders[p] == name], studied[name], [], landscapes, members, keys)
            studies.append(Study(name, title, own.inputs, own))
    return Collection(inputs, runs, broken, landscapes, groups, differing, studies, duplicates)


def as_compared(config: dict) -> dict:
    """The config as the report compares runs, for their groups and for repeats: risk.schedule's defaults filled in
    (runs from before risk.schedule existed ran without one), and the engine node (the device) left out, as
    run_identity leaves it: a run on the GPU is a seed of its condition on the CPU."""
    config = {k: v for k, v in config.items() if k not in HOW_KEYS}
    risk = config.get("risk")
    if not isinstance(risk, dict):
        return config
    schedule = risk.get("schedule")
    defaults = {key.rsplit(".", 1)[1]: value for key, value in SCHEDULE_DEFAULTS.items()}
    return {**config, "risk": {**risk, "schedule": {**defaults, **(schedule if isinstance(schedule, dict) else {})}}}


def study_folders(inputs: list[Path]) -> dict[Path, str]:
    """The study folders (STUDIES) directly inside the input directories: folder -> study name."""
    out = {}
    for root in inputs:
        for name, (_, names) in STUDIES.items():
            for folder in names:
                if (root / folder).is_dir():
                    out[(root / folder).resolve()] = name
    return out


def study_of(path: Path, folders: dict[Path, str]) -> str | None:
    """The study whose folder holds this run directory, or None."""
    if not folders:
        return None
    resolved = Path(path).resolve()
    for folder, name in folders.items():
        if resolved == folder or folder in resolved.parents:
            return name
    return None


def _remedy(path: Path) -> str:
    """What makes a run that stopped short reportable: a sweep's job (its status.json holds the sweep's fingerprint
    of it, config_sha) is resumed by its sweep, as `riskplan train --resume` says when it refuses one."""
    status = read_status(path)
    if isinstance(status, dict) and "config_sha" in status:
        return f"let its sweep finish, or run the sweep again with hydra.sweep.dir={path.parent} (it resumes its jobs)"
    return RESUME


def _load(path: Path) -> tuple[RunInfo | None, str, bool]:
    """Load one run; (None, reason, unfinished) when it is broken, partial or failed, `unfinished` when a resume
    could finish it (killed, still running or failed, rather than damaged)."""
    failed = _failed_status(path)
    try:
        run = load_run(path)
    except Exception as err:
        return None, failed or _reason(err, path), bool(failed)
    if not run.complete:
        reason = run.problem or "incomplete run"
        return None, f"{failed}; {reason}" if failed else reason, True
    if failed:
        return None, failed, True
    missing = [name for name in ("metrics", "eval") if getattr(run, name) is None or getattr(run, name).empty]
    if missing:
        what = {"metrics": "metrics table (no iterations)", "eval": "eval table (no evaluation episodes)"}
        return None, "empty " + " and ".join(what[m] for m in missing), False
    if not run.config:
        return None, "no config (.hydra/config.yaml missing and none in run.mcap)", False
    if run.summary is not None and not isinstance(run.summary, dict):
        return None, "summary.json is not a JSON object (it was not written by riskplan)", False
    problem = config_problem(run.config) or _edited(path, run.config)  # a typo's own line first: the key it names
    if problem:
        return None, problem, False
    rebuilt = not all((path / table_file(name)).is_file() for name in TABLES) or bool(
        run.problem and "rebuilt" in run.problem
    )
    flat = {k: v for k, v in flatten(as_compared(run.config)).items() if k not in IGNORED_KEYS}
    info = RunInfo(run, flat, rebuilt, log_cut=not rebuilt and log_cut_short(path / RUN_LOG))
    try:
        # the report reads the headline policy's evaluation alone: a team's other robots' episodes (eight times
        # as many rows) are left on disk, not held and sent between the processes that load the runs
        run.eval = info.eval_of()
        usable = not run.eval.empty and not info.metrics_of().empty
    except (AttributeError, KeyError) as err:
        return None, f"tables lack a column: {err}", False
    if not usable:
        return None, f"no metrics or evaluation rows for the headline policy (robot {info.headline})", False
    return info, "", False


def _load_all(paths: list[Path], progress: Progress | None = None) -> dict[Path, tuple[RunInfo | None, str, bool]]:
    """_load of each run directory, on all CPUs (reading the tables and checking the configs is a fifth of a
    reproduction's report): a condition's seeds at a time, so that one process checks their config once."""
    conditions: dict[tuple, list[Path]] = {}
    for path in paths:
        conditions.setdefault(_condition(path), []).append(path)
    batches = list(conditions.values())
    loaded = shared_map(
        lambda batch: [_load(p) for p in batch],
        batches,
        cost=lambda batch: sum(map(_size, batch)),
        progress=progress,
        weight=len,
    )
    return {path: result for batch, results in zip(batches, loaded) for path, result in zip(batch, results)}


def _condition(path: Path) -> tuple[Path, str]:
    """A run directory's folder and its name without the seed (risk=cvar,seed=1 -> risk=cvar,): a sweep names a
    condition's seeds alike. Only the sharing of the loading depends on it."""
    return path.parent, re.sub(r"(?<![^,])seed=\d+", "", path.name)


def _size(path: Path) -> int:
    """Bytes of the files in a run directory: a guess of what loading it costs (its tables, or run.mcap); 0 for
    one that cannot be listed (_load says why)."""
    try:
        return sum(file.stat().st_size for file in path.iterdir() if file.is_file())
    except OSError:
        return 0


def _edited(path: Path, config: dict) -> str:
    """Why a run's .hydra/config.yaml is not the config its run.mcap recorded last (edited or damaged since: its run
    would be reported as another condition's, or as another seed), or ''. A key the log lacks is one a later
    riskplan added, no difference (riskplan.run.run_directory.differing, as a resume checks it)."""
    logged = logged_config(path / RUN_LOG) if (path / CONFIG).is_file() and (path / RUN_LOG).is_file() else None
    changed = differing(logged, config) if logged is not None else []
    if not changed:
        return ""
    key, more = changed[0], f" (and {len(changed) - 1} more)" if len(changed) > 1 else ""
    return (
        f"{CONFIG}: differs from the config {RUN_LOG} recorded for this run in {key} ({_at(config, key)!r} here, "
        f"{_at(logged, key)!r} recorded){more}; restore it, or train a new run"
    )


def _at(config: Any, key: str) -> Any:
    """The value at a dotted key of a nested config (None where it is missing)."""
    for part in key.split("."):
        config = config.get(part) if isinstance(config, dict) else None
    return config


def _failed_status(path: Path) -> str:
    """The error recorded in status.json by a failed job, or ''."""
    file = path / STATUS
    if not file.is_file():
        return ""
    try:
        status = json.loads(file.read_text())
    except (OSError, ValueError):
        return ""
    if status.get("status") == "failed":
        return f"job failed: {status.get('error') or 'no reason recorded'}"
    return ""


def _reason(err: BaseException, path: Path | None = None) -> str:
    """One line for an exception (a path inside the run directory shown relative to it)."""
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    if not isinstance(err, BadInput):
        return f"{type(err).__name__}: {text}"
    if path is not None and err.where.startswith(f"{path}/"):
        return f"{err.where[len(str(path)) + 1 :]}: {err.problem}".replace("\n", "\\n")
    return text


_CHECKED: dict[str, str] = {}  # config (without its seed) as JSON -> problem ('' when fine): seeds share one check


def config_problem(config: dict) -> str:
    """Why a run's config cannot be reported (it fails the schema, or a value the report relies on is out of
    range), or ''."""
    seed = config.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        return f"config fails the schema: seed is {seed!r}; expected a whole number"
    try:
        key = json.dumps({k: v for k, v in config.items() if k != "seed"}, sort_keys=True, default=str)
    except (TypeError, ValueError):
        key = None
    if key is not None and key in _CHECKED:
        return _CHECKED[key]
    try:
        cfg = check_schema(config)
        risk, robots = cfg.risk, cfg.team.robots
        if not 0.0 < risk.beta <= 1.0:
            raise BadInput(KEYS.risk.beta, f"got {risk.beta}; expected 0 < beta <= 1")
        if robots < 1:
            raise BadInput(KEYS.team.robots, f"got {robots}; expected a whole number >= 1")
        problem = ""
    except BadInput as err:
        problem = f"config fails the schema: {err}"
    except Exception as err:
        problem = f"config fails the schema: {_reason(err)}"
    if key is not None:
        _CHECKED[key] = problem
    return problem


def _distance(a: dict, b: dict) -> int:
    """Number of keys on which two flat configs differ."""
    return sum(1 for k in set(a) | set(b) if a.get(k, MISSING) != b.get(k, MISSING))


def group_runs(runs: list[RunInfo]) -> tuple[list[Group], list[str]]:
    """Group runs by every config key but the seed; label and colour the groups."""
    keys = sorted({k for r in runs for k in r.flat})
    differing = [k for k in keys if len({hashable(r.flat.get(k, MISSING)) for r in runs}) > 1]
    by_key: dict[tuple, list[RunInfo]] = {}
    for r in runs:
        key = tuple(hashable(r.flat.get(k, MISSING)) for k in differing)
        by_key.setdefault(key, []).append(r)
    groups = []
    for key, members in by_key.items():
        members.sort(key=lambda r: (r.seed, str(r.path)))
        group = Group(key, members, settings={k: members[0].flat.get(k, MISSING) for k in differing})
        for r in members:
            r.group = group
        groups.append(group)
    groups.sort(key=lambda g: (g.robots, g.measure != "neutral", g.beta, str(g.key)))
    label_groups(groups, differing)
    _colour(groups)
    return groups, differing


def _colour(groups: list[Group]) -> None:
    """The paper's pair first (risk-neutral blue, risk-averse black), then the palette in order."""
    neutral, averse = paper_pair(groups)
    if neutral is not None:
        neutral.color = PALETTE[0]
    if averse is not None:
        averse.color = PALETTE[1]
    taken = [g for g in (neutral, averse) if g is not None]
    palette = [c for c in PALETTE if c not in {g.color for g in taken}]
    for i, g in enumerate(g for g in groups if g not in taken):
        g.color = palette[i % len(palette)]
