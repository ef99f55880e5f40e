"""What faulty robots send (team.faults): faults change only the messages a robot sends, never what it computes or
what it does with the messages it receives.

From iteration `from` (Fault.start) on:
- crash: the robot sends nothing: its links deliver nothing and are never forced through by team.max_gap (messages
  it sent before are still in flight and arrive; under stale=latest its neighbours keep mixing the newest value they
  hold, as they would for any silent neighbour);
- stuck: it sends, every slot, the theta it sent in its first slot at or after `from` (frozen there and kept in the
  Mixer's Buffers, so a checkpoint resumes it exactly);
- byzantine: it sends `value` (one number for every parameter, or one per parameter), or its own theta plus
  Gaussian noise of standard deviation `scale`, drawn from default_rng([seed, BYZANTINE_STREAM, iteration, round,
  robot]) (the same value to every neighbour: LeBlanc et al.'s malicious model), so a resumed run redraws it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from riskplan.config.faults import Fault
from riskplan.config.schema import FaultKind

BYZANTINE_STREAM = 7933  # byzantine noise: default_rng([seed, 7933, iteration, round, robot])
MASK = (1 << 64) - 1


def healthy(faults: Sequence[Fault], robots: int, iteration: int) -> np.ndarray:
    """(N,) bool: False for the robots whose fault has started by `iteration`."""
    flags = np.ones(robots, dtype=bool)
    for fault in faults:
        if iteration >= fault.start:
            flags[fault.robot] = False
    return flags


def byzantine_value(fault: Fault, theta: np.ndarray, seed: int, iteration: int, round_index: int) -> np.ndarray:
    """(M,) what byzantine robot `fault.robot` sends in slot (iteration, round_index), its own theta being `theta`."""
    theta = np.asarray(theta, dtype=float)
    if fault.value is not None:
        return np.array(np.broadcast_to(np.array(fault.value, dtype=float), theta.shape))
    rng = np.random.default_rng([int(seed) & MASK, BYZANTINE_STREAM, int(iteration) & MASK, round_index, fault.robot])
    return theta + fault.scale * rng.standard_normal(theta.shape[0])


def sent_value(
    fault: Fault | None,
    theta: np.ndarray,
    seed: int,
    iteration: int,
    round_index: int,
    frozen: np.ndarray | None = None,
) -> np.ndarray | None:
    """(M,) what one robot sends in slot (iteration, round_index), or None when it sends nothing (crashed).

    `fault`: the robot's Fault or None; `theta`: its own theta; `frozen`: a stuck robot's frozen value, None
    before it is frozen (the caller keeps it: the result is the value to freeze then)."""
    theta = np.asarray(theta, dtype=float)
    if fault is None or iteration < fault.start:
        return theta
    if fault.kind == FaultKind.crash:
        return None
    if fault.kind == FaultKind.stuck:
        return theta if frozen is None else np.asarray(frozen, dtype=float)
    return byzantine_value(fault, theta, seed, iteration, round_index)


def sent_values(
    faults: Sequence[Fault],
    thetas: np.ndarray,
    seed: int,
    iteration: int,
    round_index: int,
    stuck_theta: np.ndarray | None,
    stuck_since: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """What the whole team sends in slot (iteration, round_index): ((N, M) values, (N,) bool silent robots or None
    when none is). `thetas` itself when no fault is active (no copy). A stuck robot sending for the first time since
    its fault started freezes its theta into `stuck_theta[robot]` and the iteration into `stuck_since[robot]`
    (changed in place; -1 = not frozen yet)."""
    active = [f for f in faults if iteration >= f.start]
    if not active:
        return thetas, None
    sent, silent = np.array(thetas, dtype=float, copy=True), None
    for fault in active:
        j = fault.robot
        frozen = None
        if fault.kind == FaultKind.stuck:
            if stuck_since[j] < 0:
                stuck_theta[j] = thetas[j]
                stuck_since[j] = iteration
            frozen = stuck_theta[j]
        value = sent_value(fault, thetas[j], seed, iteration, round_index, frozen)
        if value is None:
            silent = np.zeros(len(thetas), dtype=bool) if silent is None else silent
            silent[j] = True
        else:
            sent[j] = value
    return sent, silent
