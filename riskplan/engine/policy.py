"""Softmax policy of eqs. (2)-(3) and its score function d log mu / d theta (errata to eq. 10).

`probabilities` and `scores` state the maths in numpy; `tables` builds the same quantities for the rollout kernel
in one numba pass, for every policy of a batch.

What theta parameterises is a `Policy` (`make_policy`, from the `policy` config node):
  * kind "features" (the default): mu(u | x) ∝ exp(theta . f(x, u)), where f lists, in the order of
    `policy.features`, the M source signals s^j(x + u) ("signals", eq. 3: the paper's policy), the indicator that
    x + u lies in a risky region ("risky"; the first matching region decides, as for the reward) and the indicator
    of the Stay move ("stay"). A blocked move's x + u is the robot's own cell.
  * kind "tabular": theta is a (C * 5,) table of logits, cell-major (theta[c * 5 + a]); mu(. | c) is the softmax of
    the cell's five entries, and the score of a step is e_(c, a) - mu(. | c) (`tabular_tables` and the kernel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from riskplan.engine.dynamics import _cumulative_softmax
from riskplan.engine.world import MOVE_NAMES, World

SIGNALS, RISKY, STAY = "signals", "risky", "stay"  # the entries of policy.features
FEATURES, TABULAR = "features", "tabular"  # policy.kind
EXTRA_NAMES = {RISKY: "risky_region", STAY: "stay"}  # theta_names of the features other than the signals
STAY_MOVE = 2  # index of Stay in MOVES (E, W, Stay, N, S)


@dataclass(frozen=True, eq=False)
class Policy:
    """What theta is for one world: its names and, for a features policy, where each feature's weight sits.

    Build it with `make_policy`. For kind "tabular", `features`, `signal_at`, `extra_at`, `extras` and `peaks`
    describe the features policy that seeds the table (`initial`): theta0 weights the signals.
    """

    kind: str  # FEATURES or TABULAR
    features: tuple[str, ...]  # policy.features in theta's order ("signals" stands for the M signal weights)
    names: tuple[str, ...]  # theta_names: one unique name per entry of theta
    seed_names: tuple[str, ...]  # the parameters train.theta0 lists: `names` for features, the signals' for tabular
    signal_at: int  # index (in the seed parameters) of the first signal weight; -1 without "signals"
    extra_at: np.ndarray  # (E,) int64: index (in the seed parameters) of each extra feature's weight
    extras: np.ndarray  # (C, 5, E) float64: the extra features (risky, stay) of every (cell, move)
    peaks: np.ndarray  # (len(seed_names),) float64: largest |feature| of each seed parameter's column

    @property
    def tabular(self) -> bool:
        """Whether theta is the table of (cell, move) logits."""
        return self.kind == TABULAR

    @property
    def size(self) -> int:
        """Length of theta."""
        return len(self.names)

    def move_features(self, world: World, signals: np.ndarray | None = None) -> np.ndarray:
        """The seed features policy's f(x, u) of every (cell, move), (C, 5, len(seed_names)); see `move_features`."""
        return move_features(world, signals, self.features)

    def initial(self, world: World, weights: np.ndarray) -> np.ndarray:
        """theta at the start of training from the seed parameters `weights` (train.theta0, padded).

        A features policy starts at `weights` itself. A tabular policy starts from the logits the features policy
        with those weights gives, theta[c * 5 + a] = weights . f(c, a) (f: the signals of x + u): with the paper's
        theta0 [20, 20] the table starts as the paper's initial policy, with [0, 0] it starts uniform. The logits are
        summed as `tables` sums them, so both policies' move probabilities agree bit for bit.
        """
        weights = np.ascontiguousarray(weights, dtype=np.float64)
        if not self.tabular:
            return weights.copy()
        return feature_logits(self.move_features(world), weights).reshape(-1)

    def seed_bound(self, weights: np.ndarray) -> float:
        """`logit_bound` of the seed features policy at `weights` (..., len(seed_names)): sum_i |w_i| x peak |f_i|."""
        with np.errstate(over="ignore", invalid="ignore"):
            return float(np.max(np.abs(np.asarray(weights, dtype=float)) @ self.peaks))

    def logit_bound(self, thetas: np.ndarray) -> float:
        """Largest |logit| any policy in `thetas` (..., size) can produce; finite means no softmax overflows.

        Features: sum_i |theta_i| x peak |f_i| (a signal's peak |amplitude|, 1 for risky and stay); tabular: the
        largest |theta| (the logits are theta itself).
        """
        if not self.tabular:
            return self.seed_bound(thetas)
        thetas = np.abs(np.asarray(thetas, dtype=float))
        return float(np.max(thetas)) if thetas.size else 0.0


