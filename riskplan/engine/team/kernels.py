"""The consensus kernels: numba loops over a team's links that send, receive and mix messages (paper eq. 14), and
the numpy rule they follow. `riskplan.engine.team.mixer.Mixer` decides what they do; these only do it.

The kernels run over a range of rows (robots i); from PARALLEL_ENTRIES links or (N, N) entries on, their _parallel
drivers run ROWS rows at a time in parallel. A row is always one thread's: the numbers do not depend on the thread
count. The kernels take the Mixer's buffers one by one (numba takes arrays, not its Buffers), so their parameter
lists echo the Mixer's calls.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from riskplan.engine.team.network import Network


def mix_numpy(
    weights: np.ndarray, adjacency: np.ndarray, use: np.ndarray, neighbour: np.ndarray, own: np.ndarray
) -> np.ndarray:
    """sum_j a^{ij} theta^j over the links in `use` (neighbour values), each idle link's weight handed to robot i
    itself (`own`), by numpy: the rule the per-link kernels below follow, summed in numpy's order."""
    n = len(own)
    effective = weights * use[:, :, None]
    idle = (weights * (adjacency & ~use)[:, :, None]).sum(axis=1)
    diagonal = np.arange(n)
    effective[diagonal, diagonal, :] = weights[diagonal, diagonal, :] + idle
    values = np.where(use[:, :, None], neighbour, 0.0)  # stale slots never meet a weight, even as 0 * inf
    values[diagonal, diagonal, :] = own
    return np.einsum("ijm,ijm->im", effective, values)


PARALLEL_ENTRIES = 1 << 15
ROWS = 16
NO_INTS = np.zeros((0, 0), dtype=np.int64)  # placeholders for the kernels' optional arrays
NO_FLAGS = np.zeros((0, 0), dtype=bool)
NO_FLOATS = np.zeros((0, 0))
NO_PENDING = np.zeros((0, 0, 0, 0, 0))


def send(*args) -> None:
    """`_send_links` over every row (the Mixer's send step), in parallel from PARALLEL_ENTRIES (N, N) entries on."""
    n = args[0].shape[0]
    if n * n >= PARALLEL_ENTRIES:
        _send_parallel(*args)
    else:
        _send_links(*args, 0, n)


def receive(*args) -> None:
    """`_receive_links` over every row (the Mixer's receive step), in parallel from PARALLEL_ENTRIES entries on."""
    n = args[0].shape[0]
    if n * n >= PARALLEL_ENTRIES:
        _receive_parallel(*args)
    else:
        _receive_links(*args, 0, n)


def mix_used(weights, adjacency, use, neighbour, own) -> np.ndarray:
    """sum_j e^{ij}_m v^{ij}_m for every robot (see `_mix_used`): the links in `use` mix the neighbour's value and
    every other link's weight goes to robot i itself. M = 1 sums in numpy's own order (`mix_numpy`), as always."""
    n, m = own.shape
    if m == 1:
        return mix_numpy(weights, adjacency, use, neighbour, own)
    out = np.empty((n, m))
    args = (weights, adjacency, use, neighbour, np.ascontiguousarray(own), out)
    if n * n >= PARALLEL_ENTRIES:
        _mix_used_parallel(*args)
    else:
        _mix_used(*args, 0, n)
    return out


