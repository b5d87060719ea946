"""ARS starts (algo.starts): the turns, the halvings, the leader in the policy, and resuming."""

from __future__ import annotations

import io
import re
from functools import partial

import pytest
import torch
from torch import nn
from torch.nn.utils import parameters_to_vector

from rlpipe.algos import ARS, ARSConfig
from rlpipe.algos.ars.starts import Starts
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env

CARTPOLE = EnvConfig(id="CartPole-v1", backend="gymnasium")
WEIGHT = "module.1.module.weight"  # the linear policy's, behind the normaliser


def test_turns_go_to_the_fewest_steps_and_halvings_keep_the_best_scores():
    policy = nn.Linear(2, 1, bias=False)
    nn.init.zeros_(policy.weight)
    starts = Starts(count=4, until=0.5, window=2)
    assert starts.rungs == 2
    # candidate k always returns 10 * k and moves its weight to k; k=0 takes longer episodes
    done, turns = 0.0, []
    while len(starts.live) > 1 and done < 1:  # bounded: a halving that never comes fails below
        starts.next_turn(policy)
        k = starts.turn
        turns.append(k)
        with torch.no_grad():
            policy.weight.fill_(k)
        steps = 30 if k == 0 else 10
        done += 0.02
        live_before = list(starts.live)
        starts.record(policy, 10.0 * k, steps, done)
        # the leader (best score among the live) is what the policy holds between turns
        scored = [j for j in starts.live if starts.returns[j]]
        assert policy.weight[0, 0].item() == starts.leader == max(scored)
        if len(starts.live) < len(live_before):
            assert done >= 0.25
    assert turns[:4] == [0, 1, 2, 3]  # all at 0 steps: in order
    assert turns.count(0) < turns.count(1)  # k=0 spends 3x the steps per turn
    assert starts.live == [3] and starts.halvings == 2 and done == pytest.approx(0.5)
    assert [bool(s) for s in starts.states] == [False, False, False, True]


def test_state_dict_round_trip_continues_the_same_turns():
    policy = nn.Linear(2, 1)
    starts = Starts(count=3, until=0.6)
    for i in range(4):
        starts.next_turn(policy)
        starts.record(policy, float(i % 3), 5 + i, 0.1 * i)
    saved = starts.state_dict()
    other = Starts(count=3, until=0.6)
    other.load_state_dict(saved)
    starts.next_turn(policy)
    copy_policy = nn.Linear(2, 1)
    other.next_turn(copy_policy)
    assert other.turn == starts.turn
    assert torch.equal(
        parameters_to_vector(policy.parameters()), parameters_to_vector(copy_policy.parameters())
    )


def _ars(**kw) -> ARS:
    torch.manual_seed(0)
    kw = {"total_frames": 3000, **kw}
    cfg = ARSConfig(num_directions=2, num_best=1, workers=1, **kw)
    return ARS(partial(make_env, CARTPOLE), cfg)


def test_a_start_the_budget_ends_before_its_turn_says_not_run(capsys):
    """A budget spent within the first iteration halves the starts before the second has run:
    its line says so, not a return of -inf."""
    algo = _ars(starts=2, starts_until=0.2, total_frames=10)
    algo.train_step()
    said = [line for line in capsys.readouterr().out.splitlines() if "ARS starts" in line]
    assert len(said) == 1 and said[0].endswith("; dropped not run)"), said
    assert "inf" not in said[0]


def test_ars_runs_starts_until_one_remains_and_resumes_exactly(capsys):
    algo = _ars(starts=4, starts_until=0.5)
    live = []
    for _ in range(10):
        metrics = algo.train_step()
        live.append(metrics["train/starts_live"])
        leader = algo.starts.states[algo.starts.leader]
        assert torch.equal(algo.policy.state_dict()[WEIGHT], leader[WEIGHT])
    assert live == sorted(live, reverse=True) and live[0] == 4 and live[-1] == 1
    # each halving says one line on the console: who stays, on what recent returns
    said = [line for line in capsys.readouterr().out.splitlines() if "ARS starts" in line]
    assert [line.split(" kept")[0] for line in said] == [
        "rlpipe: ARS starts: 2 of 4",
        "rlpipe: ARS starts: 1 of 2",
    ]
    assert re.search(
        r"frames \(recent returns [-\d.]+, [-\d.]+; dropped [-\d.]+, [-\d.]+\)$", said[0]
    )
    # resumed from a checkpoint after 5 steps: the same θ after 10
    half = _ars(starts=4, starts_until=0.5)
    for _ in range(5):
        half.train_step()
    buffer = io.BytesIO()
    torch.save(half.state_dict(), buffer)
    buffer.seek(0)
    resumed = _ars(starts=4, starts_until=0.5)
    resumed.load_state_dict(torch.load(buffer, weights_only=True))
    for _ in range(5):
        resumed.train_step()
    assert torch.equal(resumed.search.theta, algo.search.theta)
    assert resumed.starts.live == algo.starts.live and resumed.frames == algo.frames
    for run in (algo, half, resumed):
        run.close()


def test_one_start_is_the_plain_search():
    plain, one = _ars(), _ars(starts=1)
    for _ in range(3):
        assert plain.train_step().keys() == one.train_step().keys()
    assert one.starts is None and "starts" not in one.state_dict()
    assert torch.equal(plain.search.theta, one.search.theta)
    plain.close()
    one.close()
