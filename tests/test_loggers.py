"""Logger backends: CSV files, TensorBoard events, and a clear error for a missing extra."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from torchrl.record.loggers import CSVLogger, TensorboardLogger

from rlpipe import LoggerConfig, make_logger
from rlpipe.errors import RlpipeError
from rlpipe.loggers import EXTRAS, TeeLogger, require_extra, takes_video


def test_csv_logger_writes_csv(tmp_path: Path) -> None:
    logger = make_logger(LoggerConfig("csv"), tmp_path)
    assert isinstance(logger, CSVLogger)
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
    pytest.importorskip("tensorboard")
    try:
        require_extra("tensorboard", "logger=tensorboard")
    except RlpipeError as err:
        pytest.skip(str(err))
    logger = make_logger(LoggerConfig("tensorboard"), tmp_path / "run")
    assert isinstance(logger, TeeLogger)
    assert [type(inner) for inner in logger.loggers] == [CSVLogger, TensorboardLogger]
    assert takes_video(logger)
    logger.log_scalar("eval/return_mean", 3.0, step=1)
    logger.shutdown()
    assert list((tmp_path / "run" / "tensorboard").rglob("events.out.tfevents.*"))
    assert (tmp_path / "run" / "metrics" / "scalars" / "eval" / "return_mean.csv").is_file()
