"""The Hydra task (riskplan.experiments.hydra_app): Hydra's repeat compositions are skipped only inside a launch."""

from __future__ import annotations


def test_hydras_repeat_compositions_are_skipped_only_inside_a_launch():
    """run_hydra skips Hydra's mode-probing composition and the basic sweeper's second composition of every job
    (the planner composed them); both are Hydra's own again afterwards, and the optimising sweepers keep theirs."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra._internal.hydra import Hydra
    from hydra.plugins.sweeper import Sweeper
    from hydra.types import RunMode

    from riskplan.experiments.hydra_app import _without_repeat_compositions

    get_mode = Hydra.get_mode
    with _without_repeat_compositions(multirun=True):
        assert Hydra.get_mode(None, "config", ["seed=0,1"]) is RunMode.MULTIRUN
        assert BasicSweeper.validate_batch_is_legal(None, [["seed=not-a-number"]]) is None
        assert Sweeper.validate_batch_is_legal is not BasicSweeper.validate_batch_is_legal
    with _without_repeat_compositions(multirun=False):
        assert Hydra.get_mode(None, "config", []) is RunMode.RUN
    assert Hydra.get_mode is get_mode
    assert "validate_batch_is_legal" not in BasicSweeper.__dict__
