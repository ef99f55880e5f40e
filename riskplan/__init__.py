"""riskplan: risk-averse sensor planning with distributed CVaR policy gradients.

Python API (the same composition, validation and files as the CLI):
    cfg = riskplan.compose(["risk=neutral", "seed=3"])
    run = riskplan.train(cfg, "outputs/runs/my_run")
    run = riskplan.load_run("outputs/runs/my_run")   # .metrics .eval .trajectories .config .summary .complete
"""

from __future__ import annotations

from riskplan.version import __version__

__all__ = ["compose", "train", "load_run", "__version__"]


def compose(overrides=()):
    """Compose and validate a config from Hydra overrides (riskplan.config.compose)."""
    from riskplan.config import compose as _compose

    return _compose(list(overrides))


def train(config, out_dir, progress: bool = True):
    """Train, evaluate and record one experiment into out_dir; returns its Run (riskplan.training.train).

    With `progress`, a live bar on a terminal or in a Jupyter notebook (nothing is printed elsewhere)."""
    from riskplan.progress import TrainingBar, silent
    from riskplan.training import train as _train

    with TrainingBar() if progress else silent() as bar:
        return _train(config, out_dir, progress=bar)


def load_run(path):
    """Load a run directory (tables rebuilt from run.mcap if needed) (riskplan.runs.load_run)."""
    from riskplan.runs import load_run as _load_run

    return _load_run(path)
