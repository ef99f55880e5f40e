"""Consensus rounds (riskplan.engine.team.mixer, paper eq. 14 under Assumption 5): mixing on fixed graphs at the SLEM
rate, delays and drops within their bounds (against a reference simulation), switching links, the same numbers for
the same seed and after a restore, and bad shapes; huge integer keys do not overflow."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from support import net_of, run_rounds, setup_of, team_conf

from riskplan.engine.team.convergence import consensus_error
from riskplan.engine.team.mixer import MIX_STREAM, Mixer
from riskplan.engine.team.network import build_network

# ---------------------------------------------------------------------------------------------- fixed-graph mixing


def log_slope(errors):
    """Per-round contraction fitted on the part of a decay curve above rounding noise."""
    errors = np.asarray(errors)
    keep = np.nonzero(errors > errors[0] * 1e-11)[0]
    k = keep[(keep >= 5)]
    slope = np.polyfit(k, np.log(errors[k]), 1)[0]
    return math.exp(slope)


@pytest.mark.parametrize(
    "kw",
    [
        {"graph": "line", "robots": 5},
        {"graph": "ring", "robots": 6},
        {"graph": "star", "robots": 5},
        {"graph": "grid", "robots": 6},
        {"graph": "ring", "robots": 5, "directed": True, "weights": "lazy"},
        {"graph": "line", "robots": 4, "weights": "lazy"},
    ],
)
def test_consensus_error_decays_at_slem_rate(kw):
    team = team_conf(**kw)
    net = build_network(team, 2, 0)
    theta = np.random.default_rng(5).normal(size=(kw["robots"], 2)) * 10
    errors = [consensus_error(t) for t in run_rounds(net, team, theta, 120)]
    assert log_slope(errors) == pytest.approx(net.slem, abs=0.02)


def test_complete_graph_agrees_in_one_round():
    team = team_conf(robots=5, graph="complete", weights="max_degree")
    theta = np.random.default_rng(0).normal(size=(5, 3))
    out = Mixer(build_network(team, 3, 0), team, 0).mix(theta, 0)
    assert consensus_error(out) < 1e-12 and np.allclose(out[0], theta.mean(axis=0))


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_no_delay_no_drop_is_exactly_the_matrix_product(stale):
    support = net_of(robots=4, graph="ring").adjacency | np.eye(4, dtype=bool)
    diag = (np.random.default_rng(1).random((4, 4, 2)) + 0.1) * support[:, :, None]  # different per parameter
    diag /= diag.sum(axis=1, keepdims=True)
    team = team_conf(robots=4, graph="ring", diagonal=diag.tolist(), stale=stale)
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 0), np.random.default_rng(2).normal(size=(4, 2))
    for l in range(5):
        expected = np.einsum("ijm,jm->im", net.weights, theta)
        theta = mixer.mix(theta, l)
        assert np.allclose(theta, expected, rtol=0, atol=1e-14)


def test_doubly_stochastic_weights_keep_the_average():
    team = team_conf(robots=7, graph="grid", consensus_rounds=3)
    net = build_network(team, 2, 0)
    theta = np.random.default_rng(3).normal(size=(7, 2))
    for t in run_rounds(net, team, theta, 20, rounds=3):
        assert np.allclose(t.mean(axis=0), theta.mean(axis=0), atol=1e-12)


# ---------------------------------------------------------------------------------------------- delays and drops


def gaps(times_by_link, start=-1):
    """Largest gap between consecutive event iterations per link, counting from `start`."""
    return max(np.diff([start] + times).max() for times in times_by_link.values())


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_delays_and_drops_still_reach_consensus_and_respect_bounds(stale):
    b0, b = 3, 4
    team = team_conf(robots=6, graph="ring", delay={"max": b0}, drop=0.5, max_gap=b, stale=stale)
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 11), np.random.default_rng(4).normal(size=(6, 2)) * 10
    start = consensus_error(theta)
    links = list(zip(*np.nonzero(net.adjacency)))
    delivered = {link: [] for link in links}
    used = {link: [] for link in links}
    delays, forced = [], 0
    for l in range(400):
        theta = mixer.mix(theta, l)
        for link in links:
            if mixer.delivered[link]:
                delivered[link].append(l)
            sent = mixer.used_sent[link]
            if sent >= 0:
                used[link].append(l)
                delays.append(l - sent)
        forced += mixer.forced.sum()
    assert consensus_error(theta) < 1e-8 * start
    assert gaps(delivered) <= b  # Assumption 5 (3): a delivered send at least every B iterations
    assert forced > 0  # with drop 0.5 and B = 4 the guarantee had to step in
    if stale == "arrival":
        assert min(delays) == 0 and max(delays) == b0  # Assumption 5 (4): delays on 0..B0
        assert gaps(used) <= b + b0  # so every link is heard at least every B + B0 iterations
    else:
        assert min(delays) == 0 and max(delays) <= b + b0  # the newest value held is never older than B + B0


def test_arrival_rule_matches_a_reference_simulation():
    """Newest message on a link wins; a silent neighbour's weight goes to the robot itself."""
    n, b0, b, p, seed = 3, 3, 3, 0.4, 9
    team = team_conf(robots=n, graph="line", delay={"max": b0}, drop=p, max_gap=b)
    net = build_network(team, 1, seed)
    w = net.weights[:, :, 0]
    links = list(zip(*np.nonzero(net.adjacency)))
    mixer, theta = Mixer(net, team, seed), np.array([[0.0], [10.0], [-5.0]])
    ref, inflight, last = theta.copy(), [], {link: -1 for link in links}
    several = 0
    for l in range(60):
        rng = np.random.default_rng([seed, MIX_STREAM, l, 0])
        delay = rng.integers(0, b0 + 1, size=(n, n))
        kept = rng.random((n, n)) >= p
        for i, j in links:
            if kept[i, j] or l - last[(i, j)] >= b:
                last[(i, j)] = l
                inflight.append((l + delay[i, j], l, i, j, ref[j].copy()))
        new = np.zeros_like(ref)
        for i in range(n):
            new[i] = w[i, i] * ref[i]
            for j in np.nonzero(net.adjacency[i])[0]:
                msgs = [x for x in inflight if x[0] == l and x[2] == i and x[3] == j]
                several += len(msgs) > 1
                new[i] += w[i, j] * (max(msgs, key=lambda x: x[1])[4] if msgs else ref[i])
        inflight = [x for x in inflight if x[0] > l]
        ref, theta = new, mixer.mix(theta, l)
        assert np.allclose(theta, ref, rtol=0, atol=1e-12)
    assert several > 0  # the case "several arrive on one link" was exercised


