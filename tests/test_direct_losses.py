"""DirectDQNLoss and DirectSACLoss compute TorchRL's losses, gradients and priorities on the same
parameters, and stay bound to them through target updates, checkpoint loads and copies
(DirectPPOLoss: test_direct_ppo_loss.py)."""

from __future__ import annotations

import copy

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor
from torch import nn
from torchrl.data import Bounded, Categorical
from torchrl.modules import (
    MLP,
    ProbabilisticActor,
    QValueActor,
    TanhNormal,
)
from torchrl.objectives import DQNLoss, SACLoss

from rlpipe.algos.direct import (
    DirectDQNLoss,
    DirectSACLoss,
    tanh_normal_rsample,
    td0_target,
)
from rlpipe.algos.offpolicy import ForeachSoftUpdate
from rlpipe.encoders import EncodeFirst
from rlpipe.models import TensorModule, mlp

# TorchRL's losses serve here only as the reference a forward pass is compared with: none is
# given a target updater, which TorchRL warns about at every call.
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater:UserWarning")


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


@pytest.mark.parametrize("loss_function", ["smooth_l1", "l2", "l1"])
@pytest.mark.parametrize("reduction", ["mean", "sum", "none"])
@pytest.mark.parametrize("rows", ["plain", "weighted", "masked"])
def test_the_direct_dqn_loss_reduces_its_rows_as_dqnloss(loss_function, reduction, rows):
    """The one-op distance (no weights, no mask) and TorchRL's path (weights, a mask, no
    reduction) give DQNLoss's loss."""
    kwargs = dict(delay_value=True, loss_function=loss_function, reduction=reduction)
    theirs = DQNLoss(_actor(), action_space=Categorical(3), **kwargs)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), **kwargs)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    ours.load_state_dict(theirs.state_dict())
    batches = _batch(), _batch()
    for batch in batches:
        if rows == "weighted":
            batch["priority_weight"] = torch.linspace(0.1, 1.0, 64)
        if rows == "masked":
            batch["collector", "mask"] = torch.arange(64) % 3 != 0
    a, b = theirs(batches[0])["loss"], ours(batches[1])["loss"]
    assert b.shape == a.shape
    torch.testing.assert_close(b, a)


def test_a_terminal_state_bootstraps_nothing_whatever_its_value():
    """``r + γ^k V'`` where the episode goes on; ``r`` at a terminal state, even where ``V'`` is
    not finite there (TorchRL's ``(1 - terminated) · V'`` would give nan)."""
    loss = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    loss.make_value_estimator(gamma=0.9)
    batch = _batch(8)
    terminated = batch["next", "terminated"]
    assert terminated.any() and not terminated.all()
    next_value = torch.where(terminated, torch.nan, torch.ones(8, 1))
    expected = torch.where(
        terminated,
        batch["next", "reward"],
        batch["next", "reward"] + 0.9 ** batch["steps_to_next_obs"].float(),
    )
    torch.testing.assert_close(td0_target(loss, batch, next_value), expected)


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


def test_q_max_clamps_each_target_at_the_returns_ceiling():
    """``q_max`` turns each target above it (and only those) into ``q_max``: the priorities
    are ``(Q - min(r + γ^k max Q', q_max))²``; a ``q_max`` above every target is DQNLoss."""
    theirs = DQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    ours.load_state_dict(theirs.state_dict())
    batch = _batch()
    online, target = ours._networks()
    with torch.no_grad():
        chosen = online(batch["observation"]).gather(-1, batch["action"].unsqueeze(-1))
        bootstrap = target(batch["next", "observation"]).max(-1, keepdim=True).values
        targets = td0_target(ours, batch, bootstrap)
    ceiling = targets.median().item()
    assert (targets > ceiling).any() and (targets < ceiling).any()
    ours.q_max = ceiling
    ours(batch)
    expected = (chosen - targets.clamp(max=ceiling)).pow(2)
    torch.testing.assert_close(batch["td_error"], expected)
    assert not torch.allclose(batch["td_error"], (chosen - targets).pow(2))
    ours.q_max = targets.max().item() + 1.0
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


def _double(batch: TensorDict) -> TensorDict:
    return batch.apply(lambda x: x.double() if x.is_floating_point() else x)


def test_a_loss_cast_after_its_first_forward_binds_its_cast_parameters():
    """``double()`` (as ``to()`` and ``cuda()``) puts other tensors in the parameters' place:
    the direct forward then computes on those, as TorchRL's does."""
    theirs = DQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    ours.load_state_dict(theirs.state_dict())
    ours(_batch())  # bound to the float parameters
    theirs.double(), ours.double()
    out = ours(_double(_batch()))["loss"]
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, theirs(_double(_batch()))["loss"])
    sac = _sac(DirectSACLoss)
    sac(_sac_batch())
    assert sac.double()(_double(_sac_batch()))["loss_qvalue"].dtype == torch.float64


def test_a_load_after_the_first_forward_is_seen():
    """``load_state_dict`` copies into the bound parameters: no binding again is needed."""
    theirs = DQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    ours = DirectDQNLoss(_actor(), action_space=Categorical(3), delay_value=True)
    for loss in (theirs, ours):
        loss.make_value_estimator(gamma=0.9)
    with torch.no_grad():
        for p in theirs.parameters():
            p.add_(0.3)
    before = ours(_batch())["loss"]
    ours.load_state_dict(theirs.state_dict())
    after = ours(_batch())["loss"]
    assert not torch.allclose(after, before)
    torch.testing.assert_close(after, theirs(_batch())["loss"])


