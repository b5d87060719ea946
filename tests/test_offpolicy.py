"""The off-policy loop's parts: the foreach soft target update is TorchRL's SoftUpdate, the
leaf-writing storage is TorchRL's LazyTensorStorage, and one batch of updates draws its
minibatches in one sample."""

from __future__ import annotations

from functools import partial

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.objectives import SoftUpdate

from rlpipe.algos import DQN, SAC, DQNConfig, SACConfig
from rlpipe.algos.storage import LeafStorage
from rlpipe.config import EnvConfig
from rlpipe.envs import make_env

SMALL = dict(batch_size=8, buffer_size=64, learning_starts=8, frames_per_batch=8)


@pytest.mark.parametrize(
    ("algo", "cfg", "env_id"),
    [(DQN, DQNConfig(**SMALL, tau=0.1), "CartPole-v1"), (SAC, SACConfig(**SMALL), "Pendulum-v1")],
    ids=["dqn", "sac"],
)
def test_the_foreach_target_update_is_torchrls_soft_update(algo, cfg, env_id):
    """Both updaters over copies of one loss, the online nets moved between steps: the targets
    stay equal step after step."""
    torch.manual_seed(0)
    ours = algo(partial(make_env, EnvConfig(id=env_id), seed=0), cfg)
    torch.manual_seed(0)
    reference = algo(partial(make_env, EnvConfig(id=env_id), seed=0), cfg)
    theirs = SoftUpdate(reference.loss, tau=cfg.tau)
    try:
        for step in range(3):
            for a, b in zip(ours.loss.parameters(), reference.loss.parameters(), strict=True):
                noise = torch.randn(a.shape, generator=torch.Generator().manual_seed(step))
                with torch.no_grad():
                    a.add_(noise)
                    b.add_(noise)
            ours.target_updater.step()
            theirs.step()
            mine = ours.loss.state_dict()
            for key, value in reference.loss.state_dict().items():
                if "target" in key:
                    torch.testing.assert_close(mine[key], value)
        assert any("target" in key for key in mine)  # the comparison above compared targets
    finally:
        ours.close()
        reference.close()


def test_a_batch_of_updates_takes_its_minibatches_from_one_draw(monkeypatch):
    torch.manual_seed(0)
    algo = DQN(partial(make_env, EnvConfig(num_envs=2), seed=0), DQNConfig(**SMALL))
    draws = []
    sample = algo.buffer.sample
    monkeypatch.setattr(algo.buffer, "sample", lambda n: draws.append(n) or sample(n))
    try:
        while not draws:
            algo.train_step()
        assert draws == [algo.cfg.updates_per_batch * algo.cfg.batch_size]
        steps = {int(s["step"]) for s in algo.optimizer.state.values()}
        assert steps == {algo.cfg.updates_per_batch}
    finally:
        algo.close()


def transitions(rows: int, start: int) -> TensorDict:
    """``rows`` transitions numbered from ``start`` (every leaf tells which row it is)."""
    n = torch.arange(start, start + rows)
    obs = n[:, None].float().expand(rows, 3)
    return TensorDict(
        {
            "observation": obs,
            "action": n[:, None] % 2,
            "next": {
                "observation": obs + 1,
                "reward": -n[:, None].float(),
                "done": n[:, None] % 3 == 0,
            },
        },
        [rows],
    )


def test_a_loaded_leaf_storage_lives_on_its_device():
    """A state dict read onto the CPU (as checkpoints are) loads onto the storage's device, where
    the next writes go. Meta stands for CUDA here, where a resumed run's first write failed (a
    CUDA check of sac_pendulum and dqn_cartpole resumed with compile=true)."""
    saved = ReplayBuffer(storage=LeafStorage(10))
    saved.extend(transitions(4, 0))
    resumed = ReplayBuffer(storage=LeafStorage(10, device="meta"))
    resumed.load_state_dict(saved.state_dict())
    assert len(resumed) == 4
    assert {leaf.device.type for leaf in resumed.storage._storage.values(True, True)} == {"meta"}


def test_the_leaf_storage_is_torchrls_lazy_tensor_storage():
    """Both buffers fed the same writes (single rows, several rows, past the end so that the
    writes wrap around) hold the same rows, report the same length, write the same state dict,
    and with the same seed draw the same samples; data with other keys takes TorchRL's path."""
    ours = ReplayBuffer(storage=LeafStorage(10))
    theirs = ReplayBuffer(storage=LazyTensorStorage(10))
    start = 0
    for rows in (1, 3, 1, 4, 6, 1, 2):
        batch = transitions(rows, start)
        start += rows
        assert torch.equal(ours.extend(batch), theirs.extend(batch))
        assert len(ours) == len(theirs)
        assert (ours[: len(ours)] == theirs[: len(theirs)]).all()
    assert len(ours) == 10 and ours[:]["observation"][:, 0].tolist() != list(range(10))
    mine, reference = ours.state_dict(), theirs.state_dict()
    assert mine.keys() == reference.keys() and str(mine) == str(reference)
    torch.manual_seed(1)
    drawn = ours.sample(32)
    torch.manual_seed(1)
    assert (drawn == theirs.sample(32)).all()
    other = transitions(1, 99).exclude(("next", "done"))  # not the storage's keys
    ours.extend(other)
    theirs.extend(other)
    assert (ours[:] == theirs[:]).all()
