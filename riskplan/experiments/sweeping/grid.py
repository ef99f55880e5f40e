"""What a sweep's overrides go through before anything runs: counted, expanded, every combination composed and
checked, job folders named, Hydra's own settings checked."""

from __future__ import annotations

import contextlib
import copy
import functools
import hashlib
import itertools
import json
import math
import posixpath
import warnings
from fractions import Fraction
from pathlib import Path
from typing import ClassVar

from hydra import compose as hydra_compose
from hydra import initialize_config_dir
from hydra._internal.config_loader_impl import ConfigLoaderImpl, get_overrides_dirname
from hydra._internal.utils import create_config_search_path
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, Glob, Override, OverrideType, RangeSweep, ValueType
from hydra.errors import HydraException
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from riskplan.config import schema
from riskplan.config.hydra_safety import check_hydra_node, check_resolvers
from riskplan.config.typed import choice_problem
from riskplan.config.validate import IgnoredKey
from riskplan.engine.step import batch_key
from riskplan.experiments.sweep_worker import HOW_KEYS, config_sha, folder_name
from riskplan.experiments.sweeping.as_data import Composition, JobConfig, shared
from riskplan.experiments.sweeping.jobs import SWEEPS_ROOT, Job
from riskplan.run.build import build_setup
from riskplan.run.compose import CONF_DIR, explain, parse_overrides
from riskplan.run.compose import compose as riskplan_compose
from riskplan.run.cost import run_bytes, setup_steps
from riskplan.run.maps import map_record
from riskplan.util.errors import BadInput, MissingExtra, first_line
from riskplan.util.limits import check_jobs
from riskplan.util.paths import claim_dir, hydra_quote
from riskplan.util.progress import PhaseBars


def target_dir(sweep_dir: Path | None, explicit_dir: Path | None, argv: list[str]) -> Path:
    """The sweep directory, made or claimed now that the input is known to be good."""
    if sweep_dir is not None:
        target = Path(sweep_dir)
        target.mkdir(parents=True, exist_ok=True)
    elif explicit_dir is not None:
        target = explicit_dir
        target.mkdir(parents=True, exist_ok=True)
    else:
        target = claim_dir(SWEEPS_ROOT)
    if explicit_dir is None or not explicit_dir.is_absolute():  # absolute: jobs on other machines (submitit, ray)
        argv.append(f"hydra.sweep.dir={hydra_quote(target.resolve())}")  # may start in another directory
    return target


def sweep_size(task_ovs: list) -> tuple[int, object]:
    """How many combinations the overrides make, from their parsed values (a range is never listed), and the
    swept override with the most values."""
    parser = override_parser()
    total, biggest, most = 1, None, 0
    for override in task_ovs:
        if not override.is_sweep_override():
            continue
        value = override.value()
        if isinstance(value, RangeSweep):
            if any(isinstance(v, float) and not math.isfinite(v) for v in (value.start, value.stop, value.step)):
                raise BadInput(
                    f"override '{override.input_line}'",
                    "has a range bound or step that is not a finite "
                    "number; give finite numbers, e.g. range(0,5) or "
                    "range(0,1,0.25)",
                )
            if not value.step:
                raise BadInput(
                    f"override '{override.input_line}'",
                    "has a range step of 0; give a step that is not 0, e.g. range(0,5) or range(0,1,0.25)",
                )
            count = _range_length(value.start, value.stop, value.step)
        elif isinstance(value, ChoiceSweep):
            count = len(value.list)
        else:  # glob(...) over a config group's options: few
            try:
                reparsed = parser.parse_overrides([override.input_line])[0]
                count = sum(1 for _ in reparsed.sweep_string_iterator())
            except Exception:
                count = 1
        total *= count
        if count > most:
            biggest, most = override, count
    return total, biggest


def _range_length(start, stop, step) -> int | float:
    """len(range(start, stop, step)) for ints of any size and for floats, without listing it (inf when unbounded;
    0 for a zero or undefined step, which expand() then reports)."""
    try:
        if all(isinstance(v, int) for v in (start, stop, step)):
            return max(0, math.ceil(Fraction(stop - start, step))) if step else 0
        ratio = (float(stop) - float(start)) / float(step)
    except (ZeroDivisionError, TypeError, ValueError, OverflowError):
        return 0
    if math.isnan(ratio):
        return 0
    return max(0, math.ceil(ratio)) if math.isfinite(ratio) else math.inf