def test_latest_rule_never_goes_back_in_time():
    team = team_conf(robots=4, graph="ring", delay={"max": 4}, drop=0.3, stale="latest")
    net = build_network(team, 2, 0)
    mixer, theta, previous = Mixer(net, team, 1), np.random.default_rng(0).normal(size=(4, 2)), None
    for l in range(50):
        theta = mixer.mix(theta, l)
        used = mixer.used_sent
        if previous is not None:
            assert (used >= previous).all()
        previous = used


# ---------------------------------------------------------------------------------------------- switching


def test_switching_union_over_window_has_every_link_and_consensus_holds():
    window = 4
    team = team_conf(robots=6, graph="ring", switching={"enabled": True, "up": 0.3, "window": window})
    net = build_network(team, 2, 0)
    mixer, theta = Mixer(net, team, 2), np.random.default_rng(6).normal(size=(6, 2))
    ups = []
    for l in range(300):
        theta = mixer.mix(theta, l)
        ups.append(mixer.links_up(l).copy())
    ups = np.array(ups)
    assert np.array_equal(ups[0] & ~net.adjacency, np.zeros_like(net.adjacency))
    assert all(np.array_equal(ups[t], ups[t].T) for t in range(len(ups)))  # undirected links switch both ways
    for t in range(len(ups) - window + 1):
        assert np.array_equal(ups[t : t + window].any(axis=0), net.adjacency)
    fraction = ups[:, net.adjacency].mean()
    assert 0.3 <= fraction <= 0.6  # up with probability 0.3, plus the forced ups
    assert consensus_error(theta) < 1e-8


