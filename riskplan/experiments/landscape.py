"""The objective landscape: mean and CVaR of the total reward on a grid of theta, with common random numbers.

theta has one weight per source, so with the paper's two sources the whole objective is a picture. Every grid
point replays the same episode streams (one stream key for the whole grid), so differences between points are
differences between policies, not between random draws; the surface is smooth and its optima are comparable.

A landscape directory is run-like: `.hydra/config.yaml`, `landscape.parquet` (one row per grid point),
`summary.json` with `"kind": "landscape"` (the marker the report recognises) and `status.json`, placed last: the
report reads a landscape only when it says done. Any two components of a features policy's theta can be varied
(`summary.json` says what each weighs); a tabular policy's logits cannot.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from numpy.lib.stride_tricks import sliding_window_view
from omegaconf import OmegaConf

from riskplan.engine import rng
from riskplan.engine.risk_measures import tail_count
from riskplan.engine.rollout import simulate
from riskplan.engine.step import logit_bound
from riskplan.experiments.output_manifest import Output, claim_output
from riskplan.run.build import build_setup
from riskplan.run.columns import frame_to_parquet, read_parquet
from riskplan.run.provenance import provenance
from riskplan.run.results import run_config
from riskplan.util.errors import BadInput, one_line
from riskplan.util.limits import STEPS_PER_SECOND, check_memory, check_time

LANDSCAPES_ROOT = Path("outputs") / "landscapes"  # where riskplan landscape claims its folders
KIND = "landscape"
TABLE = "landscape.parquet"
SCHEMA_VERSION = 1
DEFAULT_POINTS = 41
DEFAULT_EPISODES = 4000
DEFAULT_RANGE = (-20.0, 60.0)
CHUNK_EPISODES = 1_000_000  # episodes per kernel call (bounds memory)


@dataclass
class Landscape:
    """A computed landscape on disk."""

    path: Path
    config: dict
    table: pd.DataFrame
    summary: dict

    @property
    def axes(self) -> tuple[int, int]:
        a = self.summary.get("axes", [0, 1])
        return int(a[0]), int(a[1])

    @property
    def axis_labels(self) -> tuple[str, str]:
        """What the two varied components weigh (landscapes from before the labels varied two source weights)."""
        labels = self.summary.get("axis_labels")
        if isinstance(labels, list) and len(labels) == 2 and all(isinstance(x, str) for x in labels):
            return labels[0], labels[1]
        return tuple(f"weight of source {i + 1}" for i in self.axes)

    @property
    def beta(self) -> float:
        return float(self.summary.get("beta", self.config.get("risk", {}).get("beta", 0.1)))

    def grid(self, column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(values of axis a, values of axis b, column as an array [b, a]) for imshow/pcolormesh."""
        a, b = self.axes
        ca, cb = f"theta_{a}", f"theta_{b}"
        pivot = self.table.pivot_table(index=cb, columns=ca, values=column, aggfunc="first")
        return pivot.columns.to_numpy(float), pivot.index.to_numpy(float), pivot.to_numpy(float)

    def smoothed_best(self, column: str) -> dict:
        """The maximum of the 3x3 moving average of `column` (robust to the Monte Carlo noise of single points)."""
        va, vb, values = self.grid(column)
        smooth = sliding_window_view(np.pad(values, 1, mode="edge"), (3, 3)).mean(axis=(2, 3))
        if not np.isfinite(smooth).any():
            return {"theta": None, "value": math.nan}
        i, j = np.unravel_index(int(np.nanargmax(np.where(np.isfinite(smooth), smooth, np.nan))), smooth.shape)
        return {"theta": [float(va[j]), float(vb[i])], "value": float(smooth[i, j])}

    def best_index(self, column: str) -> int | None:
        """Position of the grid point maximising `column` among its finite values (None when there is none)."""
        values = self.table[column].to_numpy(dtype=float)
        finite = np.isfinite(values)
        if not finite.any():
            return None
        return int(np.argmax(np.where(finite, values, -np.inf)))

    def best(self, column: str) -> dict:
        """The grid point maximising `column`: its theta and value (theta None, value NaN when none is finite)."""
        index = self.best_index(column)
        if index is None:
            return {"theta": None, "value": math.nan}
        row = self.table.iloc[index]
        return {"theta": [float(row[c]) for c in _theta_columns(self.table)], "value": float(row[column])}


