"""ARS on Ray: the same search as the local backend, config plumbing, and the bad inputs."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from functools import partial

import pytest
import torch
from conftest import TINY, needs_extra

from rlpipe.algos import ARSConfig
from rlpipe.algos.ars import ARSSearch, RayConfig, make_ars_policy
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env
from rlpipe.errors import RlpipeError

CARTPOLE = EnvConfig(id="CartPole-v1")
RAY_OPTIONS = ["algo=ars", "algo.num_directions=2", "algo.num_best=2", "logger=none"]


@pytest.fixture(autouse=True)
def _ray_env(monkeypatch):
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")  # Ray would try to report usage
    monkeypatch.setenv("RAY_raylet_start_wait_time_s", "180")  # a busy machine starts slowly


def two_iterations(**backend) -> tuple[torch.Tensor, list, list]:
    """θ, episode returns and normaliser means after two iterations of a tiny search."""
    policy, normalizer = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    search = ARSSearch(
        policy,
        partial(make_env, CARTPOLE),
        num_directions=3,
        normalizer=normalizer,
        seed=5,
        **backend,
    )
    try:
        stats = [search.step() for _ in range(2)]
        if backend.get("backend") == "ray":  # started by the first step
            import ray

            assert ray.available_resources().get("CPU", 0) == 0  # the two actors hold both CPUs
    finally:
        search.close()
    return search.theta, [s["episode_return"] for s in stats], normalizer.mean.tolist()


def test_ray_backend_gives_the_same_search_as_the_local_backend():
    ray = needs_extra("ray", "ray")
    on_ray = two_iterations(backend="ray", workers=2, ray_num_cpus=2)
    assert not ray.is_initialized()  # the search shut down the Ray it started
    for local in (two_iterations(workers=1), two_iterations(workers=2)):
        assert torch.equal(local[0], on_ray[0]) and local[1] == on_ray[1]
        # one batch in this process merges the observation statistics in another order
        assert local[2] == pytest.approx(on_ray[2], rel=1e-12)


def test_ray_search_starts_ray_only_when_it_steps():
    ray = needs_extra("ray", "ray")
    policy, _ = make_ars_policy(make_env(CARTPOLE), ARSConfig())
    search = ARSSearch(policy, partial(make_env, CARTPOLE), backend="ray", ray_num_cpus=2)
    search.close()
    assert not ray.is_initialized()


def test_cli_trains_ars_on_ray(rlpipe_cli):
    needs_extra("ray", "ray")
    proc = rlpipe_cli(*TINY, *RAY_OPTIONS, "algo.backend=ray", "algo.ray.num_cpus=2")
    assert proc.returncode == 0, proc.stderr
    assert "final eval" in proc.stdout


def test_config_checks_and_rebuild():
    with pytest.raises(RlpipeError, match="algo.backend must be one of local, ray; got 'spark'"):
        ARSConfig(backend="spark")
    assert ARSConfig(ray={"address": "head:6379"}).ray == RayConfig(address="head:6379")


def one_error_line(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    return lines[0]


def test_ray_backend_without_ray_names_the_install_command(tmp_path):
    code = "import sys; sys.modules['ray'] = None; from rlpipe.__main__ import main; main()"
    proc = subprocess.run(
        [sys.executable, "-c", code, *TINY, *RAY_OPTIONS, "algo.backend=ray"],
        cwd=tmp_path,
        env={k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    line = one_error_line(proc)
    assert (
        line
        == 'rlpipe: error: the Ray backend needs Ray; install it with: pip install "rlpipe[ray]"'
    )


def test_unreachable_ray_address_is_one_line(rlpipe_cli):
    needs_extra("ray", "ray")
    with socket.socket() as sock:  # a loopback port nothing listens on
        sock.bind(("127.0.0.1", 0))
        address = f"127.0.0.1:{sock.getsockname()[1]}"
    proc = rlpipe_cli(*TINY, *RAY_OPTIONS, "algo.backend=ray", f"algo.ray.address={address}")
    line = one_error_line(proc)
    assert line.startswith(f"rlpipe: error: cannot reach a Ray cluster at {address} (")
