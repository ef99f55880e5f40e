"""Measure team.backend=ray for the docs: python bench/ray_backend.py [backends|scaling|target|cluster|all] [--out DIR]

- backends: paper_team on the ray backend against the simulated one, seeds 0-4 (summary.json `cvar`, the team
  CVaR_0.1 of theta-bar on the evaluation episodes); the target is within 2%.
- scaling: robots per core on this machine: paper_team's world on a ring of 1, 2, 4, 8, 16 robots on a local Ray
  instance, iterations/s per robot (wall clock, and counting only the robot's own computing).
- target: wall-clock time until the team's training CVaR_0.1 (the network average row, pooled episodes, a 5-iteration
  moving average) first reaches a target, against robots (1, 4, 16).
- cluster: a two-node Ray cluster on this machine (tests/clusters/ray_cluster.py), 16 robots on a ring, robot 5 four
  times slower, team.staleness=2: does the team converge, and how stale is what the slow robot mixes.

Each prints a Markdown table and writes its numbers to DIR/<name>.json (DIR: outputs/bench-ray-team). The runs are
kept in DIR/runs/, so the figures can be redrawn from them (`riskplan report` reads them like any run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from riskplan import compose, train
from riskplan.run.log_reader import read_log

ROOT = Path(__file__).resolve().parents[1]
QUICK_EVAL = ["train.eval_episodes=20000", "train.bootstrap=200", "train.paths=2"]


def run_once(out: Path, overrides: list[str]) -> dict:
    """Train one run (again only if it is not finished in `out`); its summary, metrics and ray metadata."""
    if not (out / "summary.json").is_file():
        if out.exists():
            import shutil

            shutil.rmtree(out)
        started = time.monotonic()
        train(compose(overrides), out, progress=False)
        (out / "elapsed.json").write_text(json.dumps({"seconds": time.monotonic() - started}))
    import pandas as pd

    summary = json.loads((out / "summary.json").read_text())
    metadata = read_log(out / "run.mcap").metadata
    elapsed = json.loads((out / "elapsed.json").read_text())["seconds"] if (out / "elapsed.json").is_file() else None
    return {
        "summary": summary,
        "metrics": pd.read_parquet(out / "metrics.parquet"),
        "ray": metadata.get("ray_team"),
        "ray_end": metadata.get("ray_team_end"),
        "elapsed": elapsed,
    }


def backends(out: Path, seeds: int = 5) -> dict:
    """paper_team, ray against simulated, per seed: CVaR_0.1 of theta-bar and its relative difference."""
    rows = []
    for seed in range(seeds):
        got = {}
        for backend in ("simulated", "ray"):
            run = run_once(
                out / "runs" / f"backends_{backend}_{seed}",
                ["experiment=paper_team", f"seed={seed}", f"team.backend={backend}"],
            )
            got[backend] = run
        sim, ray = got["simulated"]["summary"], got["ray"]["summary"]
        stale = got["ray"]["metrics"].staleness.dropna()
        rows.append(
            {
                "seed": seed,
                "cvar_simulated": sim["cvar"]["value"],
                "cvar_ray": ray["cvar"]["value"],
                "cvar_ray_low": ray["cvar"]["low"],
                "cvar_ray_high": ray["cvar"]["high"],
                "relative": ray["cvar"]["value"] / sim["cvar"]["value"] - 1,
                "train_s_simulated": sim["wall_time"],
                "train_s_ray": ray["wall_time"],
                "elapsed_s_ray": got["ray"]["elapsed"],
                "max_staleness": float(stale.max()) if len(stale) else None,
            }
        )
    print(
        "| seed | CVaR_0.1 simulated | CVaR_0.1 ray [95% CI] | ray / simulated - 1 | train s sim / ray | max staleness |"
    )
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['seed']} | {r['cvar_simulated']:.1f} | {r['cvar_ray']:.1f} [{r['cvar_ray_low']:.1f}, "
            f"{r['cvar_ray_high']:.1f}] | {r['relative']:+.2%} | {r['train_s_simulated']:.1f} / {r['train_s_ray']:.1f} "
            f"| {r['max_staleness']:.0f} |"
        )
    worst = max(abs(r["relative"]) for r in rows)
    mean_sim = np.mean([r["cvar_simulated"] for r in rows])
    mean_ray = np.mean([r["cvar_ray"] for r in rows])
    print(
        f"mean over seeds: simulated {mean_sim:.1f}, ray {mean_ray:.1f} ({mean_ray / mean_sim - 1:+.2%}); "
        f"largest |difference| {worst:.2%} (target 2%)"
    )
    return {"rows": rows, "mean_simulated": mean_sim, "mean_ray": mean_ray, "largest_relative": worst}


def ring(robots: int) -> list[str]:
    return [f"team.robots={robots}"] + (
        ["team.graph=ring"] if robots > 2 else ["team.graph=line"] if robots == 2 else []
    )


def scaling(out: Path, counts=(1, 2, 4, 8, 16), iterations: int = 40, samples: int = 2000) -> dict:
    """Iterations per second per robot against robots on this machine (a local Ray instance)."""
    rows = []
    for n in counts:
        run = run_once(
            out / "runs" / f"scaling_{n}_{samples}",
            [
                "experiment=paper_team",
                "team.backend=ray",
                *ring(n),
                f"train.iterations={iterations}",
                f"train.samples={samples}",
                *QUICK_EVAL,
            ],
        )
        timing = run["ray_end"]["robots"]
        train_s = run["ray_end"]["train_seconds"]
        per_robot = [t["iterations"] / t["seconds"] for t in timing]
        computing = [t["iterations"] / t["compute"] for t in timing]
        rows.append(
            {
                "robots": n,
                "cores": os.cpu_count(),
                "train_s": train_s,
                "startup_s": run["ray_end"].get("startup_seconds"),
                "team_iterations_per_s": iterations / train_s,
                "iterations_per_s_per_robot": float(np.mean(per_robot)),
                "compute_only_iterations_per_s": float(np.mean(computing)),
                "waiting_fraction": float(np.mean([t["wait"] / t["seconds"] for t in timing])),
                "episodes_per_s": n * samples * iterations / train_s,
            }
        )
    base = rows[0]["iterations_per_s_per_robot"]
    print(
        "| robots | robots per core | iterations/s per robot | efficiency vs 1 robot | robot's own compute "
        "iterations/s | waiting | team episodes/s | start-up s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['robots']} | {r['robots'] / r['cores']:.1f} | {r['iterations_per_s_per_robot']:.1f} | "
            f"{r['iterations_per_s_per_robot'] / base:.0%} | {r['compute_only_iterations_per_s']:.1f} | "
            f"{r['waiting_fraction']:.0%} | {r['episodes_per_s']:.0f} | {r['startup_s']:.1f} |"
        )
    return {"rows": rows}


def time_to_target(metrics, target: float, window: int = 5) -> tuple[float | None, int | None]:
    """Seconds (the slowest robot's cumulative time) and iteration at which the moving average of the team's
    training CVaR first reaches `target`."""
    team = metrics[metrics.robot == (-1 if (metrics.robot == -1).any() else 0)].set_index("iteration").cvar
    smooth = team.rolling(window, min_periods=window).mean()
    hit = smooth[smooth >= target]
    if not len(hit):
        return None, None
    l = int(hit.index[0])
    robots = metrics[metrics.robot >= 0]
    elapsed = robots[robots.iteration <= l].groupby("robot").seconds.sum().max()
    return float(elapsed), l


def target(out: Path, counts=(1, 4, 16), value: float = 1380.0, iterations: int = 120, samples: int = 1000) -> dict:
    """Wall-clock time to a training CVaR of `value` against robots (a local Ray instance, W per robot fixed)."""
    rows = []
    for n in counts:
        run = run_once(
            out / "runs" / f"target_{n}",
            [
                "experiment=paper_team",
                "team.backend=ray",
                *ring(n),
                f"train.iterations={iterations}",
                f"train.samples={samples}",
                *QUICK_EVAL,
            ],
        )
        seconds, l = time_to_target(run["metrics"], value)
        rows.append(
            {
                "robots": n,
                "target": value,
                "seconds": seconds,
                "iteration": l,
                "train_s": run["ray_end"]["train_seconds"],
                "final_cvar": run["summary"]["cvar"]["value"],
            }
        )
    print(
        f"| robots | iterations to training CVaR >= {value:.0f} | wall-clock s to it | train s ({iterations} "
        f"iterations) | final CVaR_0.1 of theta-bar |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        hit = "not reached" if r["seconds"] is None else f"{r['seconds']:.3f}"
        print(f"| {r['robots']} | {r['iteration']} | {hit} | {r['train_s']:.1f} | {r['final_cvar']:.1f} |")
    return {"rows": rows}


def cluster(out: Path, robots: int = 16, slow: int = 5, iterations: int = 40, samples: int = 200) -> dict:
    """16 robots on a two-node local Ray cluster, one four times slower, team.staleness=2."""
    sys.path.insert(0, str(ROOT / "tests" / "clusters"))
    from ray_cluster import RayCluster

    speeds = [1.0] * robots
    speeds[slow] = 4.0
    with RayCluster(num_nodes=2, cpus_per_node=1) as running:
        saved = running.apply_driver_env()
        try:
            run = run_once(
                out / "runs" / "cluster_16",
                [
                    "experiment=paper_team",
                    "team.backend=ray",
                    f"team.address={running.address}",
                    *ring(robots),
                    f"team.speeds=[{','.join(map(str, speeds))}]",
                    "team.staleness=2",
                    f"train.iterations={iterations}",
                    f"train.samples={samples}",
                    *QUICK_EVAL,
                ],
            )
        finally:
            running.restore_env(saved)
    metrics = run["metrics"]
    error = metrics[metrics.robot == -1].set_index("iteration").consensus_error
    robots_rows = metrics[metrics.robot >= 0]
    slow_rows = robots_rows[robots_rows.robot == slow]
    timing = run["ray_end"]["robots"]
    result = {
        "robots": robots,
        "nodes": len(run["ray"]["nodes"]),
        "robots_per_node": {
            node: sum(r["node_id"] == node for r in run["ray"]["robots"]) for node in run["ray"]["nodes"]
        },
        "consensus_error_early_max": float(error.iloc[1:20].max()),
        "consensus_error_late_mean": float(error.iloc[-10:].mean()),
        "max_staleness_all": float(robots_rows.staleness.max()),
        "max_staleness_slow": float(slow_rows.staleness.max()),
        "mean_staleness_slow": float(slow_rows.staleness.mean()),
        "mean_staleness_fast": float(robots_rows[robots_rows.robot != slow].staleness.mean()),
        "slow_waiting_fraction": timing[slow]["wait"] / timing[slow]["seconds"],
        "fast_waiting_fraction": float(np.mean([t["wait"] / t["seconds"] for i, t in enumerate(timing) if i != slow])),
        "train_s": run["ray_end"]["train_seconds"],
        "startup_s": run["ray_end"].get("startup_seconds"),
        "elapsed_s": run["elapsed"],
        "cvar": run["summary"]["cvar"]["value"],
    }
    print(
        "| robots | nodes | consensus error (max, iterations 1-19 -> mean, last 10) | max staleness (all / slow "
        "robot) | mean staleness (fast / slow) | waiting (fast / slow) | train s | CVaR_0.1 |"
    )
    print("|---|---|---|---|---|---|---|---|")
    r = result
    print(
        f"| {r['robots']} | {r['nodes']} | {r['consensus_error_early_max']:.2f} -> {r['consensus_error_late_mean']:.2f}"
        f" | {r['max_staleness_all']:.0f} / {r['max_staleness_slow']:.0f} | {r['mean_staleness_fast']:.2f} / "
        f"{r['mean_staleness_slow']:.2f} | {r['fast_waiting_fraction']:.0%} / {r['slow_waiting_fraction']:.0%} | "
        f"{r['train_s']:.1f} | {r['cvar']:.1f} |"
    )
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", nargs="?", default="all", choices=["backends", "scaling", "target", "cluster", "all"])
    parser.add_argument("--out", default="outputs/bench-ray-team")
    parser.add_argument("--samples", type=int, default=None, help="scaling: W per robot (default 2000)")
    args = parser.parse_args()
    out = Path(args.out)
    (out / "runs").mkdir(parents=True, exist_ok=True)
    jobs = {"backends": backends, "scaling": scaling, "target": target, "cluster": cluster}
    for name in jobs if args.what == "all" else [args.what]:
        started = time.monotonic()
        print(f"\n## {name}")
        extra = {"samples": args.samples} if name == "scaling" and args.samples else {}
        result = jobs[name](out, **extra)
        if extra:
            name = f"{name}_{args.samples}"
        result["measured_s"] = time.monotonic() - started
        result["load"] = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else None
        (out / f"{name}.json").write_text(json.dumps(result, indent=1, default=_plain))
        print(f"({name}: {result['measured_s']:.0f} s)")


def _plain(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, float) and math.isnan(value):
        return None
    raise TypeError(type(value))


if __name__ == "__main__":
    main()