def check_size(task_ovs: list) -> None:
    """A sweep larger than the job budget (RISKPLAN_MAX_JOBS) is bad input, before anything is expanded."""
    total, biggest = sweep_size(task_ovs)
    swept = [o for o in task_ovs if o.is_sweep_override()]
    key = f"override '{biggest.input_line}'" if len(swept) == 1 and biggest is not None else "sweep"
    check_jobs(key, total)


def check_subdir(value, several: bool) -> None:
    """A hydra.sweep.subdir of the user's: without an interpolation it must be one relative folder, and it cannot
    serve several jobs (they would share it)."""
    text = "" if value is None else str(value)
    if "${" in text:
        return  # per job (${hydra.job.num}, ...): the user's naming
    parts = [p for p in text.replace("\\", "/").split("/") if p not in ("", ".")]
    if not parts or posixpath.isabs(text) or ".." in parts or "\x00" in text:
        raise BadInput(
            "hydra.sweep.subdir",
            f"got {text!r}; give a folder inside the sweep directory, e.g. "
            f"job_${{hydra.job.num}}, or leave it out (riskplan names each job's "
            f"folder from its overrides)",
        )
    if several:
        raise BadInput(
            "hydra.sweep.subdir",
            f"got {text!r}: every job of the sweep would write into that one "
            f"folder; use an interpolation such as job_${{hydra.job.num}}, or leave "
            f"it out (riskplan names each job's folder from its overrides)",
        )


def check_duplicates(job_list: list[Job], task_ovs: list) -> None:
    """Two combinations that compose to one config (seed=0,0 or risk.beta=0.1,0.10) would be one job twice, in two
    folders or one: bad input naming the override."""
    seen: dict[str, Job] = {}
    for job in job_list:
        other = seen.setdefault(job.sha, job)
        if other is job:
            continue
        mine, theirs = _by_key(job.overrides), _by_key(other.overrides)
        differ = [k for k in theirs if theirs[k] != mine.get(k)]
        by_key = {o.key_or_group: o for o in task_ovs}
        if differ:
            key = differ[0]
            line = by_key[key].input_line if key in by_key else key
            raise BadInput(
                f"override '{line}'",
                f"gives {theirs[key]} and {mine[key]}, which compose to the same "
                f"config (one job twice); give each value once",
            )
        for override in task_ovs:
            value = _repeated(override) if override.is_sweep_override() else None
            if value is not None:
                raise BadInput(
                    f"override '{override.input_line}'",
                    f"gives the value {value} twice (one job twice); give each value once",
                )
        raise BadInput(
            "sweep",
            f"gives the combination {job.label or ','.join(sorted(job.overrides))} twice (one "
            f"job twice); give each combination once",
        )


def _by_key(overrides: list[str]) -> dict[str, str]:
    """{key: 'key=value'} of a job's overrides."""
    return {line.split("=", 1)[0].lstrip("+~"): line for line in overrides}


def _repeated(override) -> str | None:
    """A value a sweep override lists twice (as Hydra passes it to the job: 0.10 is 0.1), or None."""
    try:
        values = list(override.sweep_string_iterator())
    except Exception:
        return None
    seen: set[str] = set()
    for value in values:
        if value in seen:
            return value
        seen.add(value)
    return None


def name_folders(job_list: list[Job], naming: dict, task_ovs: list, parse: ParsedOnce | None = None) -> None:
    """The folder each job gets (Hydra's override_dirname through riskplan.experiments.sweep_worker.folder_name); two jobs that
    would share one are bad input."""
    parse = parse or ParsedOnce()
    owners: dict[str, Job] = {}
    for job in job_list:
        dirname = get_overrides_dirname(
            parse(job.overrides),
            list(naming["exclude_keys"]),
            str(naming["item_sep"]),
            str(naming["kv_sep"]),
        )
        job.folder = folder_name(dirname)
        other = owners.setdefault(job.folder, job)
        if other is not job:
            swept = [o for o in task_ovs if o.is_sweep_override()] or task_ovs
            raise BadInput(
                f"override '{swept[0].input_line}'",
                f"makes two combinations share the job folder {job.folder} "
                f"({','.join(sorted(other.overrides))} and {','.join(sorted(job.overrides))}); give "
                f"values that differ in their text, or set hydra.sweep.subdir",
            )


