"""Measure the paper's claims over several seeds (the README's tables): python bench/paper_seeds.py [SEEDS]."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from riskplan import compose, train
from riskplan.engine.risk_measures import cvar


def row(run, robot):
    z = run.eval[run.eval.robot == robot]
    return {
        "mean": z.total_reward.mean(),
        "cvar": cvar(z.total_reward, 0.1),
        "risky": (z.risky_steps > 0).mean(),
        "safe": (z.source_reached == 0).mean(),
        "wall": run.summary["wall_time"],
    }


def main(seeds: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        print(
            "| seed | CVaR_0.1 (CVaR policy) | CVaR_0.1 (neutral) | gap | P(risky) CVaR / neutral | "
            "P(safe source) CVaR | mean CVaR / neutral | train s |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for seed in range(seeds):
            a = row(train(compose([f"seed={seed}"]), Path(tmp) / f"c{seed}"), 0)
            n = row(train(compose([f"seed={seed}", "risk=neutral"]), Path(tmp) / f"n{seed}"), 0)
            print(
                f"| {seed} | {a['cvar']:.0f} | {n['cvar']:.0f} | {a['cvar'] - n['cvar']:.0f} | "
                f"{a['risky']:.1%} / {n['risky']:.1%} | {a['safe']:.1%} | {a['mean']:.0f} / {n['mean']:.0f} | "
                f"{a['wall']:.2f} / {n['wall']:.2f} |"
            )
        print()
        print(
            "| seed | team CVaR_0.1 (average theta) | centralized CVaR_0.1 | difference | "
            "consensus error peak -> final | final / norm(theta) | team train s |"
        )
        print("|---|---|---|---|---|---|---|")
        for seed in range(seeds):
            central = train(compose([f"seed={seed}"]), Path(tmp) / f"c{seed}b")
            team = train(compose([f"seed={seed}", "experiment=paper_team"]), Path(tmp) / f"t{seed}")
            t, c = row(team, -1), row(central, 0)
            m = team.metrics[team.metrics.robot == -1]
            err = m.consensus_error.to_numpy()
            norm = float(np.hypot(m.theta_0.iloc[-1], m.theta_1.iloc[-1]))
            print(
                f"| {seed} | {t['cvar']:.0f} | {c['cvar']:.0f} | {(t['cvar'] - c['cvar']) / abs(c['cvar']):+.2%} | "
                f"{err.max():.2f} -> {err[-1]:.3f} | {err[-1] / norm:.2%} | {t['wall']:.2f} |"
            )
        print()
        print("| team.order | team.consensus_rounds | final consensus error | peak | final CVaR_0.1 (average) |")
        print("|---|---|---|---|---|")
        for order in ("combine_then_adapt", "adapt_then_combine"):
            for rounds in (1, 2, 4, 8):
                team = train(
                    compose(["experiment=paper_team", f"team.consensus_rounds={rounds}", f"team.order={order}"]),
                    Path(tmp) / f"r{order}{rounds}",
                )
                err = team.metrics[team.metrics.robot == -1].consensus_error.to_numpy()
                print(f"| {order} | {rounds} | {err[-1]:.2e} | {err.max():.2f} | {row(team, -1)['cvar']:.0f} |")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 5)
