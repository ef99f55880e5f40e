"""A batched sweep's jobs set up as data: each job's folder, `.hydra/config.yaml`, `hydra.yaml` and
`overrides.yaml` written directly, from its composition's config with the job's keys set (sweeping.as_data),
instead of one Hydra `run_job` per job (a composition, a deep copy, logging set up and torn down, three
OmegaConf saves: about 50 ms a job, a minute for a thousand).

The files hold what `run_job` writes: the job's config, Hydra's node with the job's number, overrides, folder
name and output folder filled in, and its overrides. A job this cannot set up exactly as Hydra would (a config
group of its own that does not compose as data, a job of the ray backend, a folder named by the user's hydra.sweep.subdir, a Hydra callback
or env_set of the user's, a working directory changed per job) returns None: the launcher sets it up through
`run_job` as before.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import yaml
from hydra._internal.config_loader_impl import get_overrides_dirname
from omegaconf import DictConfig, OmegaConf

from riskplan.config.backends import BACKENDS
from riskplan.config.hydra_safety import OUTPUT_SUBDIR
from riskplan.experiments.sweep_worker import SUBDIR, folder_name, holds_another_run
from riskplan.experiments.sweeping.as_data import Composition, JobConfig, yaml_ready
from riskplan.experiments.sweeping.grid import JobConfigs, ParsedOnce
from riskplan.experiments.sweeping.jobs import TRAVELS
from riskplan.util.paths import write_atomic

DUMPER = getattr(yaml, "CSafeDumper", yaml.SafeDumper)  # libyaml's when PyYAML has it: the same YAML, in C
OWN_CALLBACK = TRAVELS.split("=", 1)[0].lstrip("+").split(".")[2]  # riskplan_folders: only carries the resolver


@dataclass(frozen=True)
class JobFolder:
    """A job set up as data: its folder (with `.hydra/` written) and its config."""

    out: Path
    config: JobConfig


class JobSetup:
    """Sets up a launch's jobs as data, composing once per choice of config groups (through `configs`, Hydra's
    sweep config of each, as the launcher would make it)."""

    def __init__(self, configs: JobConfigs, sweep_dir: Path):
        self.configs, self.sweep_dir = configs, Path(sweep_dir)
        self.parse = ParsedOnce()
        self.dumps = Dumps()
        self.compositions: dict[tuple[str, ...], tuple[Composition, dict] | None] = {}

    def __call__(self, overrides: list[str], number: int) -> JobFolder | None:
        """Job `number`'s folder and config, its `.hydra/` files written (not over another config's run: the job
        refuses that folder); None when Hydra must set it up."""
        parsed = self.parse(overrides)
        if any(o.is_hydra_override() for o in parsed):
            return None
        groups, keys = self.parse.split(overrides)
        if groups not in self.compositions:
            self.compositions[groups] = self._composition(groups)
        known = self.compositions[groups]
        config = None if known is None else known[0].job(keys)
        if config is None or not BACKENDS[config.params.team.backend].batched:
            return None  # a ray-backend job trains alone, through run_job
        hydra = known[1]
        naming = hydra["job"]["config"]["override_dirname"]
        dirname = get_overrides_dirname(parsed, list(naming["exclude_keys"]), naming["item_sep"], naming["kv_sep"])
        out = self.sweep_dir / folder_name(dirname)
        if holds_another_run(out, config.plain):  # its .hydra/ is that run's: the job refuses the folder
            return JobFolder(out, config)
        node = {
            **hydra,
            "job": {**hydra["job"], "id": str(number), "num": number, "override_dirname": dirname},
            "overrides": {**hydra["overrides"], "task": list(overrides)},
            "runtime": {**hydra["runtime"], "output_dir": os.path.abspath(out)},
        }
        files = out / OUTPUT_SUBDIR
        out.mkdir(exist_ok=True)
        files.mkdir(exist_ok=True)
        self._write(files / "config.yaml", self.dumps(config.plain))
        self._write(files / "hydra.yaml", self.dumps({"hydra": node}))
        self._write(files / "overrides.yaml", _dump(list(overrides)))
        return JobFolder(out, config)

    @staticmethod
    def _write(path: Path, text: str) -> None:
        """Whole or not at all; not synced to disk: run_job does not sync them either, and a re-run writes them."""
        write_atomic(path, text, durable=False)

    def _composition(self, groups: tuple[str, ...]) -> tuple[Composition, dict] | None:
        """The composition of these config groups and its Hydra node as plain data, when its jobs can be set up
        as data (see the module docstring)."""
        cfg = self.configs.compose(list(groups))
        hydra = OmegaConf.to_container(cfg.hydra, resolve=False, enum_to_str=True)
        if not _as_run_job_would(cfg, hydra):
            return None
        composition = Composition(cfg)
        return None if composition.params is None else (composition, hydra)


def _as_run_job_would(cfg: DictConfig, hydra: dict) -> bool:
    """Whether writing the files directly gives what run_job would: riskplan's folder names and nothing of the
    user's that run_job does per job (callbacks, env_set, a changed working directory, another output_subdir)."""
    job = hydra["job"]
    return (
        hydra["sweep"]["subdir"] == SUBDIR
        and hydra.get("output_subdir") == OUTPUT_SUBDIR
        and not job.get("chdir")
        and not job.get("env_set")
        and set(hydra.get("callbacks") or {}) <= {OWN_CALLBACK}
        and OmegaConf.select(cfg, "hydra.job.config.override_dirname.exclude_keys") is not None
    )


def _dump(data) -> str:
    """YAML as OmegaConf.save writes it: block style, keys in their order."""
    return yaml.dump(data, Dumper=DUMPER, sort_keys=False, allow_unicode=True, default_flow_style=False)


class Dumps:
    """YAML of mappings whose entries jobs share (Enum members by their names, as OmegaConf saves them): a job's
    config and Hydra node differ from the next job's in a few entries, and as_data copies only the dicts along a
    changed path. So a mapping's text is kept by its identity, and a new mapping dumps only its changed entries
    (a leaf's text kept by its key and value). The text is byte for byte what dumping the whole gives."""

    def __init__(self):
        self.mappings: dict[tuple[int, str], tuple[dict, str]] = {}  # (id, indent) -> (the mapping, kept alive; text)
        self.leaves: dict[tuple[str, str, str], str] = {}  # (indent, key, value as JSON) -> text

    def __call__(self, data: dict, indent: str = "") -> str:
        kept = self.mappings.get((id(data), indent))
        if kept is not None and kept[0] is data:
            return kept[1]
        text = "".join(self._entry(key, value, indent) for key, value in data.items())
        self.mappings[(id(data), indent)] = (data, text)
        return text

    def _entry(self, key: str, value, indent: str) -> str:
        if isinstance(value, dict) and value:  # a block mapping: its key, then its entries one level deeper
            return self._leaf(key, {}, indent).replace(" {}\n", "\n", 1) + self(value, indent + "  ")
        return self._leaf(key, value, indent)

    def _leaf(self, key: str, value, indent: str) -> str:
        index = (indent, key, json.dumps(value, default=repr))
        text = self.leaves.get(index)
        if text is None:
            dumped = _dump({key: yaml_ready(value)})
            text = self.leaves[index] = "".join(_indented(line, indent) for line in dumped.splitlines(True))
        return text


def _indented(line: str, indent: str) -> str:
    """A line of a dumped entry, one level deeper (an empty line stays empty, as the dumper writes it)."""
    return indent + line if line.strip("\n") else line
