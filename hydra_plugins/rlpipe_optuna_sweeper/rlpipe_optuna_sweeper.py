"""Registers rlpipe's Optuna sweeper with Hydra: ``hydra/sweeper=optuna`` and its samplers
(``hydra/sweeper/sampler=tpe|random|grid``). The sweeper: :mod:`rlpipe.optuna_search`."""

from hydra.core.config_store import ConfigStore

from rlpipe.optuna_search import OptunaSearch, OptunaSweeperConf, sampler_confs


class OptunaSweeper(OptunaSearch):
    """Hydra's name for :class:`rlpipe.optuna_search.OptunaSearch` (plugins live here)."""


store = ConfigStore.instance()
store.store(group="hydra/sweeper", name="optuna", node=OptunaSweeperConf, provider="rlpipe")
for name, conf in sampler_confs().items():
    store.store(group="hydra/sweeper/sampler", name=name, node=conf, provider="rlpipe")
