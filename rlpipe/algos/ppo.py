"""PPO assembled from TorchRL parts: a ProbabilisticActor (collecting on plain tensors) and a
ValueOperator on the batched env, GAE advantages and ClipPPOLoss (its forward on plain tensors)
over minibatch epochs."""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives.value import GAE

from rlpipe.algos.base import LOSS, EnvAlgorithm, Metrics, episode_metrics
from rlpipe.algos.collectors import CollectAction
from rlpipe.algos.configs import PPOConfig
from rlpipe.algos.direct import LOG_SQRT_2PI, DirectPPOLoss, inner_network
from rlpipe.envs import is_discrete
from rlpipe.errors import check
from rlpipe.models import make_policy
from rlpipe.normalizer import Normalizer


def orthogonal_init(net: torch.nn.Module, last_gain: float) -> None:
    """Orthogonal weights (gain √2, ``last_gain`` for the last linear layer), zero biases."""
    layers = [m for m in net.modules() if isinstance(m, torch.nn.Linear)]
    for i, layer in enumerate(layers):
        torch.nn.init.orthogonal_(layer.weight, last_gain if i == len(layers) - 1 else math.sqrt(2))
        if layer.bias is not None:
            torch.nn.init.zeros_(layer.bias)


# what each iteration logs besides the loss (means over its gradient steps): the loss module's
# key -> the metric (SB3's names)
LOGGED = {
    "loss_objective": "train/policy_gradient_loss",
    "loss_critic": "train/value_loss",
    "entropy": "train/entropy",
    "kl_approx": "train/approx_kl",
    "clip_fraction": "train/clip_fraction",
    "explained_variance": "train/explained_variance",
}


def sampling_action(
    actor: ProbabilisticActor, env: EnvBase, log_prob_key: str, device: torch.device
) -> CollectAction:
    """:func:`~rlpipe.models.make_policy`'s sampling policy (``log_prob=True``) on plain
    tensors, computing what its distribution module does, with the same random draws: a
    Categorical draw from the logits and its log-probability, or a Gaussian draw (``sample``),
    its log-probability summed over the action's dimensions and the draw clipped into the
    bounds (``action``)."""
    net = inner_network(actor).module
    if is_discrete(env):

        def categorical(observation: torch.Tensor) -> dict[str, torch.Tensor]:
            logits = net(observation)
            log_probs = logits - logits.logsumexp(-1, keepdim=True)  # Categorical's own logits
            action = torch.multinomial(log_probs.softmax(-1), 1, True)
            log_prob = log_probs.gather(-1, action).squeeze(-1)
            return {"action": action.squeeze(-1), log_prob_key: log_prob}

        return categorical
    space = env.action_spec_unbatched.space
    low, high = space.low.to(device), space.high.to(device)

    def gaussian(observation: torch.Tensor) -> dict[str, torch.Tensor]:
        loc, scale = net(observation)
        sample = loc + torch.empty_like(loc).normal_() * scale  # Normal.rsample's draw
        log_density = -((sample - loc) ** 2) / (2 * scale**2) - scale.log() - LOG_SQRT_2PI
        return {
            "sample": sample,
            log_prob_key: log_density.sum(-1),
            "action": torch.clamp(sample, low, high),
        }

    return gaussian


