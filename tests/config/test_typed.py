"""riskplan.config.typed.typed: one frozen config per composed config, remembered, and never for a bad one."""

import pytest
from omegaconf import OmegaConf

from riskplan.config.typed import TYPED_MEMO, typed
from riskplan.run.compose import compose
from riskplan.util.errors import BadInput


def test_the_same_config_is_typed_once_and_another_gets_its_own():
    cfg = compose(["experiment=paper_team"], validate=False)
    first = typed(cfg)
    assert typed(OmegaConf.create(OmegaConf.to_container(cfg))) is first  # equal content, another node
    other = typed(compose(["experiment=paper_team", "seed=3"], validate=False))
    assert other is not first and (other.seed, first.seed) == (3, 0)
    with pytest.raises(AttributeError):
        first.seed = 5  # shared, so frozen


@pytest.mark.slow  # composes TYPED_MEMO + 3 configs: about 2 s
def test_a_bad_config_raises_every_time_and_old_entries_are_dropped():
    bad = OmegaConf.to_container(compose([], validate=False))
    bad["risk"]["beta"] = "abc"
    for _ in range(2):
        with pytest.raises(BadInput, match=r"risk\.beta"):
            typed(bad)
    base = compose([], validate=False)
    first = typed(base)
    for seed in range(1, TYPED_MEMO + 1):  # enough other configs to push the first one out
        typed(compose([f"seed={seed}"], validate=False))
    again = typed(base)
    assert again == first and again is not first


def test_an_unknown_key_in_an_optional_list_of_nodes_is_named_with_its_path():
    """team.risk is `list[RiskConf] | None`: its entries are checked as RiskConf, as world.regions' are."""
    config = OmegaConf.to_container(compose(["experiment=paper_team"], validate=False))
    config["team"]["risk"] = [{"beta": 0.1}, {"beta": 0.1}, {"bta": 0.1}]
    with pytest.raises(BadInput) as err:
        typed(config)
    assert str(err.value) == (
        "key 'team.risk.2.bta': unknown key 'bta'; valid keys under 'team.risk.2': measure, beta, eta, weight, "
        "schedule, params; did you mean 'beta'?"
    )


@pytest.mark.parametrize(
    "override, where, problem",
    [
        (  # Hydra's own nodes: they said "unknown key; this node takes no new keys", naming none
            "hydra.job.chdirr=true",
            "key 'hydra.job.chdirr'",
            "unknown key 'chdirr'; valid keys under 'hydra.job': chdir, config, config_name, env_copy, env_set, id, "
            "name, num, override_dirname; did you mean 'chdir'?",
        ),
        (  # a path with '=' in it: "malformed" said nothing of quotes
            "hydra.run.dir=/x/seed=0",
            "override 'hydra.run.dir=/x/seed=0'",
            "the value holds '=', which Hydra's override grammar takes only inside quotes; write "
            "hydra.run.dir='/x/seed=0'",
        ),
    ],
)
def test_a_hydra_key_mistyped_or_unquoted_is_told_how_to_write_it(override, where, problem):
    with pytest.raises(BadInput) as err:
        compose([override])
    assert err.value.where == where and err.value.problem.startswith(problem)
