"""A sweep's jobs as data (sweeping.as_data, sweeping.job_setup): a job's config from its composition with its
keys set is exactly the config Hydra composes for it (typed, plain and its identity), and the files written for
it are byte for byte those Hydra's run_job writes."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from riskplan.config import schema
from riskplan.config.typed import as_dict, typed
from riskplan.experiments.sweep_worker import config_sha
from riskplan.experiments.sweeping import as_data, batched, grid, job_setup
from riskplan.experiments.sweeping.as_data import Composition
from riskplan.experiments.sweeping.execute import run_sweep
from riskplan.experiments.sweeping.grid import ParsedOnce
from riskplan.experiments.sweeping.job_setup import Dumps
from riskplan.run import build
from riskplan.run.compose import CONF_DIR, parse_overrides

AS_DATA = [
    ["seed=3"],
    ["risk.beta=1"],  # an int on a float key: 1.0, as OmegaConf stores it
    ["risk.beta=0.1", "seed=7"],
    ["team.graph=complete"],  # a Choice: an Enum member
    ["world.horizon=12", "train.iterations=5"],
    ["engine.device=cpu"],
    ["team.delay.max=2", "team.robots=3"],
    ["risk.schedule.kind=linear"],
    ["train.samples_growth=1", "train.baseline=false"],
    ["policy.kind=tabular", "train.step_size.initial=2"],
    ["train.theta0=[1,2]"],  # a list
    ["policy.features=[signals,risky]", "train.theta0=[0,0]"],  # a list of Choices
    ["team.robots=3", "team.starts=[[0,0],[5,0],[11,0]]"],  # a list of lists
    ["team.faults=[{robot:1,kind:byzantine,from:2,value:[-10,40]}]"],  # a list of typed entries
    ["team.delay={max:2}"],  # a mapping, merged into the key's own
    ["team.delay={max:2}", "team.delay.max=3", "seed=2"],  # a key inside it set after it
]
THROUGH_HYDRA = [
    ["+train.extra=1"],  # a key the schema lacks: Hydra names it
    ["~train.paths"],
    ["team.delay.max=3", "team.delay={drop:0.5}"],  # a mapping set after a key inside it
    ["seed=${train.iterations}"],  # an interpolation
    ["seed=abc"],  # a value the key refuses
    ["team.starts.0=[1,1]"],  # inside a list
]


@pytest.fixture(scope="module")
def compositions():
    schema.register()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        yield {
            groups: (groups, Composition(compose("config", list(groups))))
            for groups in ((), ("experiment=paper_team",))
        }
    GlobalHydra.instance().clear()


@pytest.mark.parametrize("groups", [(), ("experiment=paper_team",)])
@pytest.mark.parametrize("keys", AS_DATA, ids=",".join)
@pytest.mark.slow  # 33 Hydra compositions
def test_a_job_as_data_is_the_config_hydra_composes(compositions, groups, keys):
    _, composition = compositions[groups]
    job = composition.job(ParsedOnce()(keys))
    assert job is not None
    whole = compose("config", [*groups, *keys])  # inside the fixture's initialize_config_dir
    assert job.params == typed(whole)
    assert job.plain == OmegaConf.to_container(whole, resolve=True)
    assert config_sha(job.plain) == config_sha(whole)


@pytest.mark.parametrize("keys", THROUGH_HYDRA, ids=",".join)
def test_what_only_hydra_can_compose_is_left_to_it(compositions, keys):
    _, composition = compositions[()]
    assert composition.job(ParsedOnce()(keys)) is None


def test_a_composition_that_interpolates_sends_every_job_to_hydra(compositions):
    _, composition = compositions[()]
    cfg = OmegaConf.merge(composition.cfg, {"train": {"paths": "${train.iterations}"}})
    assert Composition(cfg).job(ParsedOnce()(["seed=1"])) is None  # setting one key could leave another stale


def test_a_config_as_a_job_is_hydras_and_its_groups_are_composed_once_a_process(monkeypatch):
    """A reproduction's checks and every sweep after them share one composition per choice of groups."""
    composed = []

    def counted(search, groups):
        composed.append(groups)
        return compose("config", [*search, *groups])

    monkeypatch.setattr(grid, "compose_groups", counted)
    monkeypatch.setattr(as_data, "_kept", type(as_data._kept)())
    first = grid.as_job(["experiment=paper_team", "risk=neutral", "seed=4"])
    second = grid.as_job(["experiment=paper_team", "risk=neutral", "risk.beta=0.3"])
    assert composed == [("experiment=paper_team", "risk=neutral")]
    schema.register()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for job, keys in ((first, ["seed=4"]), (second, ["risk.beta=0.3"])):
            assert job.params == typed(compose("config", ["experiment=paper_team", "risk=neutral", *keys]))
    GlobalHydra.instance().clear()
    assert grid.as_job(["experiment=paper_team", "seed=${train.iterations}"]) is None  # compose() takes it


