"""Config schemas, Hydra composition of every group option, and value checks."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from rlpipe.algos import ALGORITHMS, DQNConfig
from rlpipe.cli import compose_run, register_configs, to_config
from rlpipe.config import RUN_KEYS, Config, EnvConfig, LoggerConfig, config_to_dict, fingerprint
from rlpipe.errors import RlpipeError
from rlpipe.pipeline import train
from rlpipe.runtime import TORCH_THREADS, set_threads

CONF = Path(__file__).resolve().parents[1] / "conf"
register_configs()


def compose_config(*overrides: str) -> Config:
    with initialize_config_module(config_module="rlpipe.conf", version_base="1.3"):
        return to_config(compose("config", overrides=list(overrides)))


def test_default_is_dqn_on_cartpole():
    cfg = compose_config("~tuned")
    assert isinstance(cfg.algo, DQNConfig)
    assert cfg.env.id == "CartPole-v1"
    assert cfg.logger.backend == "csv"
    assert (cfg.algo.hidden_sizes, cfg.algo.batch_size, cfg.algo.buffer_size) == (
        [128, 128],
        128,
        10_000,
    )
    assert (cfg.algo.lr, cfg.algo.tau, cfg.algo.gamma) == (1e-4, 0.005, 0.99)


EXPECTED_IDS = {
    "cartpole": "CartPole-v1",
    "mountaincar": "MountainCar-v0",
    "mountaincar_continuous": "MountainCarContinuous-v0",
    "lunarlander": "LunarLander-v3",
    "lunarlander_continuous": "LunarLanderContinuous-v3",
    "acrobot": "Acrobot-v1",
    "pendulum": "Pendulum-v1",
    "bipedal": "BipedalWalker-v3",
    "bipedal_hardcore": "BipedalWalker-v3",
    "cartpole_continuous": "rlpipe/CartPoleContinuous-v0",
    "cartpole_noop": "rlpipe/CartPoleNoop-v0",
    "minigrid_pixels": "rlpipe/MiniGrid-Empty-5x5-Pixels-v0",
}


@pytest.mark.parametrize("name", sorted(EXPECTED_IDS))
def test_env_group_options(name):
    cfg = compose_config(f"env={name}")
    assert cfg.env.id == EXPECTED_IDS[name]
    assert cfg.env.kwargs.get("hardcore", False) == (name == "bipedal_hardcore")


def test_every_env_file_is_tested():
    assert {p.stem for p in (CONF / "env").glob("*.yaml")} == set(EXPECTED_IDS) | {"gym"}


def test_generic_gym_entry_takes_an_id():
    assert compose_config("env=gym", "env.id=Acrobot-v1").env.id == "Acrobot-v1"


def test_generic_gym_entry_without_id_fails():
    with pytest.raises(Exception, match="env.id"):
        compose_config("env=gym")


@pytest.mark.parametrize("logger", ["csv", "none"])
def test_logger_options(logger):
    assert compose_config(f"logger={logger}").logger.backend == logger


def test_experiment_preset_composes():
    cfg = compose_config("+experiment=dqn_cartpole")
    assert cfg.env.id == "CartPole-v1" and cfg.env.num_envs > 1
    assert cfg.total_frames <= 50_000


PRESET_ENVS = {
    "dqn_cartpole": "CartPole-v1",
    "dqn_mountaincar": "MountainCar-v0",
    "dqn_lunarlander": "LunarLander-v3",
    "dqn_acrobot": "Acrobot-v1",
    "ars_cartpole": "CartPole-v1",
    "ars_pendulum": "Pendulum-v1",
    "ars_bipedal": "BipedalWalker-v3",
    "ars_lunarlander_continuous": "LunarLanderContinuous-v3",
    "reinforce_cartpole": "rlpipe/CartPoleContinuous-v0",
    "mbrl_pendulum": "Pendulum-v1",
    "mbrl_cartpole": "rlpipe/CartPoleContinuous-v0",
    "ppo_cartpole": "CartPole-v1",
    "ppo_lunarlander": "LunarLander-v3",
    "ppo_minigrid_pixels": "rlpipe/MiniGrid-Empty-5x5-Pixels-v0",
    "sac_pendulum": "Pendulum-v1",
    "sac_bipedal": "BipedalWalker-v3",
    "sac_mountaincar_continuous": "MountainCarContinuous-v0",
}


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_every_preset_composes_with_its_env_and_algorithm(preset):
    cfg = compose_config(f"+experiment={preset}")
    assert cfg.env.id == PRESET_ENVS[preset]
    assert cfg.algo.name == preset.partition("_")[0]


@pytest.mark.parametrize(
    "override",
    ["algo.lrr=1", "total_frame=5", "algo.lr=abc", "seed=1.5", "env.num_envs=x"],
)
def test_typos_and_wrong_types_fail_at_composition(override):
    with pytest.raises(ConfigCompositionException):
        compose_config(override)


@pytest.mark.parametrize("override", ["+foo=1", "+algo.foo=2", "+env.bar=3"])
def test_added_keys_are_refused(override):
    with pytest.raises(RlpipeError, match="unknown config key"):
        compose_config(override)


@pytest.mark.parametrize(
    "override, message",
    [
        ("total_frames=0", "total_frames"),
        ("total_frames=-5", "total_frames"),
        ("eval_episodes=0", "eval_episodes"),
        ("keep_checkpoints=0", "keep_checkpoints"),
        ("env.num_envs=0", "num_envs"),
        ("algo.lr=0", "algo.lr"),
        ("algo.gamma=1.5", "gamma"),
        ("algo.buffer_size=10", "buffer_size"),
        ("algo.eps_schedule=cosine", "eps_schedule"),
        ("logger.backend=x", "logger.backend"),
        ("threads=-1", "threads must be auto or a number from 0"),
        (f"threads={(os.cpu_count() or 1) + 1}", "threads must be auto or a number from 0"),
        ("threads=many", "threads must be auto or a number from 0"),
        ("device=tpu", "device must be auto, cpu, cuda or cuda:N, got tpu"),
        ("device=cuda:x", "device must be auto, cpu, cuda or cuda:N"),
        ("device=cuda1", "device must be auto, cpu, cuda or cuda:N"),
    ],
)
def test_bad_values_fail_with_a_named_key(override, message):
    with pytest.raises(RlpipeError, match=message):
        compose_config(override)


def test_plain_dataclasses_work_without_hydra():
    cfg = Config(env=EnvConfig(id="Acrobot-v1", num_envs=2), algo=DQNConfig(lr=3e-4))
    assert cfg.algo.name == "dqn" and cfg.logger == LoggerConfig()
    with pytest.raises(RlpipeError):
        DQNConfig(batch_size=0)


def test_python_default_config_is_the_cli_default_without_tuned_settings():
    assert compose_config("~tuned") == Config()
    assert compose_config("~tuned").resolved() == Config().resolved()


@pytest.mark.parametrize("preset", sorted(p.stem for p in (CONF / "experiment").glob("*.yaml")))
def test_the_tuned_settings_of_a_pair_are_its_preset(preset):
    """``algo=A env=E`` picks ``conf/tuned/A_E.yaml``; ``+experiment=<preset>`` only names the
    pair; ``~tuned`` drops the tuned settings."""
    named = compose_config(f"+experiment={preset}")
    pair = compose_config(f"algo={named.algo.name}", f"env={_env_option(preset)}")
    assert named == pair
    plain = compose_config(f"algo={named.algo.name}", f"env={_env_option(preset)}", "~tuned")
    assert plain.algo == type(named.algo)()
    tuned = CONF / "tuned" / f"{named.algo.name}_{_env_option(preset)}.yaml"
    settings = [line for line in tuned.read_text().splitlines() if not line.startswith("#")]
    assert (plain != named) == any(line.strip() for line in settings)  # mbrl_pendulum: none


def _env_option(preset: str) -> str:
    text = (CONF / "experiment" / f"{preset}.yaml").read_text()
    return text.split("override /env: ")[1].split()[0]


@pytest.mark.parametrize("algo", ["dqn", "reinforce", "ars", "mbrl"])
def test_algo_files_only_name_their_schema(algo):
    """Defaults live in the dataclasses: an algo file repeats none and sets no run keys."""
    node = OmegaConf.load(CONF / "algo" / f"{algo}.yaml")
    assert list(node) == ["defaults"]
    assert OmegaConf.to_container(node.defaults) == [f"/schema/algo/{algo}@_here_", "_self_"]
    assert "_global_" not in (CONF / "algo" / f"{algo}.yaml").read_text()
    cfg = compose_config(f"algo={algo}", "~tuned")
    assert cfg.algo == ALGORITHMS[algo][0]()


@pytest.mark.parametrize(
    "algo, expected",
    [
        ("dqn", (60_000, 10_000, 10, 25_000)),
        ("reinforce", (None, 5_000, 20, 25_000)),
        ("ars", (None, 1_000_000, 10, 1_000_000)),
        ("mbrl", (15_000, 2_000, 10, 5_000)),
    ],
)
def test_null_run_keys_take_the_algorithms_values(algo, expected):
    resolved = compose_config(f"algo={algo}", "~tuned").resolved()
    assert tuple(getattr(resolved, key) for key in RUN_KEYS) == expected
    overridden = compose_config(
        f"algo={algo}", "~tuned", "total_frames=123", "eval_every=0"
    ).resolved()
    assert (overridden.total_frames, overridden.eval_every) == (123, 0)


def test_python_one_liner_runs_with_the_algorithms_budget(tmp_path):
    """`train(Config(env=..., algo=DQNConfig()), dir)` needs no total_frames: DQN's is 60k."""
    cfg = Config(env=EnvConfig(id="Acrobot-v1"), algo=DQNConfig())
    assert cfg.resolved() == compose_config("env=gym", "env.id=Acrobot-v1").resolved()
    assert cfg.resolved().total_frames == DQNConfig().total_frames == 60_000
    short = DQNConfig(total_frames=300, eval_every=0, eval_episodes=1, learning_starts=64)
    result = train(Config(env=EnvConfig(id="Acrobot-v1"), algo=short, progress=False), tmp_path)
    assert result.frames == 300
    assert OmegaConf.load(tmp_path / "config.yaml").total_frames == 300  # resolved, recorded