def add_naming_and_logging(argv: list[str], hydra_keys: dict, constant: list[str]) -> None:
    """riskplan's Hydra settings for a sweep, unless the user gave their own: job folders named by what varies
    (risk.beta=0.1,seed=0), not by every fixed setting (the job's .hydra/overrides.yaml keeps them all, and resuming
    matches jobs by their full config anyway), and logging into sweep.log and each job's job.log."""
    if constant and not {"hydra.sweep.subdir", "hydra.job.config.override_dirname.exclude_keys"} & set(hydra_keys):
        argv.append(
            "hydra.job.config.override_dirname.exclude_keys=[" + ",".join(hydra_quote(k) for k in constant) + "]"
        )
    if "hydra/hydra_logging" not in hydra_keys:
        argv.append("hydra/hydra_logging=riskplan_sweep")
    if "hydra/job_logging" not in hydra_keys:
        argv.append("hydra/job_logging=riskplan_job")


def expand(task_ovs: list, args: list[str]) -> list[list[str]]:
    """Every combination, in the order and with the job overrides Hydra's basic sweeper gives (the same grammar)."""
    parser = override_parser()
    try:
        combos = combinations(parser.parse_overrides([o.input_line for o in task_ovs]))
    except (HydraException, ValueError, TypeError, ArithmeticError) as err:
        raise _unexpandable(parser, task_ovs, err) from None
    if not combos or (task_ovs and any(not job for job in combos)):
        for o in parser.parse_overrides([o.input_line for o in task_ovs]):
            if o.is_sweep_override() and not list(o.sweep_string_iterator()):
                what = "matches no option of its group" if isinstance(o.value(), Glob) else "holds no value"
                raise BadInput(f"override '{o.input_line}'", f"{what}, so the sweep has no job; give it a value")
        raise BadInput("sweep", f"'{' '.join(args)}' expands to no job; check empty range(...) values")
    return combos


def _unexpandable(parser, task_ovs: list, err: Exception) -> BadInput:
    """The override a grid cannot expand, named: Hydra's own words (such as 'Unexpected type annotation: Set[str]'
    for a range inside a comma list) said neither which override nor why."""
    hint = "use comma lists, range(...), choice(...) or glob(...)"
    for o in task_ovs:
        try:
            combinations(parser.parse_overrides([o.input_line]))
        except (HydraException, ValueError, TypeError, ArithmeticError) as own:
            # a list whose items are sweeps (seed=1,range(1,2)): Hydra fails on the item's type
            nested = "Unexpected type annotation" in str(own)
            why = "a range(...), interval(...) or glob(...) cannot be an item of a list" if nested else first_line(own)
            return BadInput(f"override '{o.input_line}'", f"{why}; {hint}")
    return BadInput("sweep", f"{first_line(err)}; {hint}")


def combinations(overrides: list) -> list[list[str]]:
    """The cartesian product of the overrides' values, the first key varying slowest: a sweep gives one `key=value`
    per value, any other override its one; a key given twice keeps its last values in its first place."""
    values: dict[str, list[str]] = {}
    for override in overrides:
        key = override.get_key_element()
        if override.is_sweep_override():
            if not override.is_discrete_sweep():
                raise ValueError(f"a grid does not take {override.input_line} (a search space for an optimiser)")
            values[key] = [f"{key}={value}" for value in override.sweep_string_iterator()]
        else:
            values[key] = [f"{key}={override.get_value_element_as_str()}"]
    return [list(job) for job in itertools.product(*values.values())]


