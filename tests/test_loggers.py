"""Logger backends: CSV files, TensorBoard events, and a clear error for a missing extra."""

from __future__ import annotations

import gc
import os
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import pytest
import torch
from conftest import TINY, needs_extra
from torchrl.record.loggers import CSVLogger, TensorboardLogger

from rlpipe import LoggerConfig, make_logger
from rlpipe import loggers as loggers_module
from rlpipe.errors import RlpipeError
from rlpipe.loggers import EXTRAS, CsvLogger, TeeLogger, require_extra, takes_video


def test_csv_logger_writes_csv(tmp_path: Path) -> None:
    logger = make_logger(LoggerConfig("csv"), tmp_path)
    assert isinstance(logger, CsvLogger)
    logger.log_scalar("eval/return_mean", 12.5, step=100)
    logger.log_scalar("eval/return_mean", 20.0, step=200)
    logger.shutdown()
    csv = tmp_path / "metrics" / "scalars" / "eval" / "return_mean.csv"
    rows = [line.split(",") for line in csv.read_text().splitlines()]
    assert [(int(step), float(value)) for step, value in rows] == [(100, 12.5), (200, 20.0)]
    assert not takes_video(logger)


def test_none_logger(tmp_path: Path) -> None:
    assert make_logger(LoggerConfig("none"), tmp_path) is None
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("backend", ["tensorboard", "wandb", "mlflow"])
def test_missing_extra_names_the_install_command(
    backend: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = EXTRAS[backend][0]
    monkeypatch.setitem(sys.modules, module, None)  # importing it now raises ImportError
    with pytest.raises(RlpipeError) as err:
        make_logger(LoggerConfig(backend), tmp_path)
    message = str(err.value)
    assert f'pip install "rlpipe[{backend}]"' in message
    assert f"logger={backend}" in message and module in message
    assert "\n" not in message
    assert not any(tmp_path.iterdir())  # checked before anything is written


def test_require_extra_video(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(RlpipeError, match=r'video=true needs.*pip install "rlpipe\[video\]"'):
        require_extra("video", "video=true")


def test_tensorboard_writes_events_and_csv(tmp_path: Path) -> None:
    needs_extra("tensorboard", "tensorboard")
    try:
        require_extra("tensorboard", "logger=tensorboard")
    except RlpipeError as err:
        pytest.skip(str(err))
    logger = make_logger(LoggerConfig("tensorboard"), tmp_path / "run")
    assert isinstance(logger, TeeLogger)
    assert [type(inner) for inner in logger.loggers] == [CsvLogger, TensorboardLogger]
    assert takes_video(logger)
    logger.log_scalar("eval/return_mean", 3.0, step=1)
    logger.shutdown()
    assert list((tmp_path / "run" / "tensorboard").rglob("events.out.tfevents.*"))
    assert (tmp_path / "run" / "metrics" / "scalars" / "eval" / "return_mean.csv").is_file()


def test_csv_files_match_torchrl_csv_logger(tmp_path: Path) -> None:
    """The same files, byte for byte, as TorchRL's CSVLogger: old run dirs and readers work."""
    ours = CsvLogger(exp_name="metrics", log_dir=tmp_path / "ours")
    theirs = CSVLogger(exp_name="metrics", log_dir=str(tmp_path / "theirs"))
    values = [12.5, 3, float("nan"), float("-inf"), 1e-20, torch.tensor(2.5), -0.0]
    for logger in (ours, theirs):
        for step, value in enumerate(values):
            logger.log_scalar("eval/return_mean", value, step=100 * step)
            logger.log_scalar("train/loss", value, step=7 * step)
            logger.log_scalar("time/fps", value)  # no step: counts rows, as TorchRL does
        logger.shutdown()
    for name in ("eval/return_mean", "train/loss", "time/fps"):
        mine = (tmp_path / "ours" / "metrics" / "scalars" / f"{name}.csv").read_bytes()
        assert mine == (tmp_path / "theirs" / "metrics" / "scalars" / f"{name}.csv").read_bytes()
        assert mine.count(b"\n") == len(values)


def test_csv_logger_appends_and_rows_are_on_disk_at_once(tmp_path: Path) -> None:
    """A resumed run appends to its files; each row is in the file as soon as it is logged."""
    path = tmp_path / "metrics" / "scalars" / "eval" / "return_mean.csv"
    path.parent.mkdir(parents=True)
    path.write_text("100,1.0\n")
    logger = CsvLogger(log_dir=tmp_path)
    logger.log_scalar("eval/return_mean", 2.0, step=200)
    assert path.read_text() == "100,1.0\n200,2.0\n"  # not buffered: no flush, no shutdown
    logger.shutdown()
    logger.shutdown()  # twice is fine
    assert path.read_text() == "100,1.0\n200,2.0\n"


def test_csv_logger_bounds_open_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(loggers_module, "MAX_OPEN_FILES", 3)
    logger = CsvLogger(log_dir=tmp_path)
    for step in range(4):
        for metric in range(10):
            logger.log_scalar(f"group/m{metric}", metric + step, step=step)
            assert len(logger._files) <= 3
    logger.shutdown()
    assert not logger._files
    for metric in range(10):
        path = tmp_path / "metrics" / "scalars" / "group" / f"m{metric}.csv"
        assert path.read_text() == "".join(f"{s},{float(metric + s)}\n" for s in range(4))


def test_csv_logger_takes_no_video_and_no_hparams(tmp_path: Path) -> None:
    logger = CsvLogger(log_dir=tmp_path)
    assert not takes_video(logger)
    with pytest.raises(NotImplementedError):
        logger.log_video("eval/video", torch.zeros(1, 2, 3, 4, 4), step=1)
    logger.log_hparams({"lr": 0.1})  # config.yaml holds them
    logger.shutdown()
    assert not any(tmp_path.iterdir())  # nothing written until a scalar is logged


def test_csv_logger_memory_is_flat(tmp_path: Path) -> None:
    """No row stays in memory (TorchRL's CSVLogger keeps them all: ~2 MB for these rows)."""
    logger = CsvLogger(log_dir=tmp_path)
    names = [f"train/metric_{i}" for i in range(20)]
    for step in range(50):  # warm up: files open, dicts sized
        for name in names:
            logger.log_scalar(name, 1.5, step=step)
    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for step in range(1000):
            for name in names:
                logger.log_scalar(name, step * 0.5, step=step)  # 20,000 rows
        gc.collect()
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
        logger.shutdown()
    assert grown < 20_000, f"logger memory grew by {grown} bytes over 20,000 rows"
    assert (tmp_path / "metrics" / "scalars" / "train" / "metric_0.csv").read_text().count(
        "\n"
    ) == 1050


# eval/return_mean.csv on a full disk: its file is opened on /dev/full (every write: ENOSPC);
# rlpipe writes no file through a link, so the disk is put in place of the file this way
FULL_DISK = textwrap.dedent(
    """
    import rlpipe.files

    _open_append = rlpipe.files.open_append

    def _on_a_full_disk(path, *args, **kwargs):
        if str(path).endswith("eval/return_mean.csv"):
            return open("/dev/full", "ab", buffering=0)
        return _open_append(path, *args, **kwargs)

    rlpipe.files.open_append = _on_a_full_disk
    """
)
FULL_DISK_SCRIPT = FULL_DISK + textwrap.dedent(
    """
    import sys
    from rlpipe.loggers import CsvLogger

    logger = CsvLogger(log_dir=sys.argv[1])  # kept alive until the interpreter exits
    logger.log_scalar("train/loss", 1.0, step=1)
    try:
        logger.log_scalar("eval/return_mean", 1.0, step=1)
    except OSError as err:
        print("raised", err.errno)
    logger.log_scalar("train/loss", 2.0, step=2)
    """
)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_csv_logger_on_a_full_disk(tmp_path: Path) -> None:
    """ENOSPC propagates from log_scalar, and nothing fails again at interpreter exit."""
    proc = subprocess.run(
        [sys.executable, "-c", FULL_DISK_SCRIPT, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "raised 28"  # ENOSPC
    assert "Exception ignored" not in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    loss = tmp_path / "metrics" / "scalars" / "train" / "loss.csv"
    assert loss.read_text() == "1,1.0\n2,2.0\n"  # the other metrics go on


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux)")
def test_training_on_a_full_disk_fails_with_one_line(tmp_path: Path) -> None:
    """A run whose metric write hits ENOSPC: one error line, no traceback wall at exit."""
    run_dir = tmp_path / "run"
    args = ["algo=dqn", *TINY, f"hydra.run.dir={run_dir}"]
    script = FULL_DISK + f"import sys; sys.argv = ['rlpipe', *{args!r}]\n"
    script += "from rlpipe.__main__ import main; main()\n"
    env = {**os.environ, "SDL_VIDEODRIVER": "dummy"}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.run(
        [sys.executable, "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"rlpipe: error: cannot write metrics in {run_dir}: No space left on device; free some "
        "disk space or pick a writable hydra.run.dir, then resume"
    ]


TRACKED = [
    "~tuned",
    "total_frames=400",
    "eval_every=200",
    "eval_episodes=2",
    "algo.lr=3e-4",
    "log_every=100",
]


def _tracked_run(rlpipe_cli, tmp_path: Path, backend: str) -> Path:
    """A tiny CLI run with ``logger=<backend>``; its run dir."""
    run_dir = tmp_path / "run"
    done = rlpipe_cli("progress=false", f"logger={backend}", *TRACKED, run_dir=run_dir)
    assert done.returncode == 0, done.stderr
    if backend == "tensorboard":  # rlpipe's own lines only (no "ALSA lib ... Unknown PCM")
        lines = (done.stdout + done.stderr).splitlines()
        assert lines and all(line.startswith("rlpipe: ") for line in lines), lines
    return run_dir


def test_tensorboard_holds_the_config_name_curve_and_loss_cadence(tmp_path, rlpipe_cli) -> None:
    needs_extra("tensorboard", "tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.plugins.hparams import plugin_data_pb2

    run_dir = _tracked_run(rlpipe_cli, tmp_path, "tensorboard")
    (folder,) = (run_dir / "tensorboard").iterdir()
    assert folder.name == "dqn_CartPole-v1_seed=0_untuned_algo.lr=3e-4_"  # named by what decides it
    hparams, images, loss_steps = {}, [], []
    for events in folder.rglob("events.out.tfevents.*"):
        acc = EventAccumulator(str(events.parent), size_guidance={"tensors": 0, "images": 0})
        acc.Reload()
        try:
            contents = acc.PluginTagToContent("hparams").values()
        except KeyError:  # an events file without hparams (the scalars')
            contents = []
        for raw in contents:
            data = plugin_data_pb2.HParamsPluginData.FromString(raw)
            if data.HasField("session_start_info"):
                hparams.update(data.session_start_info.hparams)
        images += acc.Tags()["images"]
        if "train/loss" in acc.Tags()["scalars"]:
            loss_steps = [e.step for e in acc.Scalars("train/loss")]
    assert hparams["algo.lr"].number_value == pytest.approx(3e-4)
    assert hparams["env.id"].string_value == "CartPole-v1" and "seed" in hparams
    assert images == ["curve"]  # curve.png, as an image
    # log_every=100: a loss row every ~100 frames once updates start (not every 1,000)
    assert len(loss_steps) >= 2 and max(b - a for a, b in zip(loss_steps, loss_steps[1:])) <= 104


def test_mlflow_holds_the_config_name_tags_and_files(tmp_path, rlpipe_cli) -> None:
    needs_extra("mlflow", "mlflow")
    import mlflow

    run_dir = _tracked_run(rlpipe_cli, tmp_path, "mlflow")
    client = mlflow.MlflowClient(f"sqlite:///{run_dir / 'mlflow.db'}")
    (run,) = client.search_runs([client.get_experiment_by_name("rlpipe").experiment_id])
    assert run.data.params["algo.lr"] == "0.0003" and run.data.params["env.id"] == "CartPole-v1"
    assert run.data.tags["mlflow.runName"] == "dqn CartPole-v1 seed=0 [algo.lr=3e-4]"
    assert (run.data.tags["algo"], run.data.tags["seed"]) == ("dqn", "0")
    assert [a.path for a in client.list_artifacts(run.info.run_id)] == ["curve.png"]


def test_wandb_holds_the_config_name_tags_and_files(tmp_path, rlpipe_cli) -> None:
    needs_extra("wandb", "wandb")
    import shutil
    import subprocess

    run_dir = _tracked_run(rlpipe_cli, tmp_path, "wandb")  # offline: under run_dir/wandb
    (log,) = (run_dir / "wandb").glob("offline-run-*/run-*.wandb")
    wandb_cli = shutil.which("wandb")
    assert wandb_cli is not None
    # W&B's own reader of a run's transaction log (records as text when not on a terminal)
    text = subprocess.run(
        [wandb_cli, "leet", "inspect", str(log)], capture_output=True, text=True, timeout=120
    ).stdout
    assert 'display_name:  "dqn CartPole-v1 seed=0 [algo.lr=3e-4]"' in text
    assert 'tags:  "algo:dqn"' in text and 'tags:  "seed:0"' in text
    assert 'key:  "algo.lr"\n      value_json:  "0.0003"' in text
    assert 'path:  "curve.png"' in text
