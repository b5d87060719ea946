"""The floor: minimal hand-written PyTorch loops (no TorchRL, no TensorDict) doing exactly the work
of the ``dqn_cartpole``, ``sac_pendulum`` and ``ppo_cartpole`` presets.

Same env copies (a gymnasium ``SyncVectorEnv``), frames per batch, gradient steps per batch,
batch sizes, networks, loss maths, optimizer and target update as rlpipe's preset; one torch
thread; no evaluation or logging inside the timed loop. Each loop returns its counts (env steps,
gradient steps, samples drawn) so the benchmark can check the work is the same, and a greedy
policy for the learning check. ``benchmarks/floor.py`` runs them.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import gymnasium as gym
import numpy as np
import torch
import torch.nn.functional as F
from gymnasium.vector import AutoresetMode
from torch import nn


@dataclass
class Work:
    """What a loop did: env steps, gradient steps, minibatch rows drawn; its greedy policy."""

    env_steps: int = 0
    gradient_steps: int = 0
    samples: int = 0
    policy: Callable[[np.ndarray], np.ndarray] = field(default=lambda obs: obs, repr=False)


def mlp(sizes: list[int], activation: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


def vector_env(env_id: str, copies: int, seed: int) -> tuple[gym.vector.VectorEnv, np.ndarray]:
    envs = gym.vector.SyncVectorEnv(
        [lambda: gym.make(env_id)] * copies, autoreset_mode=AutoresetMode.SAME_STEP
    )
    obs, _ = envs.reset(seed=seed)
    return envs, obs


def real_next(obs: np.ndarray, done: np.ndarray, info: dict) -> np.ndarray:
    """The next observations of a step: the final ones where an episode ended (SAME_STEP)."""
    nxt = obs.copy()
    for i in np.flatnonzero(done):
        nxt[i] = info["final_obs"][i]
    return nxt


def soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    with torch.no_grad():
        torch._foreach_lerp_(list(target.parameters()), list(online.parameters()), tau)


def dqn(frames: int, seed: int) -> Work:
    """``+experiment=dqn_cartpole``: 16 copies, 128 frames then 32 double-DQN Huber updates of 256
    per batch, 3-step returns within each batch, AdamW (amsgrad, lr 2e-3 annealed to 0), gradients
    clipped by value, soft target τ 0.02, ε linear 1 → 0.2 over 5,000 frames, TD targets
    clamped at 100."""
    copies, updates, size, capacity, starts = 16, 32, 256, 50_000, 1_000
    gamma, n, tau = 0.99, 3, 0.02
    torch.manual_seed(seed)
    envs, obs = vector_env("CartPole-v1", copies, seed)
    rng = np.random.default_rng(seed)
    q = mlp([4, 128, 128, 2])
    target = copy.deepcopy(q)
    opt = torch.optim.AdamW(q.parameters(), lr=2e-3, weight_decay=1e-2, amsgrad=True, fused=True)
    buf = {
        "obs": torch.zeros(capacity, 4),
        "act": torch.zeros(capacity, dtype=torch.long),
        "ret": torch.zeros(capacity),
        "next": torch.zeros(capacity, 4),
        "cont": torch.zeros(capacity),  # gamma^k if the window does not end in a terminal, else 0
    }
    work, stored, head, done_frames = Work(), 0, 0, 0
    while done_frames < frames:
        eps = 1.0 + min(done_frames / 5_000, 1.0) * (0.2 - 1.0)
        batch = {k: [] for k in ("obs", "act", "rew", "next", "term", "done")}
        steps = min(128 // copies, math.ceil((frames - done_frames) / copies))  # cut at the budget
        per_batch = steps * copies
        for _ in range(steps):
            with torch.no_grad():
                greedy = q(torch.as_tensor(obs, dtype=torch.float32)).argmax(-1).numpy()
            act = np.where(rng.random(copies) < eps, rng.integers(0, 2, copies), greedy)
            nxt, rew, term, trunc, info = envs.step(act)
            done = term | trunc
            for key, value in zip(batch, (obs, act, rew, real_next(nxt, done, info), term, done)):
                batch[key].append(value)
            obs = nxt
        done_frames += per_batch
        work.env_steps += per_batch
        b = {k: torch.as_tensor(np.stack(v, 1), dtype=torch.float32) for k, v in batch.items()}
        ret, last = torch.zeros(copies, steps), torch.arange(steps).repeat(copies, 1)
        alive = torch.ones(copies, steps, dtype=torch.bool)
        for k in range(n):  # windows stop at an episode's end and at the batch's end
            t = torch.arange(steps) + k
            inside = (t < steps).expand(copies, -1) & alive
            tc = t.clamp(max=steps - 1)
            ret += inside * gamma**k * b["rew"][:, tc]
            last = torch.where(inside, tc.expand(copies, -1), last)
            alive = inside & (b["done"][:, tc] == 0)
        k_steps = (last - torch.arange(steps) + 1).float()
        rows = torch.arange(copies)[:, None]
        cont = (1 - b["term"][rows, last]) * gamma**k_steps
        new = {
            "obs": b["obs"],
            "act": b["act"].long(),
            "ret": ret,
            "next": b["next"][rows, last],
            "cont": cont,
        }
        idx = (head + torch.arange(per_batch)) % capacity
        for key, value in new.items():
            buf[key][idx] = value.reshape(per_batch, *value.shape[2:])
        head, stored = (head + per_batch) % capacity, min(stored + per_batch, capacity)
        for group in opt.param_groups:
            group["lr"] = 2e-3 * (1 - min(done_frames / frames, 1.0))
        if stored < max(starts, size):
            continue
        for _ in range(updates):
            i = torch.randint(stored, (size,))
            with torch.no_grad():
                best = q(buf["next"][i]).argmax(-1, keepdim=True)
                value = target(buf["next"][i]).gather(-1, best).squeeze(-1)
                goal = (buf["ret"][i] + buf["cont"][i] * value).clamp(max=100.0)
            pred = q(buf["obs"][i]).gather(-1, buf["act"][i, None]).squeeze(-1)
            loss = F.smooth_l1_loss(pred, goal)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_value_(q.parameters(), 100.0)
            opt.step()
            soft_update(target, q, tau)
            work.gradient_steps += 1
            work.samples += size
    envs.close()
    work.policy = lambda o: q(torch.as_tensor(o, dtype=torch.float32)).argmax(-1).numpy()
    return work


def _squash(loc: torch.Tensor, raw_scale: torch.Tensor, high: float, sample: bool):
    """TorchRL's TanhNormal on ``[-high, high]`` with a biased softplus scale (min 0.01): an
    action (reparametrised) and its log-probability."""
    scale = F.softplus(raw_scale + math.log(math.expm1(1.0 - 0.01))) + 0.01
    base = torch.distributions.Normal(loc, scale)
    u = base.rsample() if sample else loc
    action = torch.tanh(u)
    log_prob = base.log_prob(u) - torch.log1p(-action.pow(2) + 1e-6) - math.log(high)
    return action * high, log_prob.sum(-1)


def sac(frames: int, seed: int) -> Work:
    """``+experiment=sac_pendulum``: one Pendulum-v1 copy, a frame then a gradient step of 256
    (after 100 frames), twin 128-128 critics, a 128-128 tanh-Gaussian actor, automatic entropy
    (target −1), one fused Adam (lr 1e-3) over all, soft target τ 0.005, γ 0.99."""
    size, starts, gamma, tau, high = 256, 100, 0.99, 0.005, 2.0
    torch.manual_seed(seed)
    envs, obs = vector_env("Pendulum-v1", 1, seed)
    actor = mlp([3, 128, 128, 2])
    critics = nn.ModuleList([mlp([4, 128, 128, 1]) for _ in range(2)])
    targets = copy.deepcopy(critics)
    log_alpha = nn.Parameter(torch.zeros(()))
    opt = torch.optim.Adam(
        [*actor.parameters(), *critics.parameters(), log_alpha], 1e-3, fused=True
    )
    cap = frames
    buf = {k: torch.zeros(cap, d) for k, d in (("obs", 3), ("act", 1), ("rew", 1), ("next", 3))}
    buf["term"] = torch.zeros(cap, 1)
    work = Work()
    for t in range(frames):
        with torch.no_grad():
            act, _ = _squash(
                *actor(torch.as_tensor(obs, dtype=torch.float32)).chunk(2, -1), high, True
            )
        nxt, rew, term, trunc, info = envs.step(act.numpy())
        row = (obs, act.numpy(), rew[:, None], real_next(nxt, term | trunc, info), term[:, None])
        for key, value in zip(("obs", "act", "rew", "next", "term"), row):
            buf[key][t] = torch.as_tensor(value[0], dtype=torch.float32)
        obs = nxt
        work.env_steps += 1
        if t + 1 < max(starts, size):
            continue
        i = torch.randint(t + 1, (size,))
        s, a, r, s2, d = (buf[k][i] for k in ("obs", "act", "rew", "next", "term"))
        alpha = log_alpha.detach().exp()
        with torch.no_grad():
            a2, logp2 = _squash(*actor(s2).chunk(2, -1), high, True)
            q2 = torch.stack([c(torch.cat([s2, a2], -1)) for c in targets]).squeeze(-1)
            goal = r.squeeze(-1) + gamma * (1 - d.squeeze(-1)) * (q2.min(0).values - alpha * logp2)
        pred = torch.stack([c(torch.cat([s, a], -1)) for c in critics]).squeeze(-1)
        loss_q = (pred - goal).pow(2).sum(0).mean()
        a_new, logp = _squash(*actor(s).chunk(2, -1), high, True)
        for p in critics.parameters():
            p.requires_grad_(False)
        q_new = torch.stack([c(torch.cat([s, a_new], -1)) for c in critics]).squeeze(-1)
        for p in critics.parameters():
            p.requires_grad_(True)
        loss_actor = (alpha * logp - q_new.min(0).values).mean()
        loss_alpha = (-log_alpha * (logp.detach() - 1.0)).mean()
        opt.zero_grad(set_to_none=True)
        (loss_q + loss_actor + loss_alpha).backward()
        opt.step()
        soft_update(targets, critics, tau)
        work.gradient_steps += 1
        work.samples += size
    envs.close()
    work.policy = lambda o: _squash(
        *actor(torch.as_tensor(o, dtype=torch.float32)).chunk(2, -1), high, False
    )[0].numpy()
    return work


def ppo(frames: int, seed: int) -> Work:
    """``+experiment=ppo_cartpole``: 16 copies, 512 frames per rollout, GAE (γ 0.98, λ 0.8), then
    20 epochs of one full-batch clipped-PPO step (clip 0.2, advantages normalised, value loss
    0.5 × MSE, gradient norm ≤ 0.5), fused Adam (lr 3e-3 annealed to 0, eps 1e-5), tanh 64-64
    actor and critic with SB3's orthogonal initialisation."""
    copies, per_batch, epochs, gamma, lam, clip = 16, 512, 20, 0.98, 0.8, 0.2
    steps = per_batch // copies
    torch.manual_seed(seed)
    envs, obs = vector_env("CartPole-v1", copies, seed)
    actor, critic = mlp([4, 64, 64, 2], nn.Tanh), mlp([4, 64, 64, 1], nn.Tanh)
    for net, gain in ((actor, 0.01), (critic, 1.0)):
        linears = [m for m in net if isinstance(m, nn.Linear)]
        for j, layer in enumerate(linears):
            nn.init.orthogonal_(layer.weight, gain if j == len(linears) - 1 else math.sqrt(2))
            nn.init.zeros_(layer.bias)
    params = [*actor.parameters(), *critic.parameters()]
    opt = torch.optim.Adam(params, lr=3e-3, eps=1e-5, fused=True)
    work, done_frames = Work(), 0
    while done_frames < frames:
        roll = {k: [] for k in ("obs", "act", "logp", "rew", "next", "term", "done")}
        for _ in range(steps):
            o = torch.as_tensor(obs, dtype=torch.float32)
            with torch.no_grad():
                dist = torch.distributions.Categorical(logits=actor(o))
                act = dist.sample()
            nxt, rew, term, trunc, info = envs.step(act.numpy())
            done = term | trunc
            for key, value in zip(
                roll,
                (o, act, dist.log_prob(act), rew, real_next(nxt, done, info), term, done),
            ):
                roll[key].append(torch.as_tensor(value, dtype=torch.float32))
            obs = nxt
        done_frames += per_batch
        work.env_steps += per_batch
        b = {k: torch.stack(v, 1) for k, v in roll.items()}  # [copies, steps, ...]
        with torch.no_grad():
            value = critic(b["obs"]).squeeze(-1)
            next_value = critic(b["next"]).squeeze(-1)
            delta = b["rew"] + gamma * (1 - b["term"]) * next_value - value
            adv, running = torch.zeros_like(delta), torch.zeros(copies)
            for t in reversed(range(steps)):
                running = delta[:, t] + gamma * lam * (1 - b["done"][:, t]) * running
                adv[:, t] = running
            goal = adv + value
        left = max(1 - done_frames / frames, 0.0)
        for group in opt.param_groups:
            group["lr"] = 3e-3 * left
        flat = {k: v.reshape(per_batch, *v.shape[2:]) for k, v in b.items()}
        adv_flat, goal_flat = adv.reshape(-1), goal.reshape(-1)
        for _ in range(epochs):
            norm_adv = (adv_flat - adv_flat.mean()) / adv_flat.std().clamp_min(1e-6)
            logp = torch.distributions.Categorical(logits=actor(flat["obs"])).log_prob(
                flat["act"].long()
            )
            ratio = (logp - flat["logp"]).exp()
            gain = torch.min(ratio * norm_adv, ratio.clamp(1 - clip, 1 + clip) * norm_adv)
            loss = -gain.mean() + 0.5 * (critic(flat["obs"]).squeeze(-1) - goal_flat).pow(2).mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 0.5)
            opt.step()
            work.gradient_steps += 1
            work.samples += per_batch
    envs.close()
    work.policy = lambda o: actor(torch.as_tensor(o, dtype=torch.float32)).argmax(-1).numpy()
    return work


LOOPS = {"dqn_cartpole": dqn, "sac_pendulum": sac, "ppo_cartpole": ppo}
ENV_IDS = {
    "dqn_cartpole": "CartPole-v1",
    "sac_pendulum": "Pendulum-v1",
    "ppo_cartpole": "CartPole-v1",
}


@torch.no_grad()
def greedy_return(preset: str, policy: Callable, episodes: int, seed: int) -> float:
    """Mean return of ``episodes`` greedy episodes (the learning check, outside the timing)."""
    env = gym.make(ENV_IDS[preset])
    total = 0.0
    for episode in range(episodes):
        obs, _ = env.reset(seed=seed + episode)
        done = False
        while not done:
            action = policy(obs[None])[0]
            obs, rew, term, trunc, _ = env.step(action)
            total += float(rew)
            done = term or trunc
    env.close()
    return total / episodes