def check_hydra(hydra_args: list[str], first_job: list[str], sweeper: bool = False):
    """Compose Hydra's own config (launcher and its settings) once: a bad one is bad input, before anything runs.
    Returns hydra.job.config.override_dirname (exclude_keys, item_sep, kv_sep), which names the job folders, and
    with `sweeper` also hydra.sweeper (its settings, enums as text)."""
    schema.register()
    GlobalHydra.instance().clear()

    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            cfg = hydra_compose(config_name="config", overrides=[*hydra_args, *first_job], return_hydra_config=True)
            check_hydra_node(cfg, [o for o in parse_overrides(hydra_args) if o.is_hydra_override()])
            naming = OmegaConf.to_container(cfg.hydra.job.config.override_dirname, resolve=True)
            if sweeper:
                return naming, OmegaConf.to_container(cfg.hydra.sweeper, resolve=True, enum_to_str=True)
            return naming
    except (HydraException, OmegaConfBaseException) as err:
        where, message = explain(err)
        if where == "key 'hydra/launcher'":
            message += " (pip install 'riskplan[slurm]' for submitit_local|submitit_slurm, 'riskplan[ray]' for ray|ray_cluster)"
        if where == "key 'hydra/sweeper'":
            message += " (pip install 'riskplan[optuna]' for optuna)"
        raise BadInput(where, message) from None
    finally:
        GlobalHydra.instance().clear()


def constant_keys(combos: list[list[str]], swept: set[str] = frozenset(), parse: ParsedOnce | None = None) -> list[str]:
    """The override keys left out of job folder names: the engine's (engine.device: how a run computes, never what),
    and those with one value in every job that were not typed as a sweep (`seed=range(0,1)` keeps its key), as
    long as some key remains."""
    values = _given(combos, parse or ParsedOnce())
    unnamed = [k for k in values if unnamed_key(k)]
    named = {k: v for k, v in values.items() if k not in unnamed}
    constant = [k for k, v in named.items() if len(v) == 1 and k not in swept]
    return unnamed + (constant if len(constant) < len(named) else [])


def _given(combos: list[list[str]], parse: ParsedOnce) -> dict[str, set[str]]:
    """Each override key of the combinations, with the overrides that set it (one: the same in every job)."""
    values: dict[str, set[str]] = {}
    for combo in combos:
        for o in parse(combo):
            values.setdefault(o.key_or_group, set()).add(o.input_line)
    return values


def unnamed_key(key: str) -> bool:
    """Whether an override's key never names a job folder: a key of the engine node (sweep_worker.HOW_KEYS)."""
    return key.lstrip("+~").split(".", 1)[0] in HOW_KEYS


def validate(
    combos: list[list[str]], search: list[str] = (), parse: ParsedOnce | None = None
) -> tuple[list[Job], list[str]]:
    """Compose every combination against the schema (BadInput on the first failure), then check each with the
    model. Compositions are shared between combinations that choose the same config groups. `search`: the
    hydra.searchpath overrides (--config-dir) every composition needs to find the user's own config files."""
    parse = parse or ParsedOnce()
    schema.register()
    GlobalHydra.instance().clear()
    bases: dict[tuple[str, ...], Composition] = {}
    jobs: list[Job] = []
    notes: list[str] = []
    varying = {key for key, given in _given(combos, parse).items() if len(given) > 1}
    try:
        with (
            initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"),
            PhaseBars() if len(combos) >= PLAN_BAR else contextlib.nullcontext() as progress,
        ):
            for number, combo in enumerate(combos, 1):
                if progress is not None:
                    progress("plan: jobs checked", number, len(combos))
                groups, keys = parse.split(combo)
                try:
                    if groups not in bases:
                        bases[groups] = shared(groups, parse(search), functools.partial(compose_groups, search, groups))
                        check_resolvers(bases[groups].cfg)  # a config file's own (the overrides are checked apart)
                    as_data = bases[groups].job(keys)  # most jobs: no composition of their own
                    if as_data is None:
                        cfg = copy.deepcopy(bases[groups].cfg)
                        ConfigLoaderImpl._apply_overrides_to_config(keys, cfg)
                except (HydraException, OmegaConfBaseException) as err:
                    choice = choice_problem(err)
                    if choice is not None:  # a value outside a key's Choices fails only this job
                        jobs.append(Job(list(combo), combo_sha(combo), str(BadInput(*choice))))
                        continue
                    riskplan_compose([*search, *combo], validate=False)  # raises BadInput naming the key
                    cfg = hydra_compose(config_name="config", overrides=[*search, *combo])  # composes after all
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always")
                    try:
                        setup = build_setup(cfg if as_data is None else as_data.params)
                        steps, invalid = setup_steps(setup), None
                        shape = {"batch": batch_key(setup.params), "memory": run_bytes(setup)}
                    except MissingExtra:  # a missing package fails the whole sweep, not only this job
                        raise
                    except BadInput as err:
                        steps, invalid, shape = 0.0, str(err), {}
                for w in caught:
                    if isinstance(w.message, IgnoredKey) and w.message.chooser in varying:
                        continue  # the key is set for the sweep's variants that use it
                    if str(w.message) not in notes:
                        notes.append(str(w.message))
                plain = cfg if as_data is None else as_data.plain
                sha = config_sha(plain, map_record(setup.params.world) if invalid is None else None)
                jobs.append(Job(list(combo), sha, invalid, steps=steps, **shape))
    finally:
        GlobalHydra.instance().clear()
    return jobs, notes


