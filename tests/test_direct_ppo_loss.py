"""DirectPPOLoss computes TorchRL's ClipPPOLoss: its losses, diagnostics and gradients on the
same parameters, for categorical and Gaussian policies."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import AddStateIndependentNormalScale
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss

from rlpipe.algos.direct import DirectPPOLoss
from rlpipe.models import TensorModule, mlp


def _ppo(cls: type, discrete: bool, **kwargs) -> tuple[ClipPPOLoss, ProbabilisticActor]:
    torch.manual_seed(4)
    if discrete:
        net = TensorModule(mlp(4, 3, (16,)), ["observation"], ["logits"])
        actor = ProbabilisticActor(
            net,
            in_keys=["logits"],
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,
        )
    else:
        head = nn.Sequential(
            mlp(4, 2, (16,)), AddStateIndependentNormalScale(2, scale_mapping="exp")
        )
        actor = ProbabilisticActor(
            TensorModule(head, ["observation"], ["loc", "scale"]),
            in_keys=["loc", "scale"],
            out_keys=["sample"],
            distribution_class=IndependentNormal,
            distribution_kwargs={"upscale": 1.0},
            return_log_prob=True,
        )
    critic = ValueOperator(mlp(4, 1, (16,)), in_keys=["observation"])
    loss = cls(actor, critic, loss_critic_type="l2", normalize_advantage=True, **kwargs)
    if not discrete:
        loss.set_keys(action="sample")
    return loss, actor


def _ppo_batch(actor: ProbabilisticActor, n: int = 64) -> TensorDict:
    g = torch.Generator().manual_seed(6)
    batch = TensorDict(observation=torch.randn(n, 4, generator=g), batch_size=[n])
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        actor(batch)
    batch["advantage"] = torch.randn(n, 1, generator=g)
    batch["value_target"] = torch.randn(n, 1, generator=g)
    return batch.exclude("logits", "loc", "scale")


@pytest.mark.parametrize("discrete", [True, False])
@pytest.mark.parametrize("entropy", [True, False])
def test_the_direct_forward_is_clipppoloss(discrete, entropy):
    kwargs = dict(clip_epsilon=0.1, entropy_bonus=entropy, entropy_coeff=0.05, critic_coeff=0.7)
    theirs, actor = _ppo(ClipPPOLoss, discrete, functional=False, **kwargs)
    ours, _ = _ppo(DirectPPOLoss, discrete, **kwargs)
    ours.load_state_dict(theirs.state_dict())
    batch = _ppo_batch(actor)
    with torch.no_grad():  # a policy moved away from the one that sampled: some ratios clip
        for p in theirs.actor_network.parameters():
            p.add_(0.3 * torch.randn_like(p))
    ours.load_state_dict(theirs.state_dict())
    a, b = theirs(batch.clone()), ours(batch.clone())
    keys = ["loss_objective", "loss_critic", "clip_fraction", "kl_approx"]
    for key in keys + (["loss_entropy", "entropy"] if entropy else []):
        torch.testing.assert_close(b[key], a[key])
    assert 0 < float(b["clip_fraction"]) < 1
    for loss, out in ((theirs, a), (ours, b)):
        loss.zero_grad()
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    for ga, gb in zip(
        [p.grad for p in theirs.parameters()], [p.grad for p in ours.parameters()], strict=True
    ):
        torch.testing.assert_close(gb, ga)


def test_the_ppo_diagnostics_are_torchrls():
    kwargs = dict(entropy_bonus=False)
    theirs, actor = _ppo(ClipPPOLoss, True, functional=False, log_explained_variance=True, **kwargs)
    ours, _ = _ppo(DirectPPOLoss, True, **kwargs)
    ours.load_state_dict(theirs.state_dict())
    batch = _ppo_batch(actor)
    b = ours(batch.clone())
    torch.testing.assert_close(b["explained_variance"], theirs(batch.clone())["explained_variance"])
    entropy = actor.get_dist(actor.module[0](batch.clone())).entropy().mean()
    torch.testing.assert_close(b["entropy"], entropy)
    assert "loss_entropy" not in b.keys()


def test_the_ppo_comparison_can_fail():
    theirs, actor = _ppo(ClipPPOLoss, True, functional=False, clip_epsilon=0.2)
    ours, _ = _ppo(DirectPPOLoss, True, clip_epsilon=0.2)
    batch = _ppo_batch(actor)
    with torch.no_grad():
        for p in theirs.critic_network.parameters():
            p.add_(0.5)
    with pytest.raises(AssertionError):
        torch.testing.assert_close(
            ours(batch.clone())["loss_critic"], theirs(batch.clone())["loss_critic"]
        )