class PPO(EnvAlgorithm):
    """Proximal policy optimisation (clipped) on a batched TorchRL env, discrete or continuous.

    Each :meth:`train_step` collects ``cfg.frames_per_batch`` frames with the sampling policy
    (rounded up to whole steps of the env's copies), computes GAE advantages and value targets
    with the critic, then runs ``cfg.epochs`` passes of Adam steps over shuffled minibatches of
    ``cfg.minibatch_size`` frames on TorchRL's ClipPPOLoss (gradient norm clipped at
    ``cfg.max_grad_norm``). Continuous actions: a Gaussian with a free log-std per dimension,
    clipped into the bounds. ``network`` (or ``cfg.network``): the actor's network.
    With ``cfg.ortho_init`` the default networks start as SB3's and CleanRL's do: orthogonal
    weights (gain √2 in the hidden layers, 0.01 in the actor's last, 1 in the critic's) and zero
    biases, so the first policy is close to uniform.
    """

    cfg: PPOConfig
    state_attrs = ("loss", "optimizer", "normalizer")
    compiled = ("loss",)
    activation = torch.nn.Tanh  # SB3's and the PPO paper's

    def _build(self, env: EnvBase) -> None:
        cfg, device = self.cfg, self.device
        check(
            self.observation.flat or not cfg.normalize_observations,
            "algo.normalize_observations=true standardises flat vector observations; this env's "
            f"are of shape {self.observation.shape}: set algo.normalize_observations=false",
        )
        self.normalizer = Normalizer(self.observation.size)  # the identity unless observed
        self.policy, actor, sample_key = make_policy(
            env, self._normalized, scale="free", log_prob=True, algo="PPO"
        )
        critic = ValueOperator(
            self._normalized(self.observation.in_features, 1, "the state's value", critic=True),
            in_keys=["observation"],
        )
        self.loss = DirectPPOLoss(  # ClipPPOLoss on the modules' own parameters
            actor,
            critic,
            clip_epsilon=cfg.clip_epsilon,
            entropy_bonus=cfg.entropy_coef > 0,  # no entropy term to compute otherwise
            entropy_coeff=cfg.entropy_coef,
            critic_coeff=cfg.critic_coef,
            loss_critic_type="l2",
            normalize_advantage=True,
        )
        self.loss.set_keys(action=sample_key)
        self.loss.to(device)
        self.policy.to(device)
        self.advantage = GAE(
            gamma=cfg.gamma, lmbda=cfg.gae_lambda, value_network=critic, average_gae=False
        )
        self._params = list(self.loss.parameters())
        self.optimizer = torch.optim.Adam(self._params, lr=cfg.lr, eps=1e-5, fused=True)
        act = sampling_action(actor, env, self.loss.tensor_keys.sample_log_prob, device)
        self.make_collector(env, self.policy, cfg.frames_per_batch, act=act)

    def _normalized(
        self,
        in_features: int | tuple[int, ...],
        out_features: int,
        outputs: str,
        *,
        critic: bool = False,
    ) -> torch.nn.Module:
        """The normaliser (flat vectors), then the actor's network (yours, or a tanh MLP after
        the observation's encoder) or the critic's (an encoder of its own)."""
        if critic:
            net = self.default_network(in_features, out_features)
        else:
            net = self.network(in_features, out_features, outputs)
        default = critic or (self.user_network is None and not self.cfg.network)
        if self.cfg.ortho_init and default:
            orthogonal_init(net, last_gain=1.0 if critic else 0.01)
        return torch.nn.Sequential(self.normalizer, net) if self.observation.flat else net

    def train_step(self) -> Metrics:
        batch = self.collect()
        self.frames += batch.numel()
        self.iterations += 1
        if self.cfg.total_frames:
            left = max(1.0 - self.frames / self.cfg.total_frames, 0.0)
            if self.cfg.anneal_lr:
                for group in self.optimizer.param_groups:
                    group["lr"] = self.cfg.lr * left
            if self.cfg.anneal_clip:  # a buffer of the loss: checkpoints hold it
                self.loss.clip_epsilon.fill_(self.cfg.clip_epsilon * left)
        with torch.no_grad():
            self.advantage(batch)
        data = batch.reshape(-1)
        steps = []
        for _ in range(self.cfg.epochs):
            for minibatch in self._minibatches(data):
                out = self.loss(minibatch)
                loss = out["loss_objective"] + out["loss_critic"] + out.get("loss_entropy", 0.0)
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self._params, self.cfg.max_grad_norm)
                self.optimizer.step()
                steps.append(torch.stack([loss.detach(), *(out[k].reshape(()) for k in LOGGED)]))
        if self.cfg.normalize_observations:  # after the epochs: they saw what the rollout saw
            self.normalizer.observe(batch["observation"])
        self.sync_collector()
        means = torch.stack(steps).mean(0).tolist()  # of the iteration's gradient steps
        metrics: Metrics = dict(zip((LOSS, *LOGGED.values()), means, strict=True))
        metrics.update(episode_metrics(batch, self.frames))
        return metrics

    def _minibatches(self, data: TensorDictBase) -> list[TensorDictBase]:
        """One epoch's shuffled minibatches; the rollout itself when one minibatch holds it all."""
        if self.cfg.minibatch_size >= len(data):  # a full-batch gradient: order does not matter
            return [data]
        index = torch.randperm(len(data), device=self.device)
        return [data[i] for i in index.split(self.cfg.minibatch_size)]

    def _restored(self) -> None:
        self.sync_collector()
