"""benchmarks/breakdown.py's sorting of sampled stacks into the parts of the training step, and
same_learning.py's reading back of finished runs."""

from __future__ import annotations

import importlib
import json

import pytest
from conftest import benchmarks_importable

STEP = "train_step (rlpipe/algos/offpolicy.py:101)"


@pytest.fixture(scope="module")
def bench():
    with benchmarks_importable():
        yield importlib.import_module("breakdown"), importlib.import_module("same_learning")


@pytest.mark.parametrize(
    ("stack", "part"),
    [
        (["main (rlpipe/cli.py:10)", "build (rlpipe/algos/dqn.py:80)"], None),  # not a step
        ([STEP], "loop"),  # the step's own frame is no target update (…_step (…offpolicy.py)
        ([STEP, "step (rlpipe/algos/offpolicy.py:150)"], "target update"),
        ([STEP, "ForeachSoftUpdate.step (rlpipe/algos/offpolicy.py:150)"], "target update"),
        ([STEP, "SoftUpdate.step (torchrl/objectives/utils.py:9)"], "target update"),
        ([STEP, "OffPolicy.train_step (rlpipe/algos/offpolicy.py:101)"], "loop"),
        (
            [STEP, "Direct.forward (rlpipe/algos/direct.py:91)", "td0_target (rlpipe/x.py:3)"],
            "value estimator",
        ),
        (
            [STEP, "forward (rlpipe/algos/direct.py:91)", "forward (torch/nn/modules/linear.py:1)"],
            "loss forward",
        ),
        (
            [
                STEP,
                "forward (rlpipe/algos/direct.py:91)",
                "td0_target (torchrl/objectives/value/advantages.py:3)",
            ],
            "value estimator",
        ),
        (
            [STEP, "collect (rlpipe/algos/collectors.py:5)", "step (gymnasium/vector/sync.py:9)"],
            "env step",
        ),
        (
            [STEP, "collect (rlpipe/algos/collectors.py:5)", "forward (torch/nn/modules/x.py:1)"],
            "collection",
        ),
        (
            [
                STEP,
                "backward (torch/_tensor.py:600)",
                "_engine_run_backward (torch/autograd/graph.py:8)",
            ],
            "backward",
        ),
        ([STEP, "step (torch/optim/adam.py:2)"], "optimizer"),
    ],
)
def test_each_sampled_stack_goes_to_its_innermost_part(bench, stack, part):
    breakdown, _ = bench
    assert breakdown.part(stack) == part


def test_a_finished_run_is_read_back_not_run_again(bench, tmp_path):
    _, same = bench
    run = tmp_path / "now" / "dqn_cartpole" / "0"
    scalars = run / "metrics" / "scalars"
    for folder in ("time", "train"):
        (scalars / folder).mkdir(parents=True)
    (run / "summary.json").write_text(json.dumps({"eval_mean": 480.5, "frames": 50_000}))
    (scalars / "time" / "train_seconds.csv").write_text("50000,21.5\n")
    # episodes that ended in the last 20% of the frames are the late ones
    (scalars / "train" / "episode_return.csv").write_text("30000,10\n40001,300\n49000,500\n")
    result = same.run("/nonexistent/python", [], "dqn_cartpole", 0, run)  # would fail if run
    assert (result["eval_mean"], result["train_seconds"], result["ran"]) == (480.5, 21.5, False)
    assert result["late_return"] == 400.0


def test_the_load_line_says_runs_were_read_back_only_when_some_were(bench):
    _, same = bench
    assert same.ran_note({1: {"ran": True}, 2: {"ran": True}}) == "2 of 2 runs ran in this call"
    assert same.ran_note({1: {"ran": True}, 2: {"ran": False}}) == (
        "1 of 2 runs ran in this call; the others were read back from --out"
    )
