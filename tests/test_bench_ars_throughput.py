"""benchmarks/common.py's time_ars (ars_throughput.py, ars_ray_scaling.py): rlpipe's ARS with
the notebook's settings, as the reference loop has them, not the preset the main job picks."""

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