def is_landscape_dir(path: Path) -> bool:
    """A landscape directory: it holds landscape.parquet, or a summary.json whose kind is 'landscape'."""
    if (path / TABLE).is_file():
        return True
    file = path / "summary.json"
    if file.is_file():
        try:
            return json.loads(file.read_text()).get("kind") == KIND
        except (OSError, ValueError, AttributeError):
            return False
    return False


def load_landscape(path: Path) -> Landscape:
    """Read a landscape directory (raises on a damaged one)."""
    path = Path(path)
    if not (path / TABLE).is_file():
        raise ValueError(f"no {TABLE} (the landscape did not finish)")
    _check_done(path)
    table = read_parquet(path / TABLE)
    summary = json.loads((path / "summary.json").read_text()) if (path / "summary.json").is_file() else {}
    if not isinstance(summary, dict):
        raise ValueError("summary.json is not a JSON object (it was not written by riskplan)")
    config = run_config(path)  # BadInput naming the file for invalid YAML, not a mapping, unresolvable values
    needed = {"mean", "cvar", "value_at_risk"}
    if not needed <= set(table.columns) or len(_theta_columns(table)) < 2:
        raise ValueError(f"{TABLE} lacks columns {sorted(needed - set(table.columns))} or theta columns")
    return Landscape(path, config or {}, table, summary)


def _check_done(path: Path) -> None:
    """BadInput naming status.json unless it says done: it is written last and set aside first, so without it the
    other files may be a landscape that stopped, or one stopped while the next replaced it."""
    file = path / "status.json"
    try:
        status = json.loads(file.read_text()).get("status")
    except FileNotFoundError:
        raise BadInput(str(file), "not found, so the landscape did not finish writing") from None
    except (OSError, ValueError, AttributeError) as err:
        raise BadInput(str(file), f"cannot be read ({one_line(str(err))})") from None
    if status != "done":
        raise BadInput(str(file), f"says {status!r}, not 'done'")


def _theta_columns(table: pd.DataFrame) -> list[str]:
    cols = [c for c in table.columns if c.startswith("theta_") and c[6:].isdigit()]
    return sorted(cols, key=lambda c: int(c[6:]))


def grid_thetas(
    theta0: np.ndarray, axes: tuple[int, int], ranges: tuple[tuple[float, float], ...], points: int
) -> np.ndarray:
    """(points^2, M) thetas: axis a varies slowest; the other components stay at theta0."""
    a, b = axes
    va = np.linspace(ranges[0][0], ranges[0][1], points)
    vb = np.linspace(ranges[1][0], ranges[1][1], points)
    ga, gb = np.meshgrid(va, vb, indexing="ij")
    thetas = np.tile(np.asarray(theta0, dtype=float), (points * points, 1))
    thetas[:, a] = ga.ravel()
    thetas[:, b] = gb.ravel()
    return thetas