def make_policy(world: World, kind: str = FEATURES, features: tuple[str, ...] | list = (SIGNALS,)) -> Policy:
    """The Policy of `policy.kind` and `policy.features` (validated by riskplan.config.validate) on `world`.

    theta_names: a source's name for its signal, "risky_region" for risky, "stay" for stay, and x{x}_y{y}_{move}
    for a table entry. Names stay unique: source names are each their own (riskplan.config.validate), and an extra
    feature whose name a source already has gets the first free "feature_<name>", "feature_<name>_2", ...
    """
    kind = str(kind)
    features = (SIGNALS,) if kind == TABULAR else tuple(str(f) for f in features)
    unknown = [f for f in features if f not in (SIGNALS, RISKY, STAY)]
    if kind not in (FEATURES, TABULAR) or unknown or not features:
        raise ValueError(
            f"policy kind {kind!r} with features {list(features)}: expected features|tabular of signals, risky, stay"
        )
    source_names = list(world.source_names)
    taken = set(source_names)
    extra_names = {f: _claim(EXTRA_NAMES[f], taken, "feature_") for f in features if f != SIGNALS}
    seed_names: list[str] = []
    peaks: list[float] = []
    signal_at, extra_at, extras = -1, [], []
    for feature in features:
        if feature == SIGNALS:
            signal_at = len(seed_names)
            seed_names += source_names
            peaks += np.abs(world.source_amplitude).tolist()
        else:
            extra_at.append(len(seed_names))
            extras.append(extra_feature(world, feature))
            seed_names.append(extra_names[feature])
            peaks.append(1.0)
    if kind == TABULAR:
        x, y = world.xy(np.arange(world.cells))
        names = tuple(f"x{cx}_y{cy}_{move}" for cx, cy in zip(x.tolist(), y.tolist()) for move in MOVE_NAMES)
    else:
        names = tuple(seed_names)
    return Policy(
        kind=kind,
        features=features,
        names=names,
        seed_names=tuple(seed_names),
        signal_at=signal_at,
        extra_at=np.array(extra_at, dtype=np.int64),
        extras=np.stack(extras, axis=-1) if extras else np.zeros((world.cells, 5, 0)),
        peaks=np.array(peaks, dtype=np.float64),
    )


def _claim(name: str, taken: set[str], prefix: str = "") -> str:
    """`name`, or the first free prefix + name, then with _2, _3, ...; marked taken."""
    candidates = [name] if not prefix else [name, prefix + name]
    base = candidates[-1]
    for candidate in candidates:
        if candidate not in taken:
            break
    else:
        k = 2
        while f"{base}_{k}" in taken:
            k += 1
        candidate = f"{base}_{k}"
    taken.add(candidate)
    return candidate


def risky_cells(world: World) -> np.ndarray:
    """(C,) float64: 1 where a cell's region (the first matching one) is risky, else 0."""
    risky = np.zeros(world.cells)
    inside = world.region_of >= 0
    risky[inside] = world.region_risky[world.region_of[inside]]
    return risky


def extra_feature(world: World, feature: str) -> np.ndarray:
    """(C, 5) float64: the feature "risky" (x + u in a risky region) or "stay" (u is Stay) of every (cell, move)."""
    if feature == RISKY:
        return risky_cells(world)[world.next_cell]
    if feature == STAY:
        column = np.zeros((world.cells, 5))
        column[:, STAY_MOVE] = 1.0
        return column
    raise ValueError(f"no extra feature {feature!r}; expected {RISKY} or {STAY}")


def move_features(
    world: World, signals: np.ndarray | None = None, features: tuple[str, ...] | list = (SIGNALS,)
) -> np.ndarray:
    """Features f(x, u) of every (cell, move), shape (C, 5, F), in the order of `features`; a blocked move sees its
    own cell. The default, [signals], is s^j(x + u) of eq. (3), (C, 5, M); `signals` (C, M) replaces the signals of
    the sources' initial cells."""
    signals = world.signals() if signals is None else signals
    if tuple(str(f) for f in features) == (SIGNALS,):
        return signals[world.next_cell]
    columns = [
        signals[world.next_cell] if str(f) == SIGNALS else extra_feature(world, str(f))[:, :, None] for f in features
    ]
    return np.concatenate(columns, axis=-1)


