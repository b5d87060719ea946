"""Algorithms from outside the package: registration by call, by ``RLPIPE_PLUGINS`` and by
entry point (a light plug-in, found without torch), their config folders on Hydra's search
path, and the one-line errors of plug-ins that do not load or runs whose algorithm is missing."""

from __future__ import annotations

import importlib.metadata
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import run_module
from test_architecture import HEAVY

from rlpipe import RlpipeError, load_run
from rlpipe.config import Config, config_to_dict
from rlpipe.registry import ENTRY_POINT_GROUP, Registry

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

TOY = '''"""A light plug-in: its config and its registration, with the builder named by a string."""
from dataclasses import dataclass

import rlpipe
from rlpipe.config import AlgoConfig, checked


@dataclass
class ToyConfig(AlgoConfig):
    name: str = "toy"
    lr: float = checked(1e-3, "positive")


rlpipe.register("toy", ToyConfig, "toy_plugin.algo:Toy", conf="pkg://toy_plugin.conf")
'''


def toy_plugin(folder: Path) -> Path:
    """Write the ``toy_plugin`` package into ``folder``, with its tuned settings for CartPole
    (``toy_plugin/conf/tuned/toy_cartpole.yaml``) and no ``algo/toy.yaml``; returns ``folder``."""
    package = folder / "toy_plugin"
    (package / "conf" / "tuned").mkdir(parents=True)
    (package / "__init__.py").write_text(TOY)
    (package / "conf" / "__init__.py").write_text("")
    tuned = "# @package _global_\nalgo:\n  lr: 0.25\n"
    (package / "conf" / "tuned" / "toy_cartpole.yaml").write_text(tuned)
    return folder


def distribution(folder: Path, name: str, entry_points: dict[str, str]) -> Path:
    """An installed distribution ``name`` in ``folder`` (its ``.dist-info``) declaring
    ``entry_points`` in the ``rlpipe.algorithms`` group; returns ``folder``."""
    info = folder / f"{name}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    lines = "".join(f"{key} = {value}\n" for key, value in entry_points.items())
    (info / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n{lines}")
    return folder


def entry_points_of(monkeypatch, **points: str) -> None:
    """``importlib.metadata.entry_points(group=...)`` answers ``points`` (name: value)."""
    found = [importlib.metadata.EntryPoint(n, v, ENTRY_POINT_GROUP) for n, v in points.items()]
    monkeypatch.setattr(
        importlib.metadata,
        "entry_points",
        lambda group: found if group == ENTRY_POINT_GROUP else [],
    )


def test_register_by_call_imports_the_builder_only_when_asked(tmp_path, monkeypatch):
    (tmp_path / "lazy_algo.py").write_text(
        "from rlpipe.algos.configs import SACConfig as C\nB = 1\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    entry_points_of(monkeypatch)
    algorithms = Registry()
    algorithms.register("lazy", "lazy_algo:C", "lazy_algo:B", conf=tmp_path)
    assert "lazy" in algorithms and "lazy_algo" not in sys.modules
    assert algorithms.builder("lazy") == 1 and algorithms.config("lazy").__name__ == "SACConfig"
    assert algorithms.search_path() == [f"file://{tmp_path}"]
    with pytest.raises(RlpipeError, match="algo.name must be one of lazy; got 'other'"):
        algorithms.config("other")
    with pytest.raises(RlpipeError, match="conf= must be a folder of config files"):
        algorithms.register("lazy", "lazy_algo:C", "lazy_algo:B", conf=tmp_path / "nope")
    del sys.modules["lazy_algo"]


def test_an_entry_point_registers_its_algorithm_when_it_is_asked_for(
    tmp_path, monkeypatch, registry
):
    monkeypatch.syspath_prepend(str(toy_plugin(tmp_path)))
    entry_points_of(monkeypatch, toy="toy_plugin", dqn="no_such_module")
    assert "sac" in registry and "toy_plugin" not in sys.modules  # a known name loads nothing
    assert "toy" in registry and registry.config("toy").__name__ == "ToyConfig"
    assert "toy_plugin.algo" not in sys.modules  # the builder: when it is built
    # listing loads every entry point but one named after a registered algorithm (dqn, whose
    # module would not import): no error, dqn still rlpipe's
    assert {"ars", "dqn", "mbrl", "ppo", "reinforce", "sac", "toy"} <= set(registry)
    assert registry.builder("dqn").__module__ == "rlpipe.algos.dqn"
    assert "toy_cartpole" in registry.conf_options("tuned")


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("no_such_module", "entry point toy = 'no_such_module' of its package does not import"),
        (
            "json",
            "entry point toy = 'json' of its package registers no algorithm 'toy': its "
            "module must call rlpipe.register('toy', ...)",
        ),
    ],
    ids=["missing-module", "registers-nothing"],
)
def test_an_entry_point_that_does_not_register_is_one_line(monkeypatch, registry, value, message):
    entry_points_of(monkeypatch, toy=value)
    with pytest.raises(RlpipeError) as caught:
        registry.config("toy")
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_rlpipe_plugins_names_the_modules_to_import(tmp_path, monkeypatch, registry):
    monkeypatch.syspath_prepend(str(toy_plugin(tmp_path)))
    entry_points_of(monkeypatch)
    monkeypatch.setenv("RLPIPE_PLUGINS", "json, toy_plugin")
    assert "toy" in registry
    monkeypatch.setattr(registry, "_variable_read", False)
    monkeypatch.setenv("RLPIPE_PLUGINS", "no_such_plugin")
    with pytest.raises(
        RlpipeError,
        match="RLPIPE_PLUGINS names module 'no_such_plugin', which "
        "does not import .*; put its folder on PYTHONPATH",
    ):
        list(registry)


