"""Smoke tests of ``python -m rlpipe`` through a subprocess, including every bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace

import pytest
from conftest import TINY, assert_auto_chose, run_module
from omegaconf import OmegaConf

from rlpipe.algos import ARSConfig, DQNConfig, PPOConfig, ReinforceConfig, SACConfig
from rlpipe.cli import compose_run, trap_notice, tuned_elsewhere_notice
from rlpipe.config import EnvConfig


def test_default_job_trains_and_writes_its_run_dir(tmp_path):
    """In a fresh interpreter, as typed (the other tests' runs are forked: tests/warm.py)."""
    run = tmp_path / "run"
    args = [*TINY, "checkpoint_every=100", f"hydra.run.dir={run}"]
    # an empty matplotlib cache, as on a new machine: its font cache is built during the run
    env = {"MPLCONFIGDIR": str(tmp_path / "mpl")}
    proc = run_module("rlpipe", *args, cwd=tmp_path, env=env, fresh=True)
    assert proc.returncode == 0, proc.stderr
    assert "final eval" in proc.stdout and str(run) in proc.stdout
    assert_auto_chose(proc.stdout, copies=1)
    assert json.loads((run / "summary.json").read_text())["frames"] == 200
    assert (run / ".hydra" / "config.yaml").exists()
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names[0].startswith("best_")  # the best evaluation's, beside the newest ones
    assert names[1:] == ["ckpt_000000000100.pt", "ckpt_000000000200.pt"]
    assert (run / "metrics" / "scalars" / "eval" / "return_mean.csv").exists()
    # the console is rlpipe's: no third-party log lines (TorchRL's INFO, in colour; matplotlib's
    # "generated new fontManager"), which go to the run's log
    console = proc.stdout + proc.stderr
    assert "[torchrl]" not in console and "\x1b[" not in proc.stdout
    assert "matplotlib" not in console, console
    assert (
        "[matplotlib.font_manager][INFO] - generated new fontManager"
        in (run / "rlpipe.log").read_text()
    )


def test_the_python_api_prints_no_third_party_log_lines(tmp_path):
    code = (
        "from rlpipe import Config, train; "
        "train(Config(total_frames=100, eval_every=100, eval_episodes=1, progress=False), 'run')"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    # rlpipe's own line only: the env backend the run uses
    lines = proc.stdout.splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: env backend "), proc.stdout
    assert "[torchrl]" not in proc.stderr, proc.stderr


@pytest.mark.parametrize("name", ["a run dir", "résumé 実験"], ids=["space", "beyond-ascii"])
def test_a_run_dir_with_spaces_or_letters_beyond_ascii(rlpipe_cli, tmp_path, name):
    """Given as hydra.run.dir=... (Hydra's grammar takes letters beyond ASCII only quoted: rlpipe
    quotes them; the second name has accents and CJK letters), and resumed as resume=..."""
    run = tmp_path / name
    proc = rlpipe_cli(*TINY, run_dir=run)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "summary.json").read_text())["run_dir"] == str(run)
    more = [arg for arg in TINY if not arg.startswith("total_frames")]
    proc = rlpipe_cli(*more, "total_frames=300", f"resume={run}", run_dir=run)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((run / "summary.json").read_text())["frames"] == 300


def test_the_runs_console_lines_are_in_its_log(tmp_path, run_copy):
    """rlpipe.log holds the resume notice, the extension's line, the warnings and the summary
    line the console shows."""
    from conftest import BASE, run_module

    with open(run_copy / "metrics" / "scalars" / "eval" / "return_mean.csv", "ab") as f:
        f.write(b"30")  # a torn last line: a warning at resume
    before = (run_copy / "rlpipe.log").read_text()
    args = [arg for arg in BASE if not arg.startswith("total_frames")]
    proc = run_module("rlpipe", *args, "total_frames=300", f"resume={run_copy}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    console = [
        line for line in (proc.stdout + proc.stderr).splitlines() if line.startswith("rlpipe: ")
    ]
    # stdout's and stderr's lines, each in order: the warning on stderr, the others on stdout
    kinds = sorted(line.split()[1] for line in console)
    assert kinds == ["300", "env", "final", "resuming", "warning:"], console  # 300: extended
    log = (run_copy / "rlpipe.log").read_text()
    assert log.startswith(before)  # appended to
    for line in console:
        assert f"] - {line}\n" in log, (line, log)