def probabilities(features: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """mu_theta(u | x) for every cell, shape (..., C, 5) for theta (..., M); stable for any finite theta."""
    logits = np.einsum("cam,...m->...ca", features, np.asarray(theta, dtype=float))
    logits = logits - logits.max(axis=-1, keepdims=True)  # max-shift: no overflow for large theta
    weights = np.exp(logits)
    return weights / weights.sum(axis=-1, keepdims=True)


def scores(features: np.ndarray, probs: np.ndarray) -> np.ndarray:
    """d log mu(u|x) / d theta_j = s^j(x+u) - sum_v mu(v|x) s^j(x+v), shape (..., C, 5, M)."""
    expected = np.einsum("...ca,cam->...cm", probs, features)
    return features - expected[..., None, :]


PARALLEL_POLICIES = 16  # from this many policies on, `tables` fills them in parallel (below: no parallel region)
CHUNK = 8  # policies per parallel work item


def tables(
    world: World, thetas: np.ndarray, features: np.ndarray | None = None, cells: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Per-policy cumulative move probabilities (P, C, 5) and scores (P, C, 5, M) for thetas (P, M).

    `features` is move_features(world) when the caller keeps it (riskplan.engine.rollout.KernelArrays does: computing it is
    most of a small batch's fixed cost). With `cells` (an index array), only those cells' rows are filled, each with
    the numbers it has in the full tables, and the other rows are left unset: the kernel passes the cells its
    episodes can reach (riskplan.engine.rollout.reach), so a large map costs what its reachable part costs.
    """
    features = move_features(world) if features is None else features
    cum = np.empty(thetas.shape[:1] + features.shape[:2])
    score = np.empty(thetas.shape[:1] + features.shape)
    thetas = np.ascontiguousarray(thetas, dtype=np.float64)
    cells = np.arange(features.shape[0]) if cells is None else np.ascontiguousarray(cells, dtype=np.int64)
    if len(thetas) >= PARALLEL_POLICIES:
        _fill_tables_at_parallel(features, thetas, cum, score, cells)
    else:
        _fill_tables_at(features, thetas, cum, score, 0, len(thetas), cells)
    return cum, score


@njit(parallel=True, cache=True)
def _fill_tables_at_parallel(features, thetas, cum, score, cells):
    """`_fill_tables_at` of all policies, CHUNK at a time in parallel: each policy's numbers are one thread's, the
    same whatever the thread count."""
    chunks = (thetas.shape[0] + CHUNK - 1) // CHUNK
    for chunk in prange(chunks):
        _fill_tables_at(features, thetas, cum, score, chunk * CHUNK, min(thetas.shape[0], (chunk + 1) * CHUNK), cells)


@njit(cache=True)
def _fill_tables_at(features, thetas, cum, score, first, last, cells):
    """`probabilities` (cumulated) and `scores` for policies first..last-1 at the listed cells, in one pass.

    The same maths as the numpy functions above, as loops: every iteration of a 100-robot team builds 100 tables,
    and loops avoid the numpy composition's temporaries (tests/engine/test_policy.py checks they agree).
    """
    mu = np.empty(5)
    for p in range(first, last):
        for c in cells:
            best = -np.inf
            for a in range(5):
                mu[a] = 0.0
                for j in range(thetas.shape[1]):
                    mu[a] += thetas[p, j] * features[c, a, j]
                best = max(best, mu[a])
            _cumulative_softmax(mu, best, cum[p, c])
            for j in range(thetas.shape[1]):
                expected = 0.0
                for a in range(5):
                    expected += mu[a] * features[c, a, j]
                for a in range(5):
                    score[p, c, a, j] = features[c, a, j] - expected


@njit(cache=True)
def feature_logits(features, theta):
    """theta . f(c, a) of every (cell, move), (C, 5), summed in the order `_fill_tables_at` sums it."""
    out = np.empty(features.shape[:2])
    for c in range(features.shape[0]):
        for a in range(5):
            logit = 0.0
            for j in range(theta.shape[0]):
                logit += theta[j] * features[c, a, j]
            out[c, a] = logit
    return out


def tabular_probabilities(theta: np.ndarray, cells: int) -> np.ndarray:
    """mu_theta(u | c) of a tabular policy, shape (..., C, 5) for theta (..., C * 5); stable for any finite theta."""
    logits = np.asarray(theta, dtype=float).reshape(*np.shape(theta)[:-1], cells, 5)
    weights = np.exp(logits - logits.max(axis=-1, keepdims=True))
    return weights / weights.sum(axis=-1, keepdims=True)


def tabular_tables(thetas: np.ndarray, cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-policy cumulative move probabilities (P, C, 5) and move probabilities (P, C, 5) of tabular thetas (P, C*5).

    The kernel accumulates a step's score e_(c, a) - mu(. | c) from the probabilities: no (C, 5, C * 5) scores.
    """
    thetas = np.ascontiguousarray(thetas, dtype=np.float64).reshape(-1, cells, 5)
    cum = np.empty(thetas.shape)
    probs = np.empty(thetas.shape)
    _fill_tabular(thetas, cum, probs)
    return cum, probs


@njit(cache=True)
def _fill_tabular(logits, cum, probs):
    """The softmax of every cell's five logits, by `_fill_tables_at`'s `_cumulative_softmax` (same logits: same
    numbers)."""
    mu = np.empty(5)
    for p in range(logits.shape[0]):
        for c in range(logits.shape[1]):
            best = -np.inf
            for a in range(5):
                mu[a] = logits[p, c, a]
                best = max(best, mu[a])
            _cumulative_softmax(mu, best, cum[p, c])
            for a in range(5):
                probs[p, c, a] = mu[a]
