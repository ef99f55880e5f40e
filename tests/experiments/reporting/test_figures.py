"""Report figures drawn from a few tiny runs (riskplan.experiments.reporting.figures): the consensus error of each
order of consensus and gradient steps. The figures of the paper are checked on a small sweep in
test_report_contents.py."""

from __future__ import annotations

import pytest
from support import TINY

from riskplan import compose, train

TEAM = ["experiment=paper_team", *TINY]


@pytest.mark.slow  # over half a second (the quick tier stays under a minute)
def test_report_draws_the_consensus_error_of_each_order(tmp_path):
    from riskplan.experiments.reporting.collect import collect
    from riskplan.experiments.reporting.figures import fig_orders

    for order in ("combine_then_adapt", "gradient_tracking"):
        train(compose([*TEAM, f"team.order={order}"]), tmp_path / order)
    spec = fig_orders(collect([tmp_path]))
    assert not isinstance(spec, str), spec
    assert spec.figure.axes[0].get_legend() is None  # the legend sits outside the panels
    labels = [t.get_text() for t in spec.figure.legends[0].get_texts()]
    assert labels == ["combine_then_adapt", "gradient_tracking"]
    assert fig_orders(collect([tmp_path / "gradient_tracking"])) == "no team runs that differ in team.order"
