"""Typed schema of every config key (Hydra structured configs): a typo, a wrong type or a value outside a key's
choices fails at composition.

Every key with a fixed set of values is an Enum here, so its choices are written in one place: OmegaConf checks
them when it merges the YAML and the overrides onto the schema, and the error names them. The same dataclasses are
the engine's frozen parameters: `riskplan.config.typed.typed` turns a composed config into a RiskplanConf once,
`riskplan.config.validate.validate` checks its ranges once, and the engine reads its attributes (never raw dicts).
"""

from __future__ import annotations

from dataclasses import FrozenInstanceError, dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, OmegaConf

CONF_DIR = Path(__file__).resolve().parents[1] / "conf"  # riskplan/conf: a symlinked data dir inside the package


class Choice(str, Enum):
    """A key's allowed values: each member's name is its value, as users type it (`risk.measure=cvar`). A str, so
    it compares, formats and serialises as its value."""

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)

    @classmethod
    def names(cls) -> list[str]:
        """The allowed values, in the order they are listed."""
        return [member.value for member in cls]


# One Choice per key below: alike in shape (a docstring, then names equal to their values), each a key's own values.
class ScheduleKind(Choice):
    """risk.schedule.kind: how the gradient's CVaR level beta_l moves to risk.beta (soft risk)."""

    none = "none"
    linear = "linear"
    exponential = "exponential"


class PolicyKind(Choice):
    """policy.kind: what theta parameterises."""

    features = "features"  # a softmax over theta-weighted features of x + u (eq. 3 with policy.features)
    tabular = "tabular"  # a softmax table over (cell, move): theta is the table of logits


class Feature(Choice):
    """policy.features: what a features policy sees of each move's cell x + u."""

    signals = "signals"  # the M source signals s^j(x + u) of eq. (1): the paper's policy
    risky = "risky"  # 1 when x + u lies in a risky region
    stay = "stay"  # 1 for the stay move


class Aggregate(Choice):
    """team.aggregate: how a robot combines the values it receives (Byzantine-resilient rules drop extremes)."""

    mean = "mean"  # the paper's weighted mix, eq. (14)
    trimmed_mean = "trimmed_mean"  # drop the trim largest and trim smallest received values per coordinate
    median = "median"  # the coordinate-wise median of its own and the received values
    wmsr = "wmsr"  # W-MSR: drop up to trim received values above and below its own, per coordinate


class Backend(Choice):
    """team.backend: where the robots run."""

    simulated = "simulated"  # rows of one array stepped in lockstep, delays and drops simulated (deterministic)
    ray = "ray"  # each robot a Ray actor with its own stream, messages through Ray, real asynchrony


class FaultKind(Choice):
    """team.faults.N.kind."""

    crash = "crash"  # stops sending
    stuck = "stuck"  # keeps sending the theta it had
    byzantine = "byzantine"  # sends arbitrary theta: a fixed value, or seeded noise of a given scale


class MapUnknown(Choice):
    """world.map_unknown: what the map's unknown pixels (neither occupied nor free) become."""

    obstacle = "obstacle"  # cells that cannot be entered, as nav2's planners treat unknown space by default
    free = "free"  # free cells
    risky = "risky"  # a risky region `unknown`, paid as the first region with risky: true


class MotionKind(Choice):
    """world.sources.N.motion.kind."""

    static = "static"
    random_walk = "random_walk"


class Graph(Choice):
    """team.graph: the communication topology."""

    line = "line"
    ring = "ring"
    star = "star"
    complete = "complete"
    grid = "grid"
    random_geometric = "random_geometric"
    edges = "edges"


class WeightRule(Choice):
    """team.weights: the rule that turns the graph into the mixing matrix A."""

    metropolis = "metropolis"
    max_degree = "max_degree"
    lazy = "lazy"
    matrix = "matrix"


class Stale(Choice):
    """team.stale: what a link mixes in a slot where nothing new arrived."""

    arrival = "arrival"
    latest = "latest"


class Order(Choice):
    """team.order: how consensus and the gradient step combine."""

    combine_then_adapt = "combine_then_adapt"
    adapt_then_combine = "adapt_then_combine"
    gradient_tracking = "gradient_tracking"


class Device(Choice):
    """engine.device: where a run's episodes run; the numbers are the same on both (riskplan.engine.cuda_rollout)."""

    cpu = "cpu"  # the numba kernel on every core
    cuda = "cuda"  # an NVIDIA GPU through numba-cuda (pip install 'riskplan[cuda]')


