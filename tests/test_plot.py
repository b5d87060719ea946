"""``python -m rlpipe.plot`` and ``curve.png``: images that exist, are sane and are not blank."""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

import matplotlib.image as mpimg
import pytest
from conftest import assert_one_error_line, run_module

from rlpipe import Config, DQNConfig, train
from rlpipe.plot import main


def tiny_config(seed: int) -> Config:
    return Config(
        algo=DQNConfig(),
        seed=seed,
        device="cpu",
        total_frames=200,
        eval_every=100,
        eval_episodes=2,
        progress=False,
    )


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    """Two tiny DQN runs that differ only by seed."""
    root = tmp_path_factory.mktemp("plot")
    dirs = [root / f"seed{seed}" for seed in (0, 1)]
    for seed, run_dir in enumerate(dirs):
        train(tiny_config(seed), run_dir)
    return dirs


def assert_picture(path: Path) -> None:
    assert path.is_file(), path
    pixels = mpimg.imread(path)
    height, width = pixels.shape[:2]
    assert 200 <= height <= 4000 and 200 <= width <= 4000, pixels.shape
    assert pixels.std() > 0  # not blank


def test_curve_png_of_a_run(runs: list[Path]) -> None:
    assert_picture(runs[0] / "curve.png")


def test_plot_groups_seeds_into_one_line(runs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "both.png"
    proc = run_module("rlpipe.plot", *map(str, runs), "agg=iqm", f"out={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "1 group(s) from 2 run(s)" in proc.stdout
    assert "2 seed(s)" in proc.stdout
    assert str(out) in proc.stdout
    assert_picture(out)


def test_plot_svg(runs: list[Path], tmp_path: Path) -> None:
    out = tmp_path / "one.png"
    proc = run_module("rlpipe.plot", str(runs[0]), "svg=true", f"out={out}", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert_picture(out)
    svg = out.with_suffix(".svg")
    assert svg.is_file()
    assert "<svg" in svg.read_text()


def test_plot_default_out_is_in_the_dir(runs: list[Path], tmp_path: Path) -> None:
    proc = run_module("rlpipe.plot", str(runs[1]), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert_picture(runs[1] / "curves.png")


def test_plots_of_several_dirs_go_beside_them_not_here(runs: list[Path], tmp_path: Path) -> None:
    here = tmp_path / "elsewhere"
    here.mkdir()
    proc = run_module("rlpipe.plot", *map(str, runs), cwd=here)
    assert proc.returncode == 0, proc.stderr
    assert_picture(runs[0].parent / "curves.png")  # the dir that holds both runs
    assert not any(here.iterdir())


def test_titles_and_bands_say_only_what_is_there(runs: list[Path], tmp_path: Path) -> None:
    """One seed per line: no confidence band claimed; curve.png's ± std band stays within the
    returns each evaluation saw (Acrobot's band cannot go below -500)."""
    from rlpipe.figures import groups_figure, run_figure
    from rlpipe.runs import Group

    one = groups_figure([Group("seed0", runs[:1])], metric="eval/return_mean", aggregate="mean")
    assert (
        one._suptitle.get_text()
        == "greedy evaluation return: one seed per line (no confidence band)"
    )
    assert not one.axes[0].collections  # no band drawn
    run = tmp_path / "acrobot"
    scalars = run / "metrics" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    rows = {"mean": (-480.0, -300.0), "std": (40.0, 150.0), "min": (-500.0, -500.0)}
    rows["max"] = (-420.0, -100.0)
    for name, values in rows.items():
        (scalars / f"return_{name}.csv").write_text(f"1000,{values[0]}\n2000,{values[1]}\n")
    (run / "config.yaml").write_text("env:\n  id: Acrobot-v1\nalgo:\n  name: dqn\n")
    (band,) = run_figure(run).axes[0].collections
    lowest = band.get_paths()[0].vertices[:, 1].min()
    assert lowest == -500.0  # mean - std would be -520 and -450: clipped to the min seen


@pytest.mark.parametrize(
    "args, message",
    [
        (["EMPTY"], "no metrics under"),
        (["EMPTY/missing"], "is not a directory"),
        (["RUN", "agg=median"], "agg must be one of"),
        (["RUN", "colour=red"], "unknown option 'colour'"),
        (["EMPTY/lr=0.1"], "lr=0.1 is not a directory (nor an option: agg, svg, metric, out, "),
        (["RUN", "parent=maybe"], "parent must be true or false; got 'maybe'"),
        ([], "pass at least one run dir"),
    ],
)
def test_plot_bad_input(
    runs: list[Path],
    tmp_path: Path,
    args: list[str],
    message: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """In-process (fast): ``main`` prints one ``rlpipe: error:`` line and exits with 2."""
    monkeypatch.chdir(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    argv = [a.replace("EMPTY", str(empty)).replace("RUN", str(runs[0])) for a in args]
    assert_one_error_line(main, argv, message, capsys)
    assert not list(tmp_path.rglob("*.png"))


def test_plot_no_metrics_cli(tmp_path: Path) -> None:
    """The command line on a dir without metrics: one line on stderr, exit 2, no picture."""
    proc = run_module("rlpipe.plot", str(tmp_path), cwd=tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("rlpipe: error: no metrics under")
    assert not list(tmp_path.rglob("*.png"))


def test_plot_dir_with_equals_sign(
    runs: list[Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """outputs/lr=0.1/ is a directory, not an option: existing paths win."""
    sweep = tmp_path / "outputs" / "lr=0.1"
    shutil.copytree(runs[0], sweep / "0")
    shutil.copytree(runs[1], sweep / "1")
    monkeypatch.chdir(tmp_path)
    main(["outputs/lr=0.1/", "agg=iqm"])
    assert "1 group(s) from 2 run(s)" in capsys.readouterr().out
    assert_picture(sweep / "curves.png")
    monkeypatch.chdir(tmp_path / "outputs")
    main(["lr=0.1", "out=../here.png"])  # a bare name with = that exists: a directory too
    assert_picture(tmp_path / "here.png")


def no_drawing(*args: object, **kwargs: object) -> None:
    raise AssertionError("drew before the output location was checked")


def test_plot_out_under_a_file(
    runs: list[Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(sys.modules["rlpipe.plot"], "plot_groups", no_drawing)
    blocker = tmp_path / "a-file"
    blocker.write_text("x\n")
    out = blocker / "curves.png"
    message = f"cannot write {out}: {blocker} is not a directory; pick a writable place with out="
    assert_one_error_line(main, [str(runs[0]), f"out={out}"], message, capsys)


def test_plot_read_only_run_dir(
    runs: list[Path],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The default out, <DIR>/curves.png, in a dir that takes no new file (simulated: root
    writes through chmod 0o555): one line naming it, before anything is drawn."""
    monkeypatch.setattr(sys.modules["rlpipe.plot"], "plot_groups", no_drawing)
    copy = tmp_path / "run"
    shutil.copytree(runs[0], copy)
    (copy / "curves.png").unlink(missing_ok=True)
    real = tempfile.TemporaryFile

    def read_only(*args: object, dir: str | Path | None = None, **kwargs: object):  # noqa: A002
        if dir is not None and Path(dir) == copy:
            raise PermissionError(30, "Read-only file system")
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    message = f"cannot write {copy / 'curves.png'}: Read-only file system; pick a writable place"
    assert_one_error_line(main, [str(copy)], message, capsys)
    assert not (copy / "curves.png").exists()


@pytest.mark.skipif(
    os.geteuid() == 0,
    reason="root writes into a chmod 0o555 dir: run pytest as another user for this one; the "
    "read-only case runs for root too (test_plot_read_only_run_dir, simulated)",
)
def test_plot_chmod_read_only_run_dir(
    runs: list[Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    copy = tmp_path / "run"
    shutil.copytree(runs[0], copy)
    (copy / "curves.png").unlink(missing_ok=True)
    copy.chmod(0o555)
    try:
        assert_one_error_line(main, [str(copy)], "out=<file.png>", capsys)
    finally:
        copy.chmod(0o755)
    assert not (copy / "curves.png").exists()


def test_a_figure_a_reader_understands(
    runs: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Panels per env titled by env and algorithm, legends from the differing overrides (not
    folders), markers on sparse points, a flat line not blown up, relative paths in titles."""
    from dataclasses import replace

    from rlpipe import EnvConfig
    from rlpipe.figures import _title, groups_figure
    from rlpipe.runs import Group, group_runs

    car = [tmp_path / f"car{seed}" for seed in (0, 1)]
    for seed, run_dir in enumerate(car):
        train(replace(tiny_config(seed), env=EnvConfig(id="MountainCar-v0")), run_dir)
    for run_dir, env in [*((r, "cartpole") for r in runs), *((r, "mountaincar") for r in car)]:
        (run_dir / ".hydra").mkdir(exist_ok=True)  # as a sweep over env and seed records them
        seed = run_dir.name[-1]
        (run_dir / ".hydra" / "overrides.yaml").write_text(f"- env={env}\n- seed={seed}\n")
    fig = groups_figure(group_runs([*runs, *car]), metric="eval/return_mean", aggregate="mean")
    axes = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in axes] == ["CartPole-v1 · dqn", "MountainCar-v0 · dqn"]
    assert fig._suptitle.get_text().startswith("greedy evaluation return: mean over seeds")
    for ax in axes:
        (line,) = ax.get_lines()
        assert line.get_marker() == "o"  # 2 eval points: each one marked
        assert [t.get_text() for t in ax.get_legend().get_texts()] == ["mean of 2 seeds"]
    low, high = axes[1].get_ylim()  # MountainCar: -200 flat; the axis spans >= 10% of 200
    assert high - low >= 20 and low < -200 < high
    one = groups_figure(
        [Group("algo.lr=0.001", runs), Group("algo.lr=0.0001", car[:1])],
        metric="eval/return_mean",
        aggregate="mean",
    )
    labels = [t.get_text() for t in one.axes[0].get_legend().get_texts()]
    assert labels == ["algo.lr=0.001 (mean of 2)"]  # its panel (CartPole); the other has its own
    monkeypatch.chdir(tmp_path)
    assert _title(car[0]) == "dqn on MountainCar-v0: car0"


def _synthetic_run(run: Path, rows: dict[int, float], init_from: str | None = None) -> Path:
    """A run dir with an eval curve and a config.yaml naming its parent (as train pins it)."""
    scalars = run / "metrics" / "scalars" / "eval"
    scalars.mkdir(parents=True)
    (scalars / "return_mean.csv").write_text("".join(f"{f},{v}\n" for f, v in rows.items()))
    parent = f"init_from: {init_from}\n" if init_from else ""
    (run / "config.yaml").write_text(f"env:\n  id: CartPole-v1\nalgo:\n  name: dqn\n{parent}")
    return run


def test_plot_draws_a_fine_tuned_run_after_its_parents(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The parent's rows up to the checkpoint the child began from, then the child's, counted
    on from there (a grandparent too); parent=false: the child alone, from 0."""
    from rlpipe.figures import groups_figure
    from rlpipe.runs import Group, history

    root = _synthetic_run(tmp_path / "root", {500: 5.0, 1000: 10.0})
    pinned = f"{root}:ckpt_000000000500.pt"
    parent = _synthetic_run(tmp_path / "parent", {1000: 1.0, 2000: 2.0, 3000: 3.0}, pinned)
    child = _synthetic_run(
        tmp_path / "child", {1000: 30.0, 2000: 40.0}, f"{parent}:ckpt_000000002000.pt"
    )
    frames, values, starts = history(child, "eval/return_mean")
    assert frames.tolist() == [500, 1500, 2500, 3500, 4500]
    assert values.tolist() == [5.0, 1.0, 2.0, 30.0, 40.0]
    assert starts == [500, 2500]
    fig = groups_figure([Group("child", [child])], metric="eval/return_mean", aggregate="mean")
    (ax,) = fig.axes
    assert ax.lines[0].get_xdata().tolist() == [500, 1500, 2500, 3500, 4500]
    assert [line.get_xdata()[0] for line in ax.lines[1:]] == [500, 2500]  # where each began
    main([str(child)])
    assert_picture(child / "curves.png")
    alone = groups_figure(
        [Group("child", [child])], metric="eval/return_mean", aggregate="mean", parents=False
    )
    assert [line.get_xdata().tolist() for line in alone.axes[0].lines] == [[1000, 2000]]
    main([str(child), "parent=false", f"out={tmp_path / 'alone.png'}"])
    assert_picture(tmp_path / "alone.png")
    shutil.rmtree(root)  # a parent no longer there: left out, with a warning; still counted on
    frames, _, _ = history(child, "eval/return_mean")
    assert frames.tolist() == [1500, 2500, 3500, 4500]
    assert f"{root}, the run {parent} began from, is not there" in capsys.readouterr().err
