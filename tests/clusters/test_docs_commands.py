"""Every cluster command of docs/clusters.md is one the cluster tests run as written: each ```bash block that runs
a cluster launcher or a SLURM command is marked `<!-- tested: KIND -->` right before its fence (see common.py),
and each kind has a block. Needs no cluster (a second or less)."""

from __future__ import annotations

import re

from .common import KINDS, bash_blocks

SLURM = re.compile(r"\b(submitit_slurm|sbatch|srun|salloc|squeue|sacct|scontrol|scancel|sinfo)\b")
RAY = re.compile(r"hydra/launcher=ray|\bray (start|stop|status|submit)\b")
RAY_TEAM = re.compile(r"team\.backend=ray")


def test_every_cluster_block_of_the_docs_is_marked_tested():
    blocks = bash_blocks()
    untested = [
        f"docs/clusters.md:{line}: {text.strip().splitlines()[0]}"
        for line, kind, text in blocks
        if kind is None and (SLURM.search(text) or RAY.search(text) or RAY_TEAM.search(text))
    ]
    assert not untested, "cluster commands that no test runs (mark them <!-- tested: KIND -->):\n" + "\n".join(untested)
    kinds = [kind for _, kind, _ in blocks if kind is not None]
    assert set(kinds) == set(KINDS), kinds
    for line, kind, text in blocks:
        if kind == "slurm":
            assert SLURM.search(text), f"docs/clusters.md:{line} is marked slurm but runs no SLURM command"
        elif kind in ("ray-team", "ray-team-cluster"):
            assert RAY_TEAM.search(text), f"docs/clusters.md:{line} is marked {kind} but runs no ray team"
        elif kind is not None:
            assert RAY.search(text), f"docs/clusters.md:{line} is marked {kind} but runs no Ray launcher"