def test_groups_compose_from_the_command_line(rlpipe_cli, tmp_path):
    proc = rlpipe_cli(*TINY, "algo=dqn", "env=mountaincar", "logger=none", "env.num_envs=2")
    assert proc.returncode == 0, proc.stderr
    assert not (tmp_path / "run" / "metrics").exists()
    assert (tmp_path / "run" / "summary.json").exists()


def test_generic_gym_entry(rlpipe_cli):
    proc = rlpipe_cli(*TINY, "env=gym", "env.id=Acrobot-v1")
    assert proc.returncode == 0, proc.stderr


def test_another_id_runs_where_no_tuned_settings_were_picked():
    """env.id= beside tuned settings is refused (BAD_INPUTS); without them it is the run's id."""
    assert compose_run("~tuned", "env.id=Acrobot-v1").env.id == "Acrobot-v1"
    assert compose_run("algo=reinforce", "env.id=Acrobot-v1").env.id == "Acrobot-v1"
    assert compose_run("env.id=CartPole-v1").algo == compose_run("+experiment=dqn_cartpole").algo


def test_multirun_sweeps_seeds(tmp_path):
    proc = run_module(
        "rlpipe", "-m", *TINY, "seed=0,1", f"hydra.sweep.dir={tmp_path / 'sweep'}", cwd=tmp_path
    )
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (tmp_path / "sweep").iterdir() if p.is_dir()) == ["0", "1"]
    assert all((tmp_path / "sweep" / d / "summary.json").exists() for d in "01")


# a bad input of each kind (more of those found once the envs are made: test_faults.py's BAD_RUNS)
BAD_INPUTS = [
    (["algo=nope"], "unknown algo option 'nope'; choose one of: "),
    (["env=nope"], "unknown env option 'nope'; choose one of: acrobot, bipedal"),
    (
        ["logger=nope"],
        "unknown logger option 'nope'; choose one of: csv, mlflow, none, tensorboard, wandb",
    ),
    (["env=gym"], "env.id must be set"),
    (["algo.lrr=1"], "Key 'lrr' not in 'DQNConfig'"),
    (["total_frame=5"], "Key 'total_frame' not in 'Config'"),
    (["+foo=1"], "unknown config key 'foo'"),
    (["seed=abc"], "could not be converted to Integer"),
    (["algo.lr=fast"], "could not be converted to Float"),
    (["+experiment=dqn_cartpole", "env=pendulum"], "+experiment=dqn_cartpole is dqn on env=cartp"),
    (["+experiment=dqn_lunarlander", "algo=ppo"], "but algo=ppo was asked for: drop one of them"),
    (
        ["env.id=Acrobot-v1"],  # env=cartpole's tuned DQN is CartPole-v1's
        "are CartPole-v1's; for Acrobot-v1 use env=acrobot (tuned/dqn_acrobot.yaml) or add ~tuned",
    ),
    (
        ["+experiment=ars_bipedal", "env.id=BipedalWalkerHardcore-v3"],
        "(tuned/ars_bipedal.yaml) are BipedalWalker-v3's; for BipedalWalkerHardcore-v3 add ~tuned",
    ),
    (["env=bipedal"], "DQN needs a discrete action space"),
    (["total_frames=0"], "total_frames must be >= 1"),
    (["total_frames=-100"], "total_frames must be >= 1"),
    (["eval_episodes=0"], "eval_episodes must be >= 1"),
    (["device=tpu"], "device must be auto, cpu, cuda or cuda:N"),
]