class Frozen:
    """Instances cannot change once built. Not `dataclass(frozen=True)`: OmegaConf turns those into read-only nodes,
    which Hydra cannot merge the YAML and the overrides into."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in self.__dict__:
            raise FrozenInstanceError(f"cannot assign to field '{name}': the config is frozen")
        object.__setattr__(self, name, value)

    def __delattr__(self, name: str) -> None:
        raise FrozenInstanceError(f"cannot delete field '{name}': the config is frozen")


@dataclass
class ScheduleConf(Frozen):
    """Soft risk (CeSoR): the CVaR gradient at level beta_l, from `start` to risk.beta over `iterations`, then beta.

    kind: none (the paper: beta_l = beta throughout) | linear | exponential (geometric interpolation).
    """

    kind: ScheduleKind = ScheduleKind.none
    start: float = 1.0
    iterations: int = 100


@dataclass
class RiskConf(Frozen):
    """The objective: `cvar` optimises CVaR_beta, `neutral` the mean; beta is also the reporting level.

    measure: a registered measure's name, checked when the run is built (riskplan.engine.measures.registry): cvar
    (Algorithm 1, eq. 9), neutral (the mean, eq. 4), wang, mean_cvar, entropic, or one an installed package adds.
    """

    # `valid`: what a message says the key takes, where its type cannot (the registry checks the name at build)
    measure: str = field(
        default="cvar",
        metadata={"valid": "a measure's name: cvar, neutral, wang, mean_cvar, entropic or one from a package"},
    )
    beta: float = 0.1  # the CVaR level: optimised by cvar and mean_cvar, and the level CVaR is reported at
    eta: float = 0.5  # wang: the distortion's shift (in standard deviations); entropic: aversion per unit of reward
    weight: float = 0.5  # mean_cvar: lambda, the weight of CVaR_beta against the mean, in [0, 1]
    schedule: ScheduleConf = field(default_factory=ScheduleConf)
    params: dict[str, float] = field(default_factory=dict)  # a package's measure's parameters: risk.params.KEY=VALUE


@dataclass
class PolicyConf(Frozen):
    """The softmax policy mu_theta(u | x) (eqs. 2-3): theta weights features of x + u, or is a table of logits."""

    kind: PolicyKind = PolicyKind.features
    features: list[Feature] = field(default_factory=lambda: [Feature.signals])


@dataclass
class StepSizeConf(Frozen):
    """eps_l = initial / (1 + l/decay)^power; Assumption 6 holds for power in (0.5, 1]."""

    initial: float = 0.1
    decay: float = 50.0
    power: float = 1.0


@dataclass
class TrainConf(Frozen):
    """Policy-gradient loop settings."""

    iterations: int = 200
    samples: int = 6000
    samples_growth: float = 0.0  # W_l = ceil(samples * (1 + l)^samples_growth); > 0 makes W_l -> inf (Theorem 1)
    step_size: StepSizeConf = field(default_factory=StepSizeConf)
    theta0: list[float] = field(default_factory=lambda: [20.0, 20.0])
    baseline: bool = True  # mean baseline in the risk-neutral gradient
    eval_episodes: int = 100_000
    paths: int = 20  # sampled paths per policy and robot in trajectories.parquet
    checkpoint_every: int = 10
    bootstrap: int = 1000  # resamples for the summary's 95% intervals


@dataclass
class MotionConf(Frozen):
    """Source motion: `static`, or `random_walk` moving to a random 4-neighbour with probability `prob` per step."""

    kind: MotionKind = MotionKind.static
    prob: float = 0.0


@dataclass
class SourceConf(Frozen):
    """One source: Gaussian signal eq. (1) and a random reward paid on reaching it."""

    position: Any = None  # [x, y] in cells; on a map world also {metres: [x, y]} (None: a mapping can replace it)
    covariance: list[Any] = field(default_factory=lambda: [[16.0, 0.0], [0.0, 16.0]])  # [[a, b], [b, c]], SPD
    scale: float | None = None  # w; None means 2*pi*sqrt(det covariance), so the signal peaks at 1
    reward: Any = 0.0
    motion: MotionConf = field(default_factory=MotionConf)
    name: str = ""


NO_SOURCE = "none"  # the results' name for the episodes that reach no source (summary.json's source_reached)


def source_names(sources: list[SourceConf]) -> list[str]:
    """Each source's name in the results: its own, or source_<j>."""
    return [source.name or f"source_{j}" for j, source in enumerate(sources)]


@dataclass
class RegionConf(Frozen):
    """A named cell set with a per-step reward; give exactly one of rect, halfplane, cells, mask."""

    name: str = ""
    reward: Any = 0.0
    risky: bool = False
    rect: Any = None  # [x0, y0, x1, y1], inclusive corners; on a map world also {metres: [x0, y0, x1, y1]}
    halfplane: list[float] | None = None  # [a, b, c]: the cells with a*x + b*y > c ("y > x" is [-1, 1, 0])
    cells: list[list[int]] | None = None  # [[x, y], ...]
    mask: str | None = None  # an image the map's size: its dark pixels (relative to world.map's folder)