def test_a_run_of_an_algorithm_not_registered_says_how_to_make_it_importable(
    tmp_path, monkeypatch, registry
):
    data = config_to_dict(Config())
    data["algo"]["name"] = "td3"
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(data))
    entry_points_of(monkeypatch)
    with pytest.raises(RlpipeError) as caught:
        load_run(tmp_path)
    message = str(caught.value)
    assert message.startswith(f"{tmp_path / 'config.yaml'}: algorithm 'td3' is not registered")
    for way in (
        "rlpipe.algorithms entry point",
        "RLPIPE_PLUGINS=<module>",
        "rlpipe.register('td3'",
    ):
        assert way in message
    assert "damaged" not in message and "\n" not in message


def front_door(tmp_path: Path, *args: str) -> tuple[str, set[str]]:
    """``python -X importtime -m rlpipe args`` with the toy plug-in installed (an entry point):
    its output and the top-level packages it imported."""
    folder = distribution(toy_plugin(tmp_path / "site"), "toy-plugin", {"toy": "toy_plugin"})
    done = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "rlpipe", *args],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(folder)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    imported = {line.rpartition("|")[2].strip().split(".")[0] for line in done.stderr.splitlines()}
    lines = [line for line in done.stderr.splitlines() if not line.startswith("import time:")]
    return done.stdout + "\n".join(lines), imported


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--help"], "reinforce, sac, toy"),
        (["algo=toy", "--cfg", "job"], "lr: 0.25"),  # the plug-in's tuned/toy_cartpole.yaml
        (["algo=toy", "algo.lr=-1"], "rlpipe: error: algo.lr must be a finite number > 0, got -1"),
        (["algo=toy", "algo.lrr=1"], "Key 'lrr' not in 'ToyConfig'"),
    ],
    ids=["help", "cfg-job", "bad-value", "unknown-key"],
)
def test_an_installed_plugin_is_found_without_torch(tmp_path, args, expected):
    output, imported = front_door(tmp_path, *args)
    assert expected in output  # the plug-in was imported (which importtime does not list:
    # importlib.import_module goes round the import statement's timing)
    assert not imported & set(HEAVY), sorted(imported & set(HEAVY))


def test_an_installed_td3_sweeps_its_preset_and_plots(tmp_path):
    """examples/td3.py as an installed package would give it: an entry point ``td3 = td3``."""
    site = distribution(tmp_path / "site", "td3-example", {"td3": "td3"})
    sweep = tmp_path / "sweep"
    tiny = ["~tuned", "progress=false", "total_frames=40", "eval_episodes=2"]
    done = run_module(
        "rlpipe",
        "-m",
        "+experiment=td3_pendulum",  # a preset of the plug-in's config folder
        "seed=0,1",
        *tiny,
        "env.max_episode_steps=20",
        "algo.learning_starts=20",
        "algo.batch_size=8",
        "algo.hidden_sizes=[8]",
        f"hydra.sweep.dir={sweep}",
        cwd=tmp_path,
        pythonpath=EXAMPLES,
        env={"PYTHONPATH": str(site)},
    )
    assert done.returncode == 0, done.stderr
    assert "sweep of 2 jobs, 0 failed" in done.stdout + done.stderr
    assert all(
        yaml.safe_load((sweep / job / "config.yaml").read_text())["algo"]["name"] == "td3"
        for job in "01"
    )
    plotted = run_module("rlpipe.plot", str(sweep), cwd=tmp_path)  # metrics: no plug-in needed
    assert plotted.returncode == 0 and (sweep / "curves.png").is_file()


@pytest.mark.parametrize(
    ("args", "plugins", "message"),
    [
        (
            ["algo=td3"],
            None,
            "unknown algo option 'td3'; choose one of: ars, dqn, mbrl, ppo, reinforce, sac; an "
            "algorithm from outside rlpipe: install the package that provides it",
        ),
        (["--help"], "no_such_plugin", "RLPIPE_PLUGINS names module 'no_such_plugin', which does"),
        (
            ["algo=dqn"],
            "no_such_plugin",
            "RLPIPE_PLUGINS names module 'no_such_plugin', which does",
        ),
    ],
    ids=["unknown-algo", "help-missing-plugin", "train-missing-plugin"],
)
def test_the_command_line_says_how_to_bring_an_algorithm_in_one_line(
    tmp_path, args, plugins, message
):
    env = {"RLPIPE_PLUGINS": plugins} if plugins else None
    done = run_module("rlpipe", *args, f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path, env=env)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and message in lines[0], done.stderr
    assert not (tmp_path / "run").exists()