PLAN_BAR = 2000  # jobs from which planning shows a bar (a second or more: 10,000 jobs plan in about 10 s)


def compose_groups(search: list[str], groups: tuple[str, ...]):
    """Hydra's composition of these config-group choices (inside initialize_config_dir)."""
    return hydra_compose(config_name="config", overrides=[*search, *groups])


def as_job(overrides: list[str]) -> JobConfig | None:
    """One config as a sweep's planning makes a job's: its plain keys set as data on its groups' composition,
    which the process keeps (as_data.shared), so a reproduction's checks compose nothing its sweeps do not. None
    when it needs Hydra (riskplan.run.compose.compose composes it then, and names what is wrong)."""
    parse = ParsedOnce()
    schema.register()
    GlobalHydra.instance().clear()
    try:
        groups, keys = parse.split(overrides)
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            return shared(groups, [], functools.partial(compose_groups, [], groups)).job(keys)
    except (HydraException, OmegaConfBaseException, ValueError):
        return None
    finally:
        GlobalHydra.instance().clear()


class ParsedOnce:
    """Hydra's override parser with each distinct override parsed once in this process (a sweep repeats its values
    across jobs, the planner and the launcher read the same jobs, and a parse costs a fraction of a millisecond),
    and each key's group-or-key answer remembered. A job override parses alone, whatever the sweep."""

    lines: ClassVar[dict[str, object]] = {}  # override line -> Override, shared by every instance
    LINES_KEPT: ClassVar[int] = 200_000

    def __init__(self):
        self.parser = override_parser()
        self.groups: dict[str, bool] = {}

    def __call__(self, overrides: list[str]) -> list:
        missing = [line for line in overrides if line not in self.lines]
        if missing:
            if len(self.lines) > self.LINES_KEPT:
                self.lines.clear()
            self.lines.update(zip(missing, self.parser.parse_overrides(missing)))
        return [self.lines[line] for line in overrides]

    def learn(self, sweeps: list) -> None:
        """The job overrides of these sweep overrides (`seed=range(0,1000)`), known without parsing: a number's
        `key=value` parses to the number the sweep lists (anything else is parsed when a job needs it)."""
        for override in sweeps:
            if not (override.is_sweep_override() and override.is_discrete_sweep() and override.package is None):
                continue
            key = override.get_key_element()
            if key != override.key_or_group:  # +key, ~key
                continue
            for text, value in zip(override.sweep_string_iterator(), override.sweep_iterator()):
                if type(value) in (int, float):
                    line = f"{key}={text}"
                    self.lines.setdefault(line, _number_override(key, value, line, self.parser))

    def split(self, overrides: list[str]) -> tuple[tuple[str, ...], list]:
        """The overrides that choose config groups (as typed) and those that set keys (parsed)."""
        parsed = self(overrides)
        chooses = [self._group(o) for o in parsed]
        return (
            tuple(o.input_line for o, group in zip(parsed, chooses) if group),
            [o for o, group in zip(parsed, chooses) if not group],
        )

    def _group(self, override) -> bool:
        key = override.input_line
        if key not in self.groups:
            self.groups[key] = is_group(override, CONF_DIR)
        return self.groups[key]


