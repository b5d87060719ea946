"""Hyper-parameter search with Optuna as a Hydra sweeper (``hydra/sweeper=optuna``, the
``+sweep=...`` presets): the search space in Hydra's sweep syntax (``choice``, ``range``,
``interval``, ``tag(log, ...)``), trials launched in batches through Hydra's launcher, each
trial's returned final eval mean told to the study. Works with current Optuna (4 and later);
the Hydra plugin that registers it lives in ``hydra_plugins/rlpipe_optuna_sweeper``."""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import ChoiceSweep, IntervalSweep, Override, RangeSweep
from hydra.core.plugins import Plugins
from hydra.core.utils import JobStatus
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import MISSING, DictConfig, OmegaConf

from rlpipe.errors import RlpipeError, check

PLUGIN = "hydra_plugins.rlpipe_optuna_sweeper.rlpipe_optuna_sweeper"
SAMPLERS = {"tpe": "TPESampler", "random": "RandomSampler", "grid": "GridSampler"}


@dataclass
class SamplerConf:
    """An Optuna sampler: ``hydra/sweeper/sampler=tpe|random|grid`` (``seed``: repeatable)."""

    _target_: str = "optuna.samplers.TPESampler"
    seed: int | None = None
    _partial_: bool = False  # the grid sampler is built once the search space is known


def sampler_confs() -> dict[str, SamplerConf]:
    """The samplers by option name (``grid``: every combination of ``choice`` sweeps)."""
    return {
        name: SamplerConf(f"optuna.samplers.{cls}", _partial_=name == "grid")
        for name, cls in SAMPLERS.items()
    }


@dataclass
class OptunaSweeperConf:
    """``hydra.sweeper.*`` of ``hydra/sweeper=optuna``."""

    _target_: str = f"{PLUGIN}.OptunaSweeper"
    defaults: list[Any] = field(default_factory=lambda: [{"sampler": "tpe"}])
    sampler: Any = MISSING  # built by Hydra from hydra/sweeper/sampler
    direction: str = "minimize"  # or maximize: the trial's returned value (the final eval mean)
    study_name: str | None = None
    storage: str | None = None  # e.g. sqlite:///optuna.db: a study kept across sweeps
    n_trials: int = 20
    n_jobs: int = 1  # trials launched together, one batch (parallel with a parallel launcher)
    max_failure_rate: float = 0.0  # the share of failed trials that stops the search
    params: dict[str, str] | None = None  # key -> a sweep: choice(...), interval(...), ...


def distribution(override: Override) -> Any:
    """The Optuna distribution of one sweep override, e.g. ``algo.lr=tag(log, interval(1e-4,
    1e-2))``."""
    from optuna.distributions import CategoricalDistribution, FloatDistribution, IntDistribution

    value = override.value()
    if isinstance(value, ChoiceSweep):
        return CategoricalDistribution(list(value.list))
    if isinstance(value, RangeSweep):
        numbers = (value.start, value.stop, value.step)
        if all(isinstance(n, int) for n in numbers):
            return IntDistribution(value.start, value.stop - 1, step=value.step)
        return FloatDistribution(value.start, value.stop - value.step, step=value.step)
    if isinstance(value, IntervalSweep):
        log = "log" in value.tags
        if all(isinstance(n, int) for n in (value.start, value.end)):
            return IntDistribution(value.start, value.end, log=log)
        return FloatDistribution(value.start, value.end, log=log)
    raise RlpipeError(
        f"{override.input_line}: an Optuna search takes choice(...), range(...) or "
        "interval(...) (tag(log, interval(...)) for a log scale)"
    )


