"""Everything a run derives from its config, built (and so validated) once at the top: the PureJaxRL way."""

from __future__ import annotations

import math
import re

import numpy as np
from omegaconf import DictConfig

from riskplan.config.schema import Device, RiskplanConf
from riskplan.config.typed import as_dict, typed
from riskplan.config.validate import validate
from riskplan.engine.measures.registry import check_risk_nodes
from riskplan.engine.policy import Policy, make_policy
from riskplan.engine.rollout import make_kernel
from riskplan.engine.step import Setup
from riskplan.engine.team.mixer import Mixer
from riskplan.engine.team.network import build_network
from riskplan.engine.world import World, build_world, grid_size
from riskplan.run import budget, maps
from riskplan.util.checks import require
from riskplan.util.errors import BadInput


def build_setup(cfg: DictConfig | dict | RiskplanConf, needs_ray: bool = True) -> Setup:
    """Type and validate the config once, then build the run's objects; raises BadInput on the first problem
    (`needs_ray`: see config.validate.validate)."""
    params = typed(cfg)  # types, unknown keys, Choices, interpolations: the frozen config everything below reads
    validate(params, needs_ray)  # every range, once
    check_risk_nodes(params)  # each risk node's measure (built in or a package's) and its parameters
    check_device(params)  # engine.device=cuda: a GPU numba-cuda can use
    # Sizes first: nothing big is allocated before the memory and time estimates pass (a map's from its header).
    found = maps.read_map(params.world)
    width, height = grid_size(params.world.size) if found is None else found.cells
    check_sizes(params, found, width, height)
    layout = None if found is None else maps.load_layout(params.world, found)
    starts = None if params.team.starts is None else [list(s) for s in params.team.starts]
    world = build_world(params.world, starts, layout)
    policy = make_policy(world, params.policy.kind, params.policy.features)
    theta0 = initial_theta(world, policy, list(params.train.theta0))
    network = build_network(params.team, policy.size, params.seed)
    budget.check(budget.sizes_of(params, world.width, world.height, world.sources, network.robots))  # before the Mixer
    return Setup(
        params=params,
        config=as_dict(params),
        world=world,
        kernel=make_kernel(world, policy),
        network=network,
        mixer=Mixer(network, params.team, params.seed),
        theta0=theta0,
        policy=policy,
        theta_names=policy.names,
    )


def check_device(params: RiskplanConf) -> None:
    """engine.device=cuda needs a GPU that numba-cuda can use (the package itself is checked with the extras, in
    validate): BadInput naming engine.device=cuda, when the run is built, so check and sweep refuse it too."""
    if params.engine.device != Device.cuda:
        return
    try:
        from riskplan.engine.cuda_rollout import check_gpu  # optional: numba-cuda, for engine.device=cuda alone
    except Exception as err:  # a numba-cuda that fails at import (0.30.4 with numpy 2.5, which lacks np.row_stack)
        raise BadInput(
            "engine.device=cuda",
            f"numba-cuda fails to import ({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
            f"pip install 'riskplan[cuda]', which pins a numpy it supports",
        ) from None
    check_gpu()


def check_sizes(params: RiskplanConf, found: maps.MapFile | None, width: int, height: int) -> None:
    """The memory and time estimates of the grid before it is built; a map too large is named as world.map."""
    try:
        budget.check(budget.sizes_of(params, width, height, len(params.world.sources), params.team.robots))
    except BadInput as err:
        if found is None or err.where != "world.size":
            raise
        problem = re.sub(r"^got [^;]*; ", "", err.problem)
        problem = problem.replace("lower it, or", "give a smaller map or a larger world.map_cell, or")
        raise BadInput(
            "world.map",
            f"{found.shown} is {found.pixels[0]}x{found.pixels[1]} pixels, a {width}x{height} grid at "
            f"world.map_cell={found.cell}: {problem}",
        ) from None


def initial_theta(world: World, policy: Policy, given: list) -> np.ndarray:
    """theta_0 from train.theta0, which lists the weights of `policy.seed_names` in that order (the features in the
    order of policy.features; without signals, the extras come first).

    Entries left off at the end start at 0 (the paper's [20, 20] with policy.features=[signals, risky] starts the
    risky weight at 0); more entries than weights is BadInput. A features policy starts at these weights, a tabular
    one at the logits they give (riskplan.engine.policy.Policy.initial).
    """
    names = policy.seed_names
    count = len(names)
    shown = ", ".join(names) if count <= 8 else f"{', '.join(names[:8])}, ..."
    what = "signal weights to seed its table" if policy.tabular else "parameters"
    require(
        len(given) <= count,
        "train.theta0",
        f"got {given}; the policy has {count} {what} ({shown}); give at most {count} numbers",
    )
    weights = np.array(given, dtype=float)
    require(
        bool(np.all(np.isfinite(weights))),
        "train.theta0",
        f"got {given}; expected finite numbers, one per parameter ({shown})",
    )
    weights = np.concatenate([weights, np.zeros(count - len(weights))])
    require(
        math.isfinite(policy.seed_bound(weights)),
        "train.theta0",
        f"got {given}; the softmax logits theta . signal overflow to infinity; give smaller values",
    )
    return policy.initial(world, weights)
