"""The experiments of `riskplan reproduce`, one record each (the sweep it runs into its own folder), and the
report's studies beyond the paper (STUDIES), each with the folders that hold its runs. `reproduction` runs the
experiments in this order; the report finds a study's runs in its folders (`reporting.collect`) and gives it a
section with its figure (`reporting.figures.figure_registry`, `study=`), its table and its text; the registry-wide
tests (`tests/experiments/test_study_registry.py`) test every record. A new sweep of reproduce is one record in
EXPERIMENTS (docs/extending.md).
"""

from __future__ import annotations

from typing import NamedTuple


class Experiment(NamedTuple):
    """One sweep of reproduce, in its own folder."""

    folder: str
    title: str  # what it reproduces, in the plan and reproduce.json
    overrides: list[str]  # without the seeds
    seeds: int | None  # at most this many seeds (None: every seed asked for)


# The report's studies beyond the paper: name -> (its title, the folders of EXPERIMENTS that hold its runs); each
# is a section of the report, with its figure (figure_registry: study=name), its table and its text
STUDIES = {
    "measures": ("Risk measures", ("measures",)),
    "policies": ("Policies that see more", ("policies", "tabular")),
    "hetero_team": ("A heterogeneous team", ("hetero_team", "hetero_central")),
    "faults": ("A Byzantine robot and resilient consensus", ("faults", "faults_free")),
    "floor_plan": ("A floor plan with a watched corridor", ("floor_plan",)),
}

STUDY_SEEDS = 5  # the studies beyond the paper: at most 5 seeds (2 with --quick)
# A heterogeneous team: 8 robots from the corners and edge midpoints of the 12x12 world (ring neighbours are
# neighbouring cells), the paper's W_i = 2000, and a constant step (eq. 14's O(eps) floor shows at a fixed eps)
HETERO_STARTS = "[[0,0],[5,0],[11,0],[11,5],[11,11],[5,11],[0,11],[0,5]]"
HETERO_TEAM = [
    "experiment=paper_team",
    "team.robots=8",
    f"team.starts={HETERO_STARTS}",
    "train.step_size.power=0",
    "train.step_size.initial=0.05",
]
# Faults: 7 robots on a complete graph (4-robust, so F = 1 is within the resilience condition); robot 6 sends
# theta = (-10, 40) from the first iteration, next to the risk-neutral optimum that heads for the risky source
FAULT_TEAM = ["experiment=paper_team", "team.robots=7", "team.graph=complete"]
BYZANTINE = "team.faults=[{robot:6,kind:byzantine,from:0,value:[-10,40]}]"
EXPERIMENTS = (
    Experiment(
        "single",
        "Figs. 1-2: one robot, risk-neutral vs CVaR (W = 6000)",
        ["experiment=paper_single", "risk=neutral,cvar"],
        None,
    ),
    Experiment(
        "team",
        "Figs. 3-4: three robots on a line graph (W_i = 2000), vs the centralized CVaR runs of single/",
        ["experiment=paper_team"],
        None,
    ),
    # theta0 = 0 falls into the landscape's other optimum: wander, reaching no source; two seeds show it
    Experiment(
        "wander",
        "The landscape's local optimum: CVaR from theta0 = (0, 0), which wanders and reaches no source",
        ["experiment=paper_single", "train.theta0=[0,0]"],
        2,
    ),
    # soft risk (CeSoR): the same start, the gradient's CVaR level falling linearly from 1 to beta; vs wander/
    Experiment(
        "soft_risk",
        "Beyond the paper: soft risk from theta0 = (0, 0), CVaR level linear from 1 to beta (vs wander/)",
        ["experiment=paper_single", "train.theta0=[0,0]", "risk.schedule.kind=linear"],
        2,
    ),
    # with single/'s beta = 0.1 runs, the report's risk frontier (beta = 1 is the mean, through the CVaR gradient)
    Experiment(
        "frontier",
        "Beyond the paper: the risk frontier, CVaR policies at beta = 0.05, 0.2, 0.5, 1",
        ["experiment=paper_single", "risk.beta=0.05,0.2,0.5,1.0"],
        2,
    ),
    # the studies beyond the paper (the report draws each from its own folders: STUDIES)
    Experiment(
        "measures",
        "Beyond the paper: risk measures, each at its group defaults (conf/risk/), one robot in the paper world",
        ["experiment=paper_single", "risk=cvar,neutral,wang,mean_cvar,entropic"],
        STUDY_SEEDS,
    ),
    Experiment(
        "policies",
        "Beyond the paper: from theta0 = (0, 0), the paper's policy and one that also sees the risky region",
        ["experiment=paper_single", "train.theta0=[0,0]", "policy.features=[signals],[signals,risky]"],
        STUDY_SEEDS,
    ),
    Experiment(
        "tabular",
        "Beyond the paper: from theta0 = (0, 0), a tabular policy (a logit per cell and move; the uniform policy)",
        ["experiment=paper_single", "train.theta0=[0,0]", "policy.kind=tabular"],
        STUDY_SEEDS,
    ),
    Experiment(
        "hetero_team",
        "Beyond the paper: 8 robots from 8 start cells on a ring, constant step: gradient tracking vs eq. (14)",
        [*HETERO_TEAM, "team.graph=ring", "team.order=gradient_tracking,combine_then_adapt"],
        STUDY_SEEDS,
    ),
    Experiment(
        "hetero_central",
        "Beyond the paper: the same 8 robots on a complete graph averaging exactly (the centralized run)",
        [*HETERO_TEAM, "team.graph=complete", "team.weights=max_degree", "team.order=adapt_then_combine"],
        STUDY_SEEDS,
    ),
    Experiment(
        "faults",
        "Beyond the paper: 7 robots on a complete graph, robot 6 Byzantine: the mean vs a trimmed mean (F = 1)",
        [*FAULT_TEAM, BYZANTINE, "team.aggregate=mean,trimmed_mean", "team.trim=1"],
        STUDY_SEEDS,
    ),
    Experiment(
        "faults_free",
        "Beyond the paper: the same 7 robots without the fault (the reference)",
        FAULT_TEAM,
        STUDY_SEEDS,
    ),
    Experiment(
        "floor_plan",
        "Beyond the paper: a floor plan from ROS map files, a corridor watched by an adversary: risk-neutral vs CVaR",
        ["experiment=floor_plan", "risk=neutral,cvar"],
        STUDY_SEEDS,
    ),
)