def test_a_kept_composition_is_composed_again_once_a_config_file_changes(tmp_path, monkeypatch):
    """A --config-dir file edited between two sweeps of one process (a notebook) is read again."""
    (tmp_path / "experiment").mkdir()
    mine = tmp_path / "experiment" / "mine.yaml"
    mine.write_text("# @package _global_\ndefaults:\n  - paper_single\nseed: 5\n")
    search = [f"hydra.searchpath=[file://{tmp_path}]"]
    monkeypatch.setattr(as_data, "_kept", type(as_data._kept)())
    schema.register()
    GlobalHydra.instance().clear()
    seeds = []
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        for text in (None, "seed: 6"):
            if text is not None:
                mine.write_text(mine.read_text().replace("seed: 5", text))
            kept = as_data.shared(
                ("experiment=mine",), ParsedOnce()(search), lambda: compose("config", [*search, "experiment=mine"])
            )
            again = as_data.shared(("experiment=mine",), ParsedOnce()(search), lambda: pytest.fail("composed twice"))
            assert again is kept
            seeds.append(kept.params.seed)
    GlobalHydra.instance().clear()
    assert seeds == [5, 6]


def test_a_sweep_s_numbers_are_known_without_parsing_and_equal_the_parse():
    parse = ParsedOnce()
    sweeps = parse_overrides(["seed=range(40000,40003)", "risk.beta=0.1,1,2.5e-3", "world.name=a,b"])
    parse.learn(sweeps)
    lines = ["seed=40001", "risk.beta=1", "risk.beta=0.0025"]
    fields = ("type", "key_or_group", "value_type", "_value", "package", "input_line")
    learned = [[getattr(parse.lines[line], f) for f in fields] for line in lines]
    assert learned == [[getattr(o, f) for f in fields] for o in parse.parser.parse_overrides(lines)]
    assert [type(o._value) for o in map(parse.lines.get, lines)] == [int, int, float]
    assert "world.name=a" not in parse.lines  # strings are parsed when a job needs them


def test_the_dumps_of_shared_entries_are_byte_for_byte_a_whole_dump():
    data = {
        "a": {"b": [1, "x y"], "c": {}, "d": {"e": "line one\n\nline three\n", "f": None, "g": []}},
        "h": "yes",  # quoted: YAML 1.1 would read a bool
        "i": {"j": {"k": 1.5, "l": "${x}"}},
    }
    dumps = Dumps()
    assert dumps(data) == job_setup._dump(data)
    changed = {**data, "i": {**data["i"], "j": {"k": 2.5, "l": "${x}"}}}
    assert dumps(changed) == job_setup._dump(changed)  # only the changed entries dumped again
    assert dumps({"hydra": changed}) == job_setup._dump({"hydra": changed})


def test_runs_that_share_their_world_config_share_the_built_world(compositions):
    _, composition = compositions[()]
    one, two = (composition.job(ParsedOnce()([f"seed={s}"])) for s in (1, 2))
    first, second = build.build_setup(one.params), build.build_setup(two.params)
    assert first.world is second.world and first.kernel is second.kernel
    assert first.config == as_dict(one.params) and second.config == as_dict(two.params)
    wider = composition.job(ParsedOnce()(["world.horizon=31"]))
    assert build.build_setup(wider.params).world is not first.world


SMALL = ["train.iterations=2", "train.samples=40", "train.eval_episodes=50", "train.bootstrap=40", "train.paths=2"]
ARGS = ["seed=0,1", "risk.beta=0.1,1", *SMALL]
LISTS = [  # lists, typed entries with a Choice, a mapping merged into the key's own
    "experiment=paper_team",
    "team.robots=3",
    "team.starts=[[0,0],[5,0],[11,0]],[[1,1],[2,2],[3,3]]",
    "team.faults=[{robot:2,kind:byzantine,from:0,value:[-10,40]}]",
    "team.delay={max:2}",
    *SMALL,
]


@pytest.mark.slow  # two small batched sweeps, about 10 s
@pytest.mark.parametrize("args", [ARGS, LISTS], ids=["keys", "lists"])
def test_a_batched_sweep_s_files_are_those_hydra_s_run_job_writes(tmp_path, monkeypatch, args):
    direct = tmp_path / "direct"
    with monkeypatch.context() as patched:  # every job as data: none through run_job
        patched.setattr(batched, "_run_job", lambda *args: pytest.fail("a job went through run_job"))
        run_sweep(args, sweep_dir=direct, batch=True, out=lambda text: None)
    monkeypatch.setattr(job_setup.JobSetup, "__call__", lambda self, overrides, number: None)  # run_job for each
    hydra = tmp_path / "hydra"
    run_sweep(args, sweep_dir=hydra, batch=True, out=lambda text: None)
    folders = sorted(p.name for p in direct.iterdir() if p.is_dir())
    assert len(folders) == (4 if args is ARGS else 2)
    assert folders == sorted(p.name for p in hydra.iterdir() if p.is_dir())
    for folder in folders:
        for name in ("config.yaml", "hydra.yaml", "overrides.yaml"):
            mine = (direct / folder / ".hydra" / name).read_text().replace(str(direct), "SWEEP")
            theirs = (hydra / folder / ".hydra" / name).read_text().replace(str(hydra), "SWEEP")
            assert mine == theirs, (folder, name)
        statuses = [yaml.safe_load(Path(root / folder / "status.json").read_text()) for root in (direct, hydra)]
        assert statuses[0]["config_sha"] == statuses[1]["config_sha"] and statuses[0]["cvar"] == statuses[1]["cvar"]