# ---------------------------------------------------------------------------------------------- determinism


def noisy_team(stale="arrival"):
    return team_conf(
        robots=5,
        graph="grid",
        delay={"max": 3},
        drop=0.3,
        max_gap=3,
        consensus_rounds=2,
        stale=stale,
        switching={"enabled": True, "up": 0.6, "window": 3},
    )


@pytest.mark.parametrize("stale", ["arrival", "latest"])
def test_same_seed_same_output_and_resume_is_bit_identical(stale, tmp_path):
    team = noisy_team(stale)
    net = build_network(team, 2, 0)
    theta0 = np.random.default_rng(7).normal(size=(5, 2))
    full = run_rounds(net, team, theta0, 30, seed=5, rounds=2)
    again = run_rounds(net, team, theta0, 30, seed=5, rounds=2)
    other = run_rounds(net, team, theta0, 30, seed=6, rounds=2)
    assert all(np.array_equal(a, b) for a, b in zip(full, again))
    assert not np.array_equal(full[-1], other[-1])

    mixer, theta = Mixer(net, team, 5), theta0
    for l in range(13):
        for r in range(2):
            theta = mixer.mix(theta, l, r)
    state = mixer.state()
    assert all(isinstance(v, np.ndarray) for v in state.values())
    np.savez(tmp_path / "ck.npz", **state)  # a checkpoint writer can store it as is
    loaded = dict(np.load(tmp_path / "ck.npz"))
    as_json = json.loads(json.dumps({key: value.tolist() for key, value in state.items()}))  # a JSON checkpoint
    for saved in (loaded, as_json):
        resumed, theta_r = Mixer(build_network(team, 2, 0), team, 5).restore(saved), theta
        for l in range(13, 30):
            for r in range(2):
                theta_r = resumed.mix(theta_r, l, r)
            assert np.array_equal(theta_r, full[l + 1])


def test_state_is_a_copy_and_restore_checks_shapes():
    team = noisy_team()
    net = build_network(team, 2, 0)
    mixer = Mixer(net, team, 0)
    state = mixer.state()
    state["pending"][...] = 99.0
    assert not (mixer.state()["pending"] == 99.0).any()
    other = team_conf(robots=4, graph="ring")
    with pytest.raises(ValueError):
        Mixer(build_network(other, 2, 0), other, 0).restore(state)


# ---------------------------------------------------------------------------------------------- bad shapes, huge keys


def test_mix_rejects_wrong_shapes_and_rounds():
    team = team_conf(robots=3, consensus_rounds=2)
    mixer = Mixer(build_network(team, 2, 0), team, 0)
    with pytest.raises(ValueError):
        mixer.mix(np.zeros((3, 3)), 0)
    with pytest.raises(ValueError):
        mixer.mix(np.zeros((3, 2)), 0, round_index=2)


def test_zero_range_integers_draw_nothing():
    """Mixer._send skips integers(0, 1) (delays with B0 = 0): it must not move the generator."""
    a = np.random.default_rng([1, 7919, 3, 0])
    a.integers(0, 1, size=(40, 40))
    assert np.array_equal(a.random((40, 40)), np.random.default_rng([1, 7919, 3, 0]).random((40, 40)))


def test_huge_gaps_and_windows_run():
    # integer keys far beyond int64 must not overflow numpy in the consensus layer
    big = 10**30
    setup = setup_of(
        "team.robots=3", f"team.max_gap={big}", "team.switching.enabled=true", f"team.switching.window={big}"
    )
    thetas = np.arange(6, dtype=float).reshape(3, 2)
    for l in range(3):
        assert np.all(np.isfinite(setup.mixer.mix(thetas, l)))
