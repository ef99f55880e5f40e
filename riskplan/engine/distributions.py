"""Reward distributions as data: parse YAML trees, sample them in numpy, and compile them for the rollout kernel.

Grammar (every node is a number or a one-key mapping, plus `of:` for wrappers):
  5.0                                   constant
  {constant: 5.0}                       constant
  {uniform: [lo, hi]}                   U[lo, hi)
  {normal: [mean, std]}                 N(mean, std^2)
  {bernoulli: p}                        1 with probability p, else 0
  {mixture: [{weight: w, of: D}, ...]}  one component, chosen with probability w / sum(w)
  {sum: [D, ...]}                       independent sum
  {scale: k, of: D}                     k * D
  {clip: [lo, hi], of: D}               min(max(D, lo), hi)
The paper's risky cell reward `200*a + d`, a ~ U[0,1], d ~ N(0, 100^2), clipped to [-1e4, 1e4], is
  {clip: [-1e4, 1e4], of: {sum: [{scale: 200, of: {uniform: [0, 1]}}, {normal: [0, 100]}]}}

Limits: a tree nests at most MAX_LEVELS levels, and every node's draws are bounded in size by REWARD_LIMIT
(`check_bound`, interval arithmetic; a normal counts as |mean| + NORMAL_SPREAD std), so no draw, partial sum or
intermediate of the kernel's formulas overflows; riskplan.engine.world bounds an episode's total the same way.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from riskplan.util.checks import finite
from riskplan.util.errors import BadInput

# Opcodes of the postfix program run by the rollout kernel (riskplan.engine.dynamics._draw).
OP_CONST, OP_UNIFORM, OP_NORMAL, OP_BERNOULLI, OP_SCALE, OP_SUM, OP_CLIP, OP_MIXTURE = range(8)

LEAVES = ("constant", "uniform", "normal", "bernoulli")
WRAPPERS = ("scale", "clip")
KINDS = LEAVES + ("mixture", "sum") + WRAPPERS
VALID = "a number or one of {" + ", ".join(KINDS) + "}, e.g. {normal: [0, 100]}"
MAX_LEVELS = 32  # nesting depth of a reward tree (a sum or mixture takes a list, so deep trees are never needed)
REWARD_LIMIT = 1e100  # bound on |draw| of any node and on |an episode's total reward|: squares and sums stay finite
NORMAL_SPREAD = 40.0  # a normal draw counts as |mean| + 40 std (the kernel's ziggurat never exceeds 14 std)


@dataclass(frozen=True)
class Dist:
    """A node of a reward-distribution tree."""

    kind: str
    params: tuple[float, ...] = ()
    children: tuple[Dist, ...] = ()


def parse(data: Any, where: str = "reward", level: int = 1) -> Dist:
    """Parse YAML-like data into a Dist tree; BadInput names `where` on any error."""
    if level > MAX_LEVELS:
        raise BadInput(
            where,
            f"the reward program nests more than {MAX_LEVELS} levels deep; flatten it "
            f"(a sum or a mixture takes a list of any length)",
        )
    if isinstance(data, bool):
        raise BadInput(where, f"got {data!r}; expected {VALID}")
    if isinstance(data, (int, float)):
        return Dist("constant", (finite(data, where),))
    if not isinstance(data, Mapping):
        raise BadInput(where, f"got {data!r}; expected {VALID}")
    keys = set(data) - {"of"}
    if len(keys) != 1:
        raise BadInput(
            where,
            f"got keys {sorted(map(str, data))}; expected exactly one of {list(KINDS)} (plus 'of' for scale/clip)",
        )
    (kind,) = keys
    value = data[kind]
    if kind not in KINDS:
        raise BadInput(where, f"unknown distribution {kind!r}; expected {VALID}")
    if kind in WRAPPERS:
        if "of" not in data:
            raise BadInput(where, f"'{kind}' needs 'of: <distribution>'")
        return _wrapper(kind, value, parse(data["of"], f"{where}.of", level + 1), where)
    if "of" in data:
        raise BadInput(where, f"'{kind}' takes no 'of'")
    if kind in LEAVES:
        return _leaf(kind, value, where)
    items = _list(value, f"{where}.{kind}", SHAPES[kind])
    if kind == "sum":
        return Dist("sum", (), tuple(parse(item, f"{where}.sum.{i}", level + 1) for i, item in enumerate(items)))
    return _mixture(items, where, level)


def _wrapper(kind: str, value: Any, child: Dist, where: str) -> Dist:
    """A scale (its factor `value`) or a clip (its [lo, hi]) of the parsed `child`."""
    if kind == "scale":
        return Dist("scale", (finite(value, f"{where}.scale"),), (child,))
    lo, hi = _pair(value, f"{where}.clip")
    if lo > hi:
        raise BadInput(f"{where}.clip", f"lower bound {lo} exceeds upper bound {hi}")
    return Dist("clip", (lo, hi), (child,))


def _leaf(kind: str, value: Any, where: str) -> Dist:
    """A constant, uniform [lo, hi], normal [mean, std] or bernoulli p, its parameters checked."""
    if kind == "constant":
        return Dist("constant", (finite(value, where),))
    if kind == "uniform":
        lo, hi = _pair(value, f"{where}.uniform")
        if lo > hi:
            raise BadInput(f"{where}.uniform", f"lower bound {lo} exceeds upper bound {hi}")
        return Dist("uniform", (lo, hi))
    if kind == "normal":
        mean, std = _pair(value, f"{where}.normal")
        if std < 0:
            raise BadInput(f"{where}.normal", f"standard deviation {std} is negative; give [mean, std] with std >= 0")
        return Dist("normal", (mean, std))
    p = finite(value, f"{where}.bernoulli")
    if not 0.0 <= p <= 1.0:
        raise BadInput(f"{where}.bernoulli", f"probability {p} is outside [0, 1]")
    return Dist("bernoulli", (p,))


def _mixture(items: list, where: str, level: int) -> Dist:
    """A mixture of [{weight: w, of: <distribution>}, ...]: weights >= 0, not all 0."""
    weights, children = [], []
    for i, item in enumerate(items):
        here = f"{where}.mixture.{i}"
        if not isinstance(item, Mapping) or set(item) != {"weight", "of"}:
            raise BadInput(here, "expected {weight: w, of: <distribution>}")
        weight = finite(item["weight"], f"{here}.weight")
        if weight < 0:
            raise BadInput(f"{here}.weight", f"weight {weight} is negative")
        weights.append(weight)
        children.append(parse(item["of"], f"{here}.of", level + 1))
    if sum(weights) <= 0:
        raise BadInput(f"{where}.mixture", "weights sum to 0; give at least one positive weight")
    return Dist("mixture", tuple(weights), tuple(children))


def to_data(dist: Dist) -> Any:
    """Inverse of `parse` (canonical form): parse(to_data(d)) == d."""
    if dist.kind in ("constant", "bernoulli"):
        return {dist.kind: dist.params[0]}
    if dist.kind in ("uniform", "normal"):
        return {dist.kind: list(dist.params)}
    if dist.kind == "sum":
        return {"sum": [to_data(c) for c in dist.children]}
    if dist.kind == "mixture":
        return {"mixture": [{"weight": w, "of": to_data(c)} for w, c in zip(dist.params, dist.children)]}
    value = dist.params[0] if dist.kind == "scale" else list(dist.params)
    return {dist.kind: value, "of": to_data(dist.children[0])}


def sample(dist: Dist, rng: np.random.Generator, n: int) -> np.ndarray:
    """Draw n independent values with numpy (reference implementation; the kernel uses `compile_program`)."""
    if dist.kind == "constant":
        return np.full(n, dist.params[0])
    if dist.kind == "uniform":
        return rng.uniform(dist.params[0], dist.params[1], n)
    if dist.kind == "normal":
        return rng.normal(dist.params[0], dist.params[1], n)
    if dist.kind == "bernoulli":
        return (rng.random(n) < dist.params[0]).astype(float)
    if dist.kind == "scale":
        return dist.params[0] * sample(dist.children[0], rng, n)
    if dist.kind == "clip":
        return np.clip(sample(dist.children[0], rng, n), dist.params[0], dist.params[1])
    if dist.kind == "sum":
        return np.sum([sample(c, rng, n) for c in dist.children], axis=0)
    weights = np.asarray(normalised(dist.params))
    choice = rng.choice(len(weights), size=n, p=weights)
    draws = np.stack([sample(c, rng, n) for c in dist.children])
    return draws[choice, np.arange(n)]


LINEAR_LEAVES = ("constant", "uniform", "normal")  # a scale of these is the same kind with scaled parameters


def compile_program(dist: Dist) -> tuple[np.ndarray, np.ndarray]:
    """Flatten a tree into postfix (ops int64[k, 2], params float64[k, 2]) for the numba stack machine.

    ops[:, 1] is the number of operands popped (sum, mixture). A mixture's component weights are stored as
    OP_CONST pushes after its components, so the kernel can read them off the stack.
    """
    ops: list[tuple[int, int]] = []
    params: list[tuple[float, float]] = []

    def add(op: int, arity: int, values: tuple[float, float]) -> None:
        ops.append((op, arity))
        params.append(values)

    def emit(node: Dist) -> None:
        if node.kind == "scale" and node.children[0].kind in LINEAR_LEAVES:
            # k*c, k*U[a,b] = ka + (kb-ka)u and k*N(m,s) = km + ks*z: fold the scale into the leaf, one op fewer per
            # draw (the paper's region rewards are scaled uniforms); ks may be negative, the kernel's formula holds
            leaf = node.children[0]
            emit(Dist(leaf.kind, tuple(node.params[0] * p for p in leaf.params)))
            return
        for child in node.children:
            emit(child)
        if node.kind == "constant":
            add(OP_CONST, 0, (node.params[0], 0.0))
        elif node.kind == "uniform":
            add(OP_UNIFORM, 0, node.params)
        elif node.kind == "normal":
            add(OP_NORMAL, 0, node.params)
        elif node.kind == "bernoulli":
            add(OP_BERNOULLI, 0, (node.params[0], 0.0))
        elif node.kind == "scale":
            add(OP_SCALE, 1, (node.params[0], 0.0))
        elif node.kind == "clip":
            add(OP_CLIP, 1, node.params)
        elif node.kind == "sum":
            add(OP_SUM, len(node.children), (0.0, 0.0))
        else:
            for w in normalised(node.params):
                add(OP_CONST, 0, (w, 0.0))
            add(OP_MIXTURE, len(node.children), (0.0, 0.0))

    emit(dist)
    return np.asarray(ops, dtype=np.int64).reshape(-1, 2), np.asarray(params, dtype=np.float64).reshape(-1, 2)


def normalised(weights: tuple[float, ...] | list[float]) -> list[float]:
    """Mixture weights divided by their sum; when that sum overflows, by the largest weight first (then it cannot)."""
    total = sum(weights)
    if math.isfinite(total):
        return [w / total for w in weights]
    top = max(weights)
    scaled = [w / top for w in weights]
    total = sum(scaled)
    return [w / total for w in scaled]


def bound(dist: Dist) -> float:
    """An upper bound on |draw| (interval arithmetic; a normal counts as |mean| + NORMAL_SPREAD std); may be inf."""
    if dist.kind == "constant":
        return abs(dist.params[0])
    if dist.kind == "uniform":
        return max(abs(dist.params[0]), abs(dist.params[1]))
    if dist.kind == "normal":
        return abs(dist.params[0]) + NORMAL_SPREAD * dist.params[1]
    if dist.kind == "bernoulli":
        return 1.0
    if dist.kind == "scale":
        k = abs(dist.params[0])
        return 0.0 if k == 0 else k * bound(dist.children[0])
    if dist.kind == "clip":
        b, (lo, hi) = bound(dist.children[0]), dist.params
        return max(abs(min(max(-b, lo), hi)), abs(min(max(b, lo), hi)))
    if dist.kind == "sum":
        return sum(bound(c) for c in dist.children)
    return max(bound(c) for c in dist.children)


def check_bound(dist: Dist, where: str = "reward") -> float:
    """bound(dist), after checking that no node (so no intermediate of the kernel) exceeds REWARD_LIMIT.

    The deepest offending node is named, with the same dotted path `parse` uses.
    """
    for i, child in enumerate(dist.children):
        if dist.kind == "sum":
            here = f"{where}.sum.{i}"
        elif dist.kind == "mixture":
            here = f"{where}.mixture.{i}.of"
        else:
            here = f"{where}.of"
        check_bound(child, here)
    value = bound(dist)
    if not value <= REWARD_LIMIT:
        raise BadInput(
            where,
            f"can draw values of about {min(value, 1.8e308):.3g} in size, beyond the limit of "
            f"{REWARD_LIMIT:g} on any reward (it keeps sums, means, variances and gradients finite); "
            f"give smaller values",
        )
    return value


def depth(dist: Dist) -> int:
    """Stack depth the postfix program needs."""
    if not dist.children:
        return 1
    extra = len(dist.children) if dist.kind == "mixture" else 0
    return max(i + depth(c) for i, c in enumerate(dist.children)) + extra + 1


def pack_programs(dists: list[Dist]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Concatenate programs: (offsets int64[n+1], ops, params) so program i is ops[offsets[i]:offsets[i+1]]."""
    compiled = [compile_program(d) for d in dists]
    offsets = np.zeros(len(dists) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(op) for op, _ in compiled])
    ops = np.concatenate([op for op, _ in compiled]) if compiled else np.zeros((0, 2), np.int64)
    params = np.concatenate([p for _, p in compiled]) if compiled else np.zeros((0, 2))
    return offsets, ops, params


def _pair(value: Any, where: str) -> tuple[float, float]:
    """Two finite floats, or BadInput."""
    items = _list(value, where, "a pair [a, b]")
    if len(items) != 2:
        raise BadInput(where, f"got {list(items)!r}; expected a pair [a, b]")
    return finite(items[0], where), finite(items[1], where)


SHAPES = {  # what the list of a sum or a mixture holds, for its messages
    "sum": "[<distribution>, ...] with at least one entry",
    "mixture": "[{weight: w, of: <distribution>}, ...] with at least one entry",
}


def _list(value: Any, where: str, shape: str) -> list:
    """A non-empty list, or BadInput saying what it should be (`shape`)."""
    if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
        raise BadInput(where, f"got {value!r}; expected {shape}")
    items = list(value)
    if not items:
        raise BadInput(where, f"got an empty list; expected {shape}")
    return items