@dataclass
class WorldConf(Frozen):
    """Grid world of paper Section II/V."""

    size: list[int] = field(default_factory=lambda: [12, 12])
    start: Any = field(default_factory=lambda: [0, 0])  # [x, y] in cells; on a map world also {metres: [x, y]}
    horizon: int = 20
    stop_at_source: bool = True
    obstacles: list[list[int]] = field(default_factory=list)
    sources: list[SourceConf] = field(default_factory=list)
    regions: list[RegionConf] = field(default_factory=list)
    map: str | None = None  # a ROS map YAML (map_server): the grid's size and obstacles come from its image
    map_unknown: MapUnknown = MapUnknown.obstacle  # what the map's unknown pixels become
    map_cell: int = 1  # k: one cell is k x k of the map's pixels (occupied if any of them is)


@dataclass
class DelayConf(Frozen):
    """Message delays in iterations: uniform on 0..max (B0 of Assumption 5)."""

    max: int = 0


@dataclass
class SwitchingConf(Frozen):
    """Time-varying graph: each link is up with probability `up` per iteration, jointly connected within `window`."""

    enabled: bool = False
    up: float = 0.8
    window: int = 5


@dataclass
class TeamConf(Frozen):
    """Robots and their communication graph (paper Section IV); robots=1 is a centralized run."""

    robots: int = 1
    graph: Graph = Graph.line
    directed: bool = False
    edges: list[list[int]] | None = None  # with graph=edges: [[i, j], ...], 0-based, j sends to i if directed
    radius: float = 0.5  # random_geometric link radius in the unit square
    resample: int = 100  # random_geometric redraws before giving up on strong connectivity
    weights: WeightRule = WeightRule.metropolis
    matrix: list[Any] | None = None  # with weights=matrix: the N x N row-stochastic A
    diagonal: list[Any] | None = None  # optional per-parameter weights a^{ij}_m, shape N x N x M
    delay: DelayConf = field(default_factory=DelayConf)
    drop: float = 0.0
    max_gap: int = 10  # B of Assumption 5: a link delivers at least once every max_gap iterations
    stale: Stale = Stale.arrival  # arrival (paper eq. 14) | latest (the newest value received from each neighbour)
    consensus_rounds: int = 1
    order: Order = Order.combine_then_adapt
    starts: list[Any] | None = None  # per-robot start cells ([x, y], or {metres: [x, y]}); default world.start for all
    risk: list[RiskConf] | None = None  # per-robot risk nodes; default the top-level risk for all
    faults: list[Any] = field(default_factory=list)  # [{robot, kind, from, value | scale}], see config.faults
    aggregate: Aggregate = Aggregate.mean
    trim: int = 0  # F: the received values trimmed_mean and wmsr drop at each end, per coordinate
    backend: Backend = Backend.simulated
    staleness: int = 2  # ray: the oldest neighbour message (in iterations) a robot mixes before it waits for one
    speeds: list[float] | None = None  # ray: per-robot slow-down factors >= 1 (4 = four times slower); null: all 1
    address: str | None = None  # ray: an existing cluster (auto, or host:port); null: a local Ray instance
    switching: SwitchingConf = field(default_factory=SwitchingConf)


@dataclass
class EngineConf(Frozen):
    """How the engine computes, never what: the same config and seed give the same numbers whatever these are, so
    they enter neither a run's identity (riskplan.experiments.sweep_worker.run_identity) nor a sweep's folders."""

    device: Device = Device.cpu


@dataclass
class RiskplanConf(Frozen):
    """The whole experiment."""

    seed: int = 0
    experiment: str = "paper_single"
    risk: RiskConf = field(default_factory=RiskConf)
    policy: PolicyConf = field(default_factory=PolicyConf)
    train: TrainConf = field(default_factory=TrainConf)
    world: WorldConf = field(default_factory=WorldConf)
    team: TeamConf = field(default_factory=TeamConf)
    engine: EngineConf = field(default_factory=EngineConf)


def structured() -> DictConfig:
    """The schema as a typed OmegaConf node, for merging a config onto it. risk.params takes any key (its measure
    names its parameters, checked when the run is built), so `risk.params.gamma=0.5` needs no `+`."""
    node = OmegaConf.structured(RiskplanConf)
    OmegaConf.set_struct(node.risk.params, False)
    return node


def register() -> None:
    """Register the schema so conf/config.yaml can extend it; once a process (36 ms a time, and Hydra copies the
    stored node on every load, so one registration serves every composition)."""
    store = ConfigStore.instance()
    if "riskplan_schema.yaml" not in store.repo:
        store.store(name="riskplan_schema", node=structured())
