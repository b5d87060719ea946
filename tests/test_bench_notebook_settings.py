"""The benchmarks that race rlpipe against the notebooks' loops run the notebooks' settings
(``~tuned``), not the tuned presets an algo x env pair picks by itself."""

from __future__ import annotations

import importlib

import pytest
from conftest import benchmarks_importable


class Built(Exception):
    """Raised in place of building the algorithm: the test needs its config only."""


def test_time_ars_runs_the_notebooks_settings(monkeypatch):
    with benchmarks_importable():
        common = importlib.import_module("common")
        hp = importlib.import_module("reference_ars").HP()

    def capture(env_fn, algo_cfg):
        raise Built(algo_cfg)

    monkeypatch.setattr(common, "make_algorithm", capture)
    with pytest.raises(Built) as built:
        common.time_ars(1, 1, "env.backend=gymnasium")
    algo = built.value.args[0]
    assert (algo.num_directions, algo.num_best) == (hp.num_deltas, hp.num_best_deltas)
    assert (algo.step_size, algo.noise) == (hp.learning_rate, hp.noise)
    assert algo.step_size_end is None and algo.episode_length == hp.episode_length


def test_reinforce_cartpoles_notebook_row_runs_the_notebooks_settings():
    """reinforce_cartpole.py's "notebook defaults" row: reference_reinforce.py's settings (no
    value baseline, Adam at 1e-3), not the preset that algo=reinforce env=cartpole_continuous
    picks by itself."""
    from rlpipe import compose_run

    with benchmarks_importable():
        overrides = importlib.import_module("reinforce_cartpole").CONTINUOUS["notebook defaults"]
    algo = compose_run(*overrides).algo
    assert (algo.baseline, algo.lr, algo.weight_decay) == ("none", 1e-3, 1e-4)
    assert (algo.episodes_per_epoch, algo.updates_per_epoch, algo.batch_size) == (100, 50, 128)