class OptunaSearch(Sweeper):
    """The sweeper: asks the study for ``n_jobs`` trials at a time, launches them as jobs with
    their sampled values as overrides, and tells the study each job's returned value (a job that
    failed or returned no number: a failed trial). ``optimization_results.yaml`` in the sweep dir
    holds the best parameters and value."""

    def __init__(self, **conf: Any) -> None:
        params = conf.pop("params", None)
        self.conf = OptunaSweeperConf(**conf, params=None if params is None else dict(params))
        check(
            self.conf.direction in ("minimize", "maximize"),
            f"hydra.sweeper.direction must be minimize or maximize; got {self.conf.direction!r}",
        )
        self.launcher: Any = None
        self.config: DictConfig | None = None

    def setup(
        self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig
    ) -> None:
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )

    def sweep(self, arguments: list[str]) -> None:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)  # rlpipe prints each trial's line
        fixed, space = self._space(arguments)
        sweep_dir = Path(self.config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)
        OmegaConf.save(self.config, sweep_dir / "multirun.yaml")
        study = optuna.create_study(
            study_name=self.conf.study_name,
            storage=self.conf.storage,
            sampler=self._sampler(space),
            direction=self.conf.direction,
            load_if_exists=True,
        )
        done = failed = 0
        while done < self.conf.n_trials:
            batch_size = min(self.conf.n_jobs, self.conf.n_trials - done)
            trials = [study.ask(space) for _ in range(batch_size)]
            batch = [[*map(_override, t.params.items()), *fixed] for t in trials]
            stop = False
            for trial, job in zip(trials, self.launcher.launch(batch, initial_job_idx=done)):
                value = _value(job)
                stop |= _tell(study, trial, value)
                failed += value is None
            done += len(trials)
            check(
                failed / done <= self.conf.max_failure_rate,
                f"{failed} of {done} Optuna trials failed, more than "
                f"hydra.sweeper.max_failure_rate={self.conf.max_failure_rate}",
            )
            if stop:  # the grid sampler's grid is done
                break
        self._save_best(study, sweep_dir)

    def _space(self, arguments: Sequence[str]) -> tuple[list[str], dict[str, Any]]:
        """The fixed overrides and the search space (``params``, then the command line's)."""
        params = [f"{k}={v}" for k, v in (self.conf.params or {}).items()]
        fixed, space = [], {}
        for override in OverridesParser.create().parse_overrides([*params, *arguments]):
            key = override.get_key_element()
            if override.is_sweep_override():
                space[key] = distribution(override)
            else:
                space.pop(key, None)
                fixed.append(f"{key}={override.get_value_element_as_str()}")
        check(
            bool(space),
            "an Optuna sweep needs a search space: hydra.sweeper.params or key=choice(...)",
        )
        return fixed, space

    def _sampler(self, space: dict[str, Any]) -> Any:
        """The sampler Hydra built (the grid's, built here on the ``choice`` sweeps)."""
        sampler = self.conf.sampler
        if not isinstance(sampler, functools.partial):
            return sampler
        grid = {key: list(d.choices) for key, d in space.items() if hasattr(d, "choices")}
        check(len(grid) == len(space), "hydra/sweeper/sampler=grid takes choice(...) sweeps only")
        return sampler(search_space=grid)

    def _save_best(self, study: Any, sweep_dir: Path) -> None:
        complete = [t for t in study.trials if t.value is not None]
        if not complete:
            return
        best = {"name": "optuna", "best_params": study.best_params, "best_value": study.best_value}
        OmegaConf.save(OmegaConf.create(best), sweep_dir / "optimization_results.yaml")


def _override(item: tuple[str, Any]) -> str:
    """``key=value`` in Hydra's syntax for a sampled value."""
    key, value = item
    return f"{key}={Override._get_value_element_as_str(value)}"


def _value(job: Any) -> float | None:
    """A finished job's returned number (None: the job failed or returned none)."""
    if job.status != JobStatus.COMPLETED:
        return None
    value = job.return_value
    return float(value) if isinstance(value, (int, float)) and math.isfinite(value) else None


def _tell(study: Any, trial: Any, value: float | None) -> bool:
    """Tell ``study`` the trial's value (None: failed); True when the sampler asks to stop (the
    grid sampler, once its grid is done: the trial is recorded all the same)."""
    from optuna.trial import TrialState

    try:
        study.tell(trial, value, state=None if value is not None else TrialState.FAIL)
    except RuntimeError as err:
        if "Study.stop" not in str(err):
            raise
        return True
    return False