def _number_override(key: str, value: int | float, line: str, parser) -> Override:
    """The Override that parsing `key=<number>` gives."""
    return Override(
        type=OverrideType.CHANGE,
        key_or_group=key,
        value_type=ValueType.ELEMENT,
        _value=value,
        package=None,
        input_line=line,
        config_loader=parser.config_loader,
    )


def combo_sha(combo: list[str]) -> str:
    """A fingerprint of a combination that does not compose (no config to fingerprint): its overrides."""
    return "overrides:" + hashlib.sha256(json.dumps(combo).encode()).hexdigest()[:16]


def override_parser():
    """Hydra's override parser, with a config loader so that glob(...) over config groups works."""
    loader = ConfigLoaderImpl(config_search_path=create_config_search_path(str(CONF_DIR)))
    return OverridesParser.create(config_loader=loader)


def is_group(override, conf_dir: Path) -> bool:
    """Whether an override selects a config group option (experiment=..., risk=...) rather than sets a key."""
    return override.package is not None or (conf_dir / override.key_or_group).is_dir()


def split_bad(message: str, count: int) -> tuple[str, str]:
    """BadInput parts for 'every combination is invalid'."""
    where, _, problem = message.partition(": ")
    if count > 1:
        problem = f"{problem} (in every one of the {count} combinations; nothing was run)"
    return where, problem


class JobConfigs:
    """Each job's config as Hydra's `load_sweep_config` makes it, composed once per choice of config groups: a job
    that differs from one composed already only in plain keys is a copy of that composition with its keys set and
    its hydra.overrides.task and hydra.job.override_dirname filled in as Hydra fills them (a few milliseconds
    against a composition's tens). Anything unusual (a key the copy refuses) is composed by Hydra after all."""

    def __init__(self, loader, master):
        self.loader, self.master = loader, master
        self.parser = override_parser()
        self.hydra = list(OmegaConf.to_container(master.hydra.overrides.hydra))
        self.bases: dict[tuple[str, ...], object] = {}

    def __call__(self, overrides: list[str]):
        parsed = self.parser.parse_overrides(list(overrides))
        if any(o.is_hydra_override() for o in parsed):  # Hydra's own settings change more than keys
            return self.compose(list(overrides))
        groups = tuple(o.input_line for o in parsed if is_group(o, Path(CONF_DIR)))
        keys = [o for o in parsed if not is_group(o, Path(CONF_DIR))]
        try:
            if groups not in self.bases:
                self.bases[groups] = self.compose(list(groups))
            cfg = copy.deepcopy(self.bases[groups])
            ConfigLoaderImpl._apply_overrides_to_config(keys, cfg)
            naming = cfg.hydra.job.config.override_dirname
            cfg.hydra.overrides.task = [o.input_line for o in parsed]
            cfg.hydra.job.override_dirname = get_overrides_dirname(
                overrides=parsed, kv_sep=naming.kv_sep, item_sep=naming.item_sep, exclude_keys=naming.exclude_keys
            )
        except (HydraException, OmegaConfBaseException):
            return self.compose(list(overrides))
        OmegaConf.copy_cache(from_config=self.master, to_config=cfg)
        return cfg

    def compose(self, overrides: list[str]):
        """The sweep config of these overrides, composed by Hydra."""
        return self.loader.load_sweep_config(self.master, overrides)


def check_repeats(overrides: list) -> None:
    """A swept key given again later: Hydra keeps the last, so `seed=1,2 seed=3` dropped a dimension of the sweep
    unsaid. A plain value given again is Hydra's "the last wins" (a base list of overrides, then the sweep)."""
    swept: dict[str, str] = {}
    for o in overrides:
        key = o.key_or_group
        if key in swept:
            raise BadInput(
                key,
                f"swept by '{swept[key]}', then given again as '{o.input_line}', which would replace the sweep; give "
                f"it once, with every value to sweep: {key}=a,b,c",
            )
        if o.is_sweep_override():
            swept[key] = o.input_line