@pytest.mark.parametrize(
    "threads, device, expected",
    [("auto", "cpu", 1), ("auto", "meta", None), (2, "cpu", 2), (0, "cpu", None)],
)
def test_threads_auto_is_one_on_cpu(threads, device, expected):
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(3)
        set_threads(threads, torch.device(device))
        # None: torch's default, as rlpipe found it (one per core), whatever was set since
        assert torch.get_num_threads() == (expected or TORCH_THREADS)
    finally:
        torch.set_num_threads(before)


def _flushes() -> bool:
    """Whether torch flushes a subnormal float32 result (1e-40) to zero on this thread."""
    return (torch.tensor([1e-30]) * torch.tensor([1e-10])).item() == 0.0


def test_set_threads_flushes_subnormals():
    before = _flushes()
    try:
        torch.set_flush_denormal(False)
        assert not _flushes()  # the probe can tell
        set_threads("auto", torch.device("cpu"))
        assert _flushes()
    finally:
        torch.set_flush_denormal(before)


@pytest.mark.parametrize(
    "overrides, added",
    [
        (["algo=dqn", "~tuned"], ["eps_zeta", "q_max"]),  # dqn_cartpole's tuned q_max is 100
        (["algo=sac"], ["noise_color", "noise_steps", "fixed_alpha"]),
    ],
)
def test_a_checkpoint_s_config_from_before_a_field_existed_is_the_same_run(overrides, added):
    """A checkpoint stores its config as written then: a field added since stands at its
    default, so the run resumes; the field set otherwise is another run."""
    cfg = compose_run(*overrides)
    stored = config_to_dict(cfg)
    for name in added:
        del stored["algo"][name]
    assert fingerprint(stored) == fingerprint(cfg)
    changed = compose_run(*overrides, f"algo.{added[0]}=3")
    assert fingerprint(stored) != fingerprint(changed)