def _sac(cls: type, alpha_init: float = 0.7, encoded: bool = False) -> SACLoss:
    """SAC's losses; ``encoded``: the critic an encoder first (a network other than an MLP)."""
    torch.manual_seed(3)
    spec = Bounded(-2.0, 2.0, (1,))
    net = nn.Sequential(mlp(4, 2, (16, 16)), NormalParamExtractor("biased_softplus_1"))
    actor = ProbabilisticActor(
        TensorModule(net, ["observation"], ["loc", "scale"]),
        in_keys=["loc", "scale"],
        spec=spec,
        distribution_class=TanhNormal,
        distribution_kwargs={"low": spec.space.low, "high": spec.space.high},
    )
    critic = MLP(in_features=5, out_features=1, num_cells=[16, 16], activation_class=nn.ReLU)
    if encoded:
        critic = EncodeFirst(nn.Sequential(nn.Linear(4, 4), nn.Tanh()), critic)
    qvalue = TensorModule(critic, ["observation", "action"], ["state_action_value"])
    loss = cls(
        actor,
        qvalue,
        num_qvalue_nets=2,
        alpha_init=alpha_init,
        target_entropy=-1.0,
        loss_function="l2",
        deactivate_vmap=True,
    )
    loss.make_value_estimator(gamma=0.9)
    return loss


def _sac_batch(n: int = 64) -> TensorDict:
    batch = _batch(n, steps=False)
    batch["action"] = torch.rand(n, 1, generator=torch.Generator().manual_seed(2)) * 4 - 2
    return batch


@pytest.mark.parametrize("encoded", [False, True], ids=["mlp-critics", "encoded-critics"])
def test_the_direct_forward_is_sacloss(encoded):
    theirs, ours = _sac(SACLoss, encoded=encoded), _sac(DirectSACLoss, encoded=encoded)
    with torch.no_grad():  # targets apart from the critics
        for p in theirs.target_qvalue_network_params.values(True, True):
            p.add_(0.1 * torch.randn_like(p))
    ours.load_state_dict(theirs.state_dict())
    keys = ("loss_actor", "loss_qvalue", "loss_alpha", "alpha", "entropy")
    for step in range(3):
        batch_a, batch_b = _sac_batch(), _sac_batch()
        torch.manual_seed(step)  # the same random actions, drawn in the same order
        a = theirs(batch_a)
        torch.manual_seed(step)
        b = ours(batch_b)
        for key in keys:
            torch.testing.assert_close(b[key], a[key])
        torch.testing.assert_close(batch_b["td_error"], batch_a["td_error"])
        for loss, out in ((theirs, a), (ours, b)):
            loss.zero_grad()
            (out["loss_actor"] + out["loss_qvalue"] + out["loss_alpha"]).backward()
        for ga, gb in zip(
            [p.grad for p in theirs.parameters()], [p.grad for p in ours.parameters()], strict=True
        ):
            assert gb is not None
            torch.testing.assert_close(gb, ga)
        for loss in (theirs, ours):
            with torch.no_grad():
                for p in loss.parameters():
                    p.sub_(0.05 * p.grad)
            ForeachSoftUpdate(loss, tau=0.5).step()


def test_the_sac_comparison_can_fail():
    """Another entropy coefficient changes the actor's loss: the comparison sees it."""
    theirs, ours = _sac(SACLoss), _sac(DirectSACLoss, alpha_init=0.2)
    torch.manual_seed(0)
    a = theirs(_sac_batch())
    torch.manual_seed(0)
    with pytest.raises(AssertionError):
        torch.testing.assert_close(ours(_sac_batch())["loss_actor"], a["loss_actor"])


def test_a_copy_of_the_sac_loss_is_bound_to_its_own_parameters():
    loss = _sac(DirectSACLoss)
    twin = copy.deepcopy(loss)
    torch.manual_seed(0)
    first = loss(_sac_batch())["loss_qvalue"]
    torch.manual_seed(0)
    torch.testing.assert_close(twin(_sac_batch())["loss_qvalue"], first)
    with torch.no_grad():
        for p in twin.qvalue_network_params.values(True, True):
            p.add_(1.0)
    torch.manual_seed(0)
    assert not torch.allclose(twin(_sac_batch())["loss_qvalue"], first)


@pytest.mark.parametrize(
    "bounds", [(-1.0, 1.0), (-2.0, 2.0), (torch.tensor([-1.0, 0.0]), torch.tensor([3.0, 0.5]))]
)
def test_tanh_normal_rsample_is_torchrls(bounds):
    low, high = bounds
    loc = torch.randn(32, 2, requires_grad=True)
    scale = (torch.rand(32, 2) + 0.1).requires_grad_()
    torch.manual_seed(5)
    a, lp = TanhNormal(loc, scale, low=low, high=high).rsample_and_log_prob()
    torch.manual_seed(5)
    b, lq = tanh_normal_rsample(loc, scale, low, high)
    torch.testing.assert_close(b, a)
    torch.testing.assert_close(lq, lp)
    ga = torch.autograd.grad((a.sum() + lp.sum()), (loc, scale))
    gb = torch.autograd.grad((b.sum() + lq.sum()), (loc, scale))
    for x, y in zip(ga, gb, strict=True):
        torch.testing.assert_close(y, x)