@njit(parallel=True, cache=True)
def _send_parallel(*args):
    """`_send_links` of every row, ROWS at a time in parallel (`args`: its own, less first and last)."""
    n = args[0].shape[0]
    for chunk in prange((n + ROWS - 1) // ROWS):
        _send_links(*args, chunk * ROWS, min(n, (chunk + 1) * ROWS))


@njit(cache=True)
def _send_links(
    adjacency,
    up,
    kept,
    delay,
    iteration,
    max_gap,
    round_index,
    thetas,
    sums,
    last_delivered,
    delivered,
    forced,
    pending,
    pending_sent,
    pending_due,
    pending_sums,
    first,
    last,
):
    """Mixer._send per link of rows first..last-1: a link that is up sends unless dropped (`kept`, empty: none is);
    one without a delivery for max_gap iterations is forced through; a sent message is due `delay` later (empty:
    at once) in slot due mod B0+1, carrying theta^j (and the running sums `sums`, unless empty)."""
    n = adjacency.shape[0]
    slots = pending.shape[0]
    for i in range(first, last):
        for j in range(n):
            overdue = adjacency[i, j] and iteration - last_delivered[i, j] >= max_gap
            sent = up[i, j] and (kept.shape[0] == 0 or kept[i, j])
            forced[i, j] = overdue and not sent
            sent = sent or overdue
            delivered[i, j] = sent
            if sent:
                last_delivered[i, j] = iteration
                due = iteration + (delay[i, j] if delay.shape[0] else 0)
                slot = due % slots
                pending[slot, round_index, i, j, :] = thetas[j, :]
                pending_sent[slot, round_index, i, j] = iteration
                pending_due[slot, round_index, i, j] = due
                if sums.shape[0]:
                    pending_sums[slot, round_index, i, j, :] = sums[j, :]


@njit(parallel=True, cache=True)
def _receive_parallel(*args):
    """`_receive_links` of every row, ROWS at a time in parallel (`args`: its own, less first and last)."""
    n = args[0].shape[0]
    for chunk in prange((n + ROWS - 1) // ROWS):
        _receive_links(*args, chunk * ROWS, min(n, (chunk + 1) * ROWS))


@njit(cache=True)
def _receive_links(
    adjacency,
    iteration,
    round_index,
    rounds,
    latest_rule,
    pending,
    pending_sent,
    pending_due,
    latest,
    latest_stamp,
    used_sent,
    arrived,
    use,
    first,
    last,
):
    """Mixer._received's bookkeeping per link of rows first..last-1, on one slot's (N, N[, M]) buffers: arrivals are
    consumed, a newer arrival (stamp l R + r) becomes the link's latest value, and `use` says which links mix a
    neighbour value: the arrived ones (stale=arrival) or those holding any (stale=latest)."""
    n, m = latest.shape[0], latest.shape[2]
    for i in range(first, last):  # selects rather than branches: arrivals come in no order a branch predictor learns
        for j in range(n):
            sent = pending_sent[i, j]
            here = adjacency[i, j] and pending_due[i, j] == iteration
            arrived[i, j] = here
            pending_due[i, j] = -1 if here else pending_due[i, j]  # consumed
            stamp = sent * rounds + round_index
            newer = here and stamp > latest_stamp[i, j]
            for k in range(m):
                latest[i, j, k] = pending[i, j, k] if newer else latest[i, j, k]
            held = stamp if newer else latest_stamp[i, j]
            latest_stamp[i, j] = held
            if latest_rule:
                use[i, j] = held >= 0
                used_sent[i, j] = held // rounds if held >= 0 else -1
            else:
                use[i, j] = here
                used_sent[i, j] = sent if here else -1


@njit(parallel=True, cache=True)
def _mix_used_parallel(weights, adjacency, use, neighbour, own, out):
    """`_mix_used` of every row, ROWS at a time in parallel."""
    chunks = (own.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _mix_used(weights, adjacency, use, neighbour, own, out, chunk * ROWS, min(own.shape[0], (chunk + 1) * ROWS))


@njit(cache=True)
def _mix_used(weights, adjacency, use, neighbour, own, out, first, last):
    """Rows first..last-1 of sum_j e^{ij}_m v^{ij}_m for M > 1, with e^{ij} = a^{ij}, v^{ij} = neighbour^{ij} on the links in `use`,
    e^{ii} = a^{ii} + idle^i (idle: the weights of the links not in use, summed over j in order) and v^{ii} = own^i:
    numpy's einsum and sums of `mix_numpy`, bit for bit (see `mix_linked`: terms of +0.0 are left out)."""
    n, m = own.shape
    for i in range(first, last):
        for k in range(m):
            idle = 0.0
            for j in range(n):
                a = weights[i, j, k]  # loaded either way, so that the choices below need no branch
                idle += a if adjacency[i, j] and not use[i, j] else 0.0  # + 0.0 leaves a sum >= +0.0 as it is
            diagonal = weights[i, i, k] + idle
            total = 0.0
            for j in range(i):  # a term not in use is +0.0 (a * 0.0): left out, even where a * value is not finite
                term = weights[i, j, k] * neighbour[i, j, k]
                total += term if use[i, j] else 0.0
            total += diagonal * own[i, k]
            for j in range(i + 1, n):
                term = weights[i, j, k] * neighbour[i, j, k]
                total += term if use[i, j] else 0.0
            out[i, k] = total


class Links:
    """The links of row i of A with the diagonal, in order of j (compressed rows), and their weights a^{ij}_m."""

    def __init__(self, network: Network):
        n = network.robots
        linked = network.adjacency | np.eye(n, dtype=bool)
        receiver, sender = np.nonzero(linked)  # row by row, j increasing
        self.starts = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(linked.sum(axis=1), out=self.starts[1:])
        self.senders = sender.astype(np.int64)
        self.own = np.flatnonzero(receiver == sender)  # where each row's diagonal entry sits
        self.weights = np.ascontiguousarray(network.weights[receiver, sender])  # (links + N, M)


def mix_linked(network: Network, links: Links | None, own: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """sum_j a^{ij}_m v^{ij}_m with v^{ii} = own^i, v^{ij} = neighbour^j on links and 0 elsewhere: the einsum of
    `Mixer`'s general rules (`mix_used`), bit for bit. With M > 1 numpy's inner loop runs over m, so each sum over j is taken one term after
    the other, from 0.0; the terms off the links are a^{ij} * 0.0 = +0.0, which leave such a sum as it is (it is
    never -0.0), so the kernel adds the links alone. With M = 1 numpy's inner loop is the sum over j itself, in its
    own order: the very same einsum does it here."""
    n, m = own.shape
    if m == 1 or links is None:
        values = np.where(network.adjacency[:, :, None], neighbour[None, :, :], 0.0)
        values[np.arange(n), np.arange(n), :] = own
        return np.einsum("ijm,ijm->im", network.weights, values)
    out = np.empty((n, m))
    args = (
        links.starts,
        links.senders,
        links.own,
        links.weights,
        np.ascontiguousarray(own),
        np.ascontiguousarray(neighbour),
        out,
    )
    if len(links.senders) >= PARALLEL_ENTRIES:
        _mix_links_parallel(*args)
    else:
        _mix_links(*args, 0, n)
    return out


@njit(parallel=True, cache=True)
def _mix_links_parallel(starts, senders, diagonal, weights, own, neighbour, out):
    """`_mix_links` of every row, ROWS at a time in parallel (each row by one thread)."""
    chunks = (own.shape[0] + ROWS - 1) // ROWS
    for chunk in prange(chunks):
        _mix_links(
            starts, senders, diagonal, weights, own, neighbour, out, chunk * ROWS, min(own.shape[0], (chunk + 1) * ROWS)
        )


@njit(cache=True)
def _mix_links(starts, senders, diagonal, weights, own, neighbour, out, first, last):
    """`mix_linked` for M > 1, rows first..last-1: each robot's row summed over its links in order of j."""
    m = own.shape[1]
    for i in range(first, last):
        d = diagonal[i]
        for k in range(0, m - 1, 2):  # two parameters at a time: two independent chains of additions
            one, two = 0.0, 0.0
            for p in range(starts[i], d):
                j = senders[p]
                one += weights[p, k] * neighbour[j, k]
                two += weights[p, k + 1] * neighbour[j, k + 1]
            one += weights[d, k] * own[i, k]
            two += weights[d, k + 1] * own[i, k + 1]
            for p in range(d + 1, starts[i + 1]):
                j = senders[p]
                one += weights[p, k] * neighbour[j, k]
                two += weights[p, k + 1] * neighbour[j, k + 1]
            out[i, k], out[i, k + 1] = one, two
        if m % 2:
            k = m - 1
            total = 0.0
            for p in range(starts[i], d):
                total += weights[p, k] * neighbour[senders[p], k]
            total += weights[d, k] * own[i, k]
            for p in range(d + 1, starts[i + 1]):
                total += weights[p, k] * neighbour[senders[p], k]
            out[i, k] = total
