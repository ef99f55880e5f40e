"""Gradient tracking (team.order=gradient_tracking: DIGing, MD-PGT without momentum) inside the Mixer's rounds.

The trackers y and the push-sum weights v ride in theta's messages as running sums: S^j, the sum of every [y, v]
robot j has sent in a round slot, and rho^{ij}, the newest S^j robot i has taken in. A message newer than rho^{ij}
hands over all the mass sent on the link since then, so a dropped or delayed tracker is late, never lost or
counted twice; `in_flight` is the mass sent but not yet taken in. `engine.team.mixer.Mixer.track` runs the rounds;
a Ray robot mixes its own row by the same rule (`run.ray_robot.RobotCore`).

At iteration l, y^i_l = z^i_{l-1} + Delta^i_l - Delta^i_{l-1}, with z_{-1} = Delta_{-1} = 0 so that y_0 = Delta_0;
the rounds mix (theta, y, v) and keep z_l = A y_l and A v_l for the next iteration, and the step is theta_{l+1} =
A theta_l + eps_l y_l / v_l. Mixed as running sums, sum_i y^i_l plus the tracker mass still in flight equals
sum_i Delta^i_l under any delays, drops and switching, as long as A is doubly stochastic (checked when the network is
built). Without delays and drops v stays 1 and this is DIGing's y_{l+1} = A y_l + Delta_{l+1} - Delta_l exactly;
with them, dividing by v (v_0 = 1) undoes the bursts of late mass (a link that delivers three iterations of tracker
at once delivers three iterations of weight too), the push-sum correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class Tracking:
    """Gradient tracking's part of the Mixer's state: trackers y and push-sum weights v ride in the same messages as
    theta, as running sums; the last axis of each holds [y (M), v (M)]."""

    pending_sums: np.ndarray  # (B0+1, R, N, N, 2M): the sender's running sums in each message in flight
    sums: np.ndarray  # (R, N, 2M): S^j, the sum of all [y, v] robot j has sent in round r
    seen_sums: np.ndarray  # (R, N, N, 2M): rho^{ij}, the newest S^j robot i has taken in
    seen_sent: np.ndarray  # (R, N, N): its send iteration, -1 = none yet
    tracker: np.ndarray  # (N, 2M): [z^i_{l-1}, v^i_l], robot i's mixed tracker and push-sum weight
    gradient: np.ndarray  # (N, M): Delta^i_{l-1}, the gradient last added to the tracker

    @classmethod
    def empty(cls, slots: int, rounds: int, n: int, m: int) -> Tracking:
        """Nothing sent yet: zero trackers and gradients, push-sum weights 1."""
        return cls(
            pending_sums=np.zeros((slots, rounds, n, n, 2 * m)),
            sums=np.zeros((rounds, n, 2 * m)),
            seen_sums=np.zeros((rounds, n, n, 2 * m)),
            seen_sent=np.full((rounds, n, n), -1, dtype=np.int64),
            tracker=np.concatenate([np.zeros((n, m)), np.ones((n, m))], axis=1),
            gradient=np.zeros((n, m)),
        )


def carried(state: Tracking, grads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What each robot carries into iteration l's first round: its tracker y^i_l = z^i_{l-1} + Delta^i_l -
    Delta^i_{l-1} (z_{-1} = Delta_{-1} = 0, so y_0 = Delta_0) and its push-sum weight v^i_l."""
    m = grads.shape[1]
    return state.tracker[:, :m] + (grads - state.gradient), state.tracker[:, m:]


def mix_sums(
    state: Tracking,
    weights: np.ndarray,
    slot: int,
    round_index: int,
    sent: np.ndarray,
    arrived: np.ndarray,
    carried: np.ndarray,
) -> np.ndarray:
    """Trackers after one round, mixed as running sums: robot i takes a^{ij} (S^j - rho^{ij}) from each link whose
    message arrived now (`arrived`, (N, N)) and is newer than rho^{ij} (`sent`: its send iteration); an older
    message arriving after a newer one is ignored. The messages are those of arrival `slot` and `round_index`. With
    no delays or drops the increment is a^{ij} y^j: the plain A y of DIGing."""
    fresh = arrived & (sent > state.seen_sent[round_index])
    sums = state.pending_sums[slot, round_index]
    seen = state.seen_sums[round_index]
    increment = np.where(fresh[:, :, None], sums - seen, 0.0)
    seen[fresh] = sums[fresh]
    state.seen_sent[round_index] = np.where(fresh, sent, state.seen_sent[round_index])
    w = np.concatenate([weights] * (carried.shape[1] // weights.shape[2]), axis=2)
    diagonal = np.arange(len(w))
    off = w.copy()
    off[diagonal, diagonal, :] = 0.0
    return w[diagonal, diagonal, :] * carried + np.einsum("ijm,ijm->im", off, increment)


def in_flight(state: Tracking, weights: np.ndarray, adjacency: np.ndarray) -> np.ndarray:
    """(2M,) tracker and push-sum weight mass sent but not yet taken in, [y part, v part]: the sum over rounds and
    links of a^{ij} (S^j - rho^{ij})."""
    owed = state.sums[:, None, :, :] - state.seen_sums  # (R, N, N, 2M): [r, i, j] what j sent that i lacks
    links = adjacency[None, :, :, None]
    return (np.where(links, owed, 0.0) * np.concatenate([weights, weights], axis=2)[None]).sum(axis=(0, 1, 2))
