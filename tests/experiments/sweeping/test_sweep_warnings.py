"""A sweep gives its configs' warnings once, as it plans, and leaves out a key that a variant it sweeps ignores
(team.aggregate=mean,trimmed_mean team.trim=1: trim is the trimmed mean's); its jobs give none again, in sweep.log
or their job.log, batched or job by job (run.build.build_planned)."""

from __future__ import annotations

import pytest
from support import TINY, run_cli

TEAM = ["experiment=paper_team", "team.robots=3", "team.graph=complete", "train.bootstrap=20"]
FEW = "warning: train.bootstrap=20 is too few resamples for a 95% interval"
IGNORED = "warning: team.trim=1 is ignored with team.aggregate=mean"


@pytest.mark.slow  # two small sweeps, through the console script
@pytest.mark.parametrize("how", [[], ["--jobs", "1"]], ids=["batched", "job by job"])
def test_a_sweep_gives_its_configs_warnings_once_as_it_plans(tmp_path, how):
    """In a subprocess: the warnings as the user sees them (pytest would record them instead)."""

    def sweep(folder: str, aggregate: str) -> list[str]:
        keys = [*TINY, *TEAM, f"team.aggregate={aggregate}", "team.trim=1", f"hydra.sweep.dir={folder}"]
        result = run_cli(["sweep", *keys, *how], tmp_path)
        assert result.returncode == 0, result.stderr
        logs = [tmp_path / folder / "sweep.log", *(tmp_path / folder).glob("*/job.log")]
        assert not [line for log in logs for line in log.read_text().splitlines() if "warning" in line]
        return [line for line in result.stderr.splitlines() if line.startswith("warning:")]

    swept = sweep("swept", "mean,trimmed_mean")
    assert sum(line.startswith(FEW) for line in swept) == 1 and not any(line.startswith(IGNORED) for line in swept)
    fixed = sweep("fixed", "mean")  # trim=1 for no variant that uses it
    assert sum(line.startswith(IGNORED) for line in fixed) == 1