@pytest.mark.parametrize(
    "case, message",
    [
        ("device=tpu", "device must be auto, cpu, cuda or cuda:N, got tpu"),
        ("resume-garbage", "config.yaml is damaged"),
        ("resume-link", "is a symbolic link"),
        ("checkpoints-a-file", "where the run keeps a directory"),
    ],
)
def test_config_and_run_dir_errors_come_before_torch_loads(tmp_path, case, message):
    """A typo in a value or a bad run dir fails at once: torch never loads."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("garbage: [")
    (tmp_path / "link").symlink_to(run)
    (tmp_path / "fresh").mkdir()  # no run yet, a file where its checkpoints go
    (tmp_path / "fresh" / "checkpoints").write_text("")
    args = {
        "device=tpu": ["device=tpu", f"hydra.run.dir={tmp_path / 'new'}"],
        "resume-garbage": [f"resume={run}"],
        "resume-link": [f"resume={tmp_path / 'link'}"],
        "checkpoints-a-file": [f"hydra.run.dir={tmp_path / 'fresh'}"],
    }[case]
    code = (
        "import sys\nfrom rlpipe.command import main\n"
        f"sys.argv = ['rlpipe', *{args!r}]\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert e.code == 2, e.code\n"
        "assert 'torch' not in sys.modules, 'torch loaded'\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("rlpipe: error: ") and message in lines[0], lines


@pytest.mark.parametrize("args, message", BAD_INPUTS, ids=[" ".join(a) for a, _ in BAD_INPUTS])
def test_bad_input_is_one_clear_line(rlpipe_cli, tmp_path, args, message):
    proc = rlpipe_cli("progress=false", *args)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error: ") and message in lines[0]
    assert "Traceback" not in proc.stdout + proc.stderr
    if args[0] == "algo=nope":
        assert "dqn" in lines[0].split("choose one of: ")[1].split(", ")
    run = tmp_path / "run"
    assert not (run / "checkpoints").exists() and not (run / "metrics").exists()


def test_help_names_groups_options_keys_entry_points_and_examples(tmp_path):
    from dataclasses import fields

    from rlpipe.config import Config
    from rlpipe.help import KEYS

    done = run_module("rlpipe", "--help", cwd=tmp_path)
    assert done.returncode == 0 and done.stderr == ""
    text = done.stdout
    assert "powered by Hydra" not in text and "schema" not in text  # ours, internals hidden
    for group, option in [
        ("env", "bipedal"),
        ("algo", "mbrl"),
        ("logger", "wandb"),
        ("+experiment", "dqn_lunarlander"),
        ("+sweep", "ars_bipedal"),
    ]:
        assert f"\n  {group} " in text and option in text
    assert "cartpole (default)" in text and "dqn (default)" in text
    # every top-level key of Config (but the groups) with its default and a meaning
    top = {f.name for f in fields(Config)} - {"env", "algo", "logger"}
    assert top == set(KEYS)
    assert "seed=0 " in text and "threads=auto " in text and "total_frames=null " in text
    for command in (
        "rlpipe.evaluate",
        "rlpipe.export",
        "rlpipe.plot",
        "rlpipe.play",
        "rlpipe algo=ars env=bipedal",
    ):
        assert f"python -m {command}" in text
    assert not (tmp_path / "outputs").exists()  # help trains nothing


@pytest.mark.parametrize("args", [["--help"], [*TINY, "hydra.run.dir=run"]], ids=["help", "run"])
def test_a_closed_console_ends_nothing(tmp_path, args):
    """``| head``, a pager quit: the reader gone before a line is written (stdout and stderr, as
    with ``2>&1``). No traceback; a run trains to its end, its lines in its log."""
    read, write = os.pipe()
    os.close(read)  # no reader at all: every write fails, every time
    try:
        done = subprocess.run(
            [sys.executable, "-m", "rlpipe", *args], stdout=write, stderr=write, cwd=tmp_path
        )
    finally:
        os.close(write)
    assert done.returncode == 0
    if args != ["--help"]:
        assert json.loads((tmp_path / "run" / "summary.json").read_text())["frames"] == 200
        log = (tmp_path / "run" / "rlpipe.log").read_text()
        assert "rlpipe: final eval" in log and "Traceback" not in log


@pytest.mark.parametrize("group", ["experiment", "sweep"])
def test_a_group_added_without_plus_is_told_to_use_it(rlpipe_cli, group):
    done = rlpipe_cli(f"{group}=dqn_cartpole", "seed=1")
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].endswith(f"use +{group}=dqn_cartpole"), lines


@pytest.mark.parametrize(
    "overrides", [["algo=ars", "env=bipedal"], ["+experiment=dqn_cartpole", "seed=3", "--resolve"]]
)
def test_cfg_job_prints_what_hydra_prints(tmp_path, overrides):
    """``--cfg job`` is composed once by rlpipe (checks included); ``-p _global_`` makes Hydra
    print the same config itself."""
    ours = run_module("rlpipe", *overrides, "--cfg", "job", cwd=tmp_path)
    hydras = run_module("rlpipe", *overrides, "--cfg", "job", "-p", "_global_", cwd=tmp_path)
    assert ours.returncode == hydras.returncode == 0, ours.stderr + hydras.stderr
    assert ours.stdout == hydras.stdout and ours.stdout.startswith("env:\n")


def first_line(rlpipe_cli, *choices: str) -> str:
    """The first line a tiny run of ``choices`` prints (the run must succeed)."""
    tiny = ("total_frames=512", "eval_every=0", "eval_episodes=1", "progress=false")
    proc = rlpipe_cli(*choices, *tiny)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.splitlines()[0]


def test_a_pair_with_tuned_settings_runs_them_and_says_so(rlpipe_cli, tmp_path):
    first = first_line(rlpipe_cli, "algo=ppo", "env=cartpole")
    assert first.startswith("rlpipe: ppo on env=cartpole with its tuned settings")
    assert "conf/tuned/ppo_cartpole.yaml" in first and "add ~tuned" in first
    assert "num_envs: 16" in (tmp_path / "run" / "config.yaml").read_text()


def test_tuned_settings_of_the_same_env_under_another_option_are_named_at_start(rlpipe_cli):
    """``env=gym env.id=CartPole-v1`` runs DQN's defaults and says which option picks the tuned
    settings of that env (the RL Zoo picks them by id); another env's kwargs or ``~tuned``: not."""
    first = first_line(rlpipe_cli, "env=gym", "env.id=CartPole-v1")
    assert first == (
        "rlpipe: note: dqn's own defaults on CartPole-v1; env=cartpole instead of env=gym picks "
        "its tuned settings (tuned/dqn_cartpole.yaml)"
    )
    choices = OmegaConf.create({"algo": "ars", "env": "bipedal_hardcore", "tuned": "ars_x"})
    hardcore = EnvConfig(id="BipedalWalker-v3", kwargs={"hardcore": True})
    assert tuned_elsewhere_notice(choices, hardcore) is None  # bipedal's settings: another task
    plain = replace(hardcore, kwargs={})
    assert "env=bipedal instead of env=bipedal_hardcore" in tuned_elsewhere_notice(choices, plain)
    assert tuned_elsewhere_notice(OmegaConf.create({"algo": "ars", "env": "gym"}), plain) is None