def evaluate_grid(setup, thetas: np.ndarray, episodes: int, beta: float, seed: int) -> pd.DataFrame:
    """Mean, CVaR_beta, VaR_beta, std, P(risky), P(source j) of every theta, all on the same episode streams.

    mean_se and cvar_se are the estimators' asymptotic standard errors at each point: std(Z)/sqrt(W) and
    std((Z - v) 1{Z <= v}) / (beta sqrt(W)) (the influence function of the Rockafellar-Uryasev form).
    """
    world, kernel = setup.world, setup.kernel
    key = np.uint64(rng.stream_key(seed, rng.LANDSCAPE))
    start = world.starts[0]
    m = tail_count(beta, episodes)
    per_call = max(1, CHUNK_EPISODES // episodes)
    parts = []
    for first in range(0, len(thetas), per_call):
        block = thetas[first : first + per_call]
        p = len(block)
        batch = simulate(
            world, kernel, block, np.full(p, start, dtype=np.int64), np.full(p, key, dtype=np.uint64), episodes
        )
        z = batch.total_reward.reshape(p, episodes)
        zs = np.sort(z, axis=1)
        var = zs[:, m - 1]
        cvar = var + np.minimum(zs - var[:, None], 0.0).sum(axis=1) / (beta * episodes)
        reached = batch.source_reached.reshape(p, episodes)
        part = {f"theta_{j}": block[:, j] for j in range(block.shape[1])}
        tail = np.minimum(z - var[:, None], 0.0)  # (Z - v) 1{Z <= v}: CVaR = v + E[tail] / beta
        part.update(
            {
                "mean": z.mean(axis=1),
                "cvar": cvar,
                "value_at_risk": var,
                "std": z.std(axis=1),
                "mean_se": z.std(axis=1, ddof=1) / np.sqrt(episodes) if episodes > 1 else np.full(p, np.nan),
                "cvar_se": tail.std(axis=1, ddof=1) / (beta * np.sqrt(episodes))
                if episodes > 1
                else np.full(p, np.nan),
                "risky_fraction": (batch.risky_steps.reshape(p, episodes) > 0).mean(axis=1),
                "mean_steps": batch.steps.reshape(p, episodes).mean(axis=1),
            }
        )
        for j, name in enumerate(world.source_names):
            part[f"reached_{name}"] = (reached == j).mean(axis=1)
        part["reached_none"] = (reached < 0).mean(axis=1)
        parts.append(pd.DataFrame(part))
    return pd.concat(parts, ignore_index=True)


def check_grid(
    setup, points: int, episodes: int, ranges, axes, typed: str | None = None
) -> tuple[tuple, tuple[int, int]]:
    """Validate the grid options against the world and policy; BadInput naming the option otherwise. `typed` is
    --range as the user wrote it, for the message (else the ranges are shown as given)."""
    policy = setup.policy
    if policy.tabular:  # its theta is a logit per (cell, move): two of them say nothing of the objective
        raise BadInput(
            "policy.kind",
            f"got 'tabular'; the landscape varies two weights of a features policy (eq. 3), not two of a table's "
            f"{policy.size} logits: give policy.kind=features (policy.features chooses the weights)",
        )
    size = policy.size
    if size < 2:
        raise BadInput(
            "policy.features",
            f"gives theta one weight on this world ({policy.names[0]}); the landscape varies two: add a source, or "
            f"a feature (e.g. policy.features=[signals,risky])",
        )
    a, b = (int(axes[0]), int(axes[1]))
    if not (0 <= a < size and 0 <= b < size and a != b):
        components = ", ".join(f"{i} {name}" for i, name in enumerate(policy.names))
        raise BadInput("--axes", f"got {a},{b}; expected two different theta components of {components}")
    if points < 2:
        raise BadInput("--points", f"got {points}; expected at least 2 grid points per axis")
    if episodes < 1:
        raise BadInput("--episodes", f"got {episodes}; expected at least 1 episode per grid point")
    ranges = tuple(tuple(float(v) for v in r) for r in ranges) if ranges is not None else (DEFAULT_RANGE, DEFAULT_RANGE)
    text = typed if typed is not None else ",".join(f"{v:g}" for r in ranges for v in r)
    if len(ranges) != 2 or any(not (math.isfinite(lo) and math.isfinite(hi) and lo < hi) for lo, hi in ranges):
        raise BadInput("--range", f"got '{text}'; expected LO,HI (both axes) or LO,HI,LO,HI, finite, with LO < HI")
    spans = all(math.isfinite(hi - lo) for lo, hi in ranges)  # else the grid's step overflows: theta NaN
    corners = grid_thetas(setup.theta0, (a, b), ranges, 2) if spans else None  # |logits| peak at the corners
    if not (spans and math.isfinite(logit_bound(setup.world, corners, policy))):
        raise BadInput(
            "--range",
            f"got '{text}'; a theta that far overflows the softmax (theta . features is not finite), as riskplan "
            f"train refuses it: give a narrower range, e.g. -20,20",
        )
    check_size(points, episodes, setup.world.sources, setup.kernel.tables.horizon)
    return ranges, (a, b)


def axis_label(setup, index: int) -> str:
    """What theta[index] of a features policy weighs: a source's signal or another feature (the figure's axes)."""
    policy = setup.policy
    name = policy.names[index]
    signal = policy.signal_at >= 0 and 0 <= index - policy.signal_at < setup.world.sources
    return f"weight of source {name}" if signal else f"weight of feature {name}"


def estimate(points: int, episodes: int, sources: int, horizon: int) -> tuple[float, float, float]:
    """(bytes of the grid's table, bytes of one kernel call's episodes, seconds) of a landscape, upper bounds.

    The table holds per grid point theta, the grid point's figures and P(source j) (and pandas copies it about
    four times on the way to parquet); a kernel call holds min(CHUNK_EPISODES, points^2 x episodes) episodes
    rounded up to whole grid points (simulate's outputs and evaluate_grid's sorted copies and temporaries); the
    time is every episode running to the horizon at limits.STEPS_PER_SECOND.
    """
    cells = float(points) * float(points)
    table = cells * (2 * sources + 12) * 8 * 4
    per_call = max(1, CHUNK_EPISODES // max(episodes, 1))
    chunk = min(float(per_call) * episodes, cells * episodes) * (160 + 16 * sources)
    seconds = cells * episodes * max(int(horizon), 1) / STEPS_PER_SECOND
    return table, chunk, seconds


def check_size(points: int, episodes: int, sources: int, horizon: int) -> None:
    """BadInput naming --points or --episodes when the grid would not fit in memory or time (riskplan.util.limits)."""
    table, chunk, seconds = estimate(points, episodes, sources, horizon)
    what = f"a {points}x{points} grid x {episodes} episodes"
    check_memory("--episodes" if chunk > table else "--points", table + chunk, what)
    check_time("--points/--episodes", seconds, what)


def compute_landscape(
    cfg,
    out_dir: Path,
    *,
    points: int = DEFAULT_POINTS,
    episodes: int = DEFAULT_EPISODES,
    ranges: tuple[tuple[float, float], ...] | None = None,
    axes: tuple[int, int] = (0, 1),
    overrides: list[str] | None = None,
    key: str = "out_dir",
) -> Path:
    """Evaluate mean and CVaR on a points x points grid of (theta_a, theta_b) into a run-like directory.

    Everything is checked before anything runs (BadInput: the options, the grid's memory and time, out_dir, which
    must be new, empty or a previous landscape's and not in use; `key` names it). out_dir's lock is held from then
    on; the grid is evaluated, then the files are written as one set (WriteFailed, an OSError, when one cannot be:
    the previous landscape stays whole, see output_manifest).
    """
    setup = build_setup(cfg)
    config = setup.config
    ranges, (a, b) = check_grid(setup, points, episodes, ranges, axes)
    beta, seed = setup.params.risk.beta, setup.params.seed
    output = Output(out_dir, KIND, claim_output(out_dir, KIND, key))
    with output.locked():  # from the start: a second landscape into out_dir is refused now, not after this work
        started = time.perf_counter()
        thetas = grid_thetas(setup.theta0, (a, b), ranges, points)
        table = evaluate_grid(setup, thetas, episodes, beta, seed)
        seconds = time.perf_counter() - started
        scan = Landscape(Path(out_dir), config, table, {"axes": [a, b]})
        summary = {
            "kind": KIND,
            "schema_version": SCHEMA_VERSION,
            "experiment": config.get("experiment"),
            "axes": [a, b],
            "axis_labels": [axis_label(setup, a), axis_label(setup, b)],
            "theta_names": list(setup.theta_names),
            "ranges": [list(r) for r in ranges],
            "points": points,
            "episodes": episodes,
            "beta": beta,
            "seed": seed,
            "theta_fixed": setup.theta0.tolist(),
            "common_random_numbers": True,
            "best": {
                "mean": scan.best("mean"),
                "cvar": scan.best("cvar"),
                "value_at_risk": scan.best("value_at_risk"),
            },
            "seconds": seconds,
            "episodes_per_s": points * points * episodes / seconds if seconds > 0 else None,
            "provenance": provenance(),
        }
        with output.writing(list(FILES)):  # status.json last: placed only once the rest of the set is
            output.write(".hydra/config.yaml", OmegaConf.to_yaml(OmegaConf.create(config)))
            output.write(".hydra/overrides.yaml", yaml.safe_dump(list(overrides or [])))
            output.write_with(TABLE, lambda tmp: frame_to_parquet(table, tmp))
            output.write("summary.json", finite_json(summary))
            output.write("status.json", finite_json({"status": "done", "error": None}))
    return output.out


FILES = (".hydra/config.yaml", ".hydra/overrides.yaml", TABLE, "summary.json", "status.json")


def finite_json(data) -> str:
    """JSON with every non-finite number (NaN, +-inf) written as null: strict JSON any reader accepts."""
    return json.dumps(_finite(data), indent=2, allow_nan=False)


def _finite(value):
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value
