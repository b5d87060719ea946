"""DirectDQNLoss computes DQNLoss's loss, gradients and priorities, on the same parameters, and
stays bound to them through target updates and checkpoint loads."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Categorical
from torchrl.modules import QValueActor
from torchrl.objectives import DQNLoss

from rlpipe.algos.dqn_loss import DirectDQNLoss
from rlpipe.algos.offpolicy import ForeachSoftUpdate
from rlpipe.models import TensorModule, mlp


def _actor() -> QValueActor:
    net = mlp(4, 3, (16, 16))
    return QValueActor(TensorModule(net, ["observation"], ["action_value"]), spec=Categorical(3))


def _batch(n: int = 64, steps: bool = True) -> TensorDict:
    g = torch.Generator().manual_seed(1)
    data = {
        "observation": torch.randn(n, 4, generator=g),
        "action": torch.randint(0, 3, (n,), generator=g),
        "next": {
            "observation": torch.randn(n, 4, generator=g),
            "reward": torch.randn(n, 1, generator=g),
            "terminated": torch.rand(n, 1, generator=g) < 0.2,
            "done": torch.rand(n, 1, generator=g) < 0.3,
        },
    }
    if steps:
        data["steps_to_next_obs"] = torch.randint(1, 4, (n, 1), generator=g)
    return TensorDict(data, batch_size=[n])


@pytest.mark.parametrize("double_dqn", [True, False])
@pytest.mark.parametrize("loss_function", ["smooth_l1", "l2"])
@pytest.mark.parametrize("steps", [True, False])
def test_the_direct_forward_is_dqnloss(double_dqn, loss_function, steps):
    kwargs = dict(delay_value=True, double_dqn=double_dqn, loss_function=loss_function)
    theirs = DQNLoss(_actor(), action_space=Categorical(3), **kwargs)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), **kwargs)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    with torch.no_grad():  # targets apart from the online network: double DQN matters
        for p in theirs.target_value_network_params.values(True, True):
            p.add_(0.1 * torch.randn_like(p))
    ours.load_state_dict(theirs.state_dict())  # copies into the tensors the copies are bound to
    for _ in range(3):
        batch_a, batch_b = _batch(steps=steps), _batch(steps=steps)
        a, b = theirs(batch_a)["loss"], ours(batch_b)["loss"]
        torch.testing.assert_close(b, a)
        torch.testing.assert_close(batch_b["td_error"], batch_a["td_error"])
        for loss, value in ((theirs, a), (ours, b)):
            loss.zero_grad()
            value.backward()
        grads_a = [p.grad for p in theirs.parameters()]
        grads_b = [p.grad for p in ours.parameters()]
        assert all(g is not None for g in grads_b)
        for ga, gb in zip(grads_a, grads_b, strict=True):
            torch.testing.assert_close(gb, ga)
        for loss in (theirs, ours):  # a step and a target update: both stay bound
            with torch.no_grad():
                for p in loss.parameters():
                    p.sub_(0.05 * p.grad)
            ForeachSoftUpdate(loss, tau=0.5).step()


def test_a_wrong_target_fails_the_comparison():
    """The comparison can fail: a DirectDQNLoss whose target is a step behind differs."""
    theirs = DQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    ours.load_state_dict(theirs.state_dict())
    with torch.no_grad():
        for p in theirs.target_value_network_params.values(True, True):
            p.add_(0.1)
    with pytest.raises(AssertionError):
        torch.testing.assert_close(ours(_batch())["loss"], theirs(_batch())["loss"])


def test_a_deep_copy_is_bound_to_its_own_parameters():
    loss = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    twin = copy.deepcopy(loss)
    torch.testing.assert_close(twin(_batch())["loss"], loss(_batch())["loss"])
    with torch.no_grad():
        for p in twin.parameters():
            p.add_(1.0)
    assert not torch.allclose(twin(_batch())["loss"], loss(_batch())["loss"])