def test_a_known_exploration_trap_is_named_at_start(rlpipe_cli):
    """An env where the algorithm's defaults are known to fail (no tuned settings for the pair:
    no claim of any) says so in one line at start."""
    first = first_line(rlpipe_cli, "algo=ars", "env=gym", "env.id=MountainCarContinuous-v0")
    assert first.startswith("rlpipe: note: ars's defaults on MountainCarContinuous-v0: a known ")
    assert "exploration trap" in first and "algo=sac env=mountaincar_continuous" in first
    assert trap_notice(SACConfig(), "MountainCarContinuous-v0").startswith("rlpipe: note: sac's")
    assert trap_notice(SACConfig(), "Pendulum-v1") is None
    # time-correlated noise is SAC's way out (the tuned preset's): no note for a run that sets it
    assert (
        trap_notice(SACConfig(noise_color=1.0, noise_steps=1000), "MountainCarContinuous-v0")
        is None
    )
    assert trap_notice(PPOConfig(), "MountainCarContinuous-v0") is not None
    # an algorithm that cannot act there gets its own error, not a note before it
    assert trap_notice(DQNConfig(), "MountainCarContinuous-v0") is None


def test_the_discrete_mountain_car_trap_is_named_for_the_algorithms_it_traps(rlpipe_cli):
    """MountainCar-v0: DQN's, PPO's and REINFORCE's defaults stay at -200, ARS's get there;
    DQN's held random actions (its tuned preset's) are its way out."""
    first = first_line(rlpipe_cli, "algo=ppo", "env=mountaincar")
    assert first.startswith("rlpipe: note: ppo's defaults on MountainCar-v0: a known ")
    assert "algo=dqn env=mountaincar" in first
    assert trap_notice(DQNConfig(), "MountainCar-v0").startswith("rlpipe: note: dqn's")
    assert trap_notice(ReinforceConfig(), "MountainCar-v0") is not None
    assert trap_notice(DQNConfig(eps_zeta=2.0), "MountainCar-v0") is None
    assert trap_notice(ARSConfig(), "MountainCar-v0") is None
    assert trap_notice(SACConfig(), "MountainCar-v0") is None  # SAC cannot act there
