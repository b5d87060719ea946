"""The Ray backend of ARS rollouts: actors of one CPU each, here or anywhere in a Ray cluster."""

from __future__ import annotations

import socket
from typing import Any

from rlpipe.algos.ars.pool import RAY_INSTALL, Pool, Units
from rlpipe.algos.ars.rollout import RolloutResult, Rollouts
from rlpipe.errors import RlpipeError, check

RAY_PORT = 6379  # the port of a Ray head's GCS when an address names none


class RayActors(Pool):
    """Ray actors of one CPU each, on this machine or anywhere in a Ray cluster.

    Each actor is a :class:`Rollouts` holding its own env copies; ``workers`` 0 starts one per
    CPU of the cluster.
    """

    def __init__(
        self,
        units: Units,
        population: int,
        workers: int,
        *,
        address: str | None,
        num_cpus: int | None,
    ) -> None:
        self._owns_ray = _connect_ray(address, num_cpus)
        import ray

        self._ray = ray
        cpus = int(ray.cluster_resources().get("CPU", 0))
        workers = min(workers or cpus, population)
        super().__init__(units, population, max(workers, 1))
        try:
            check(
                1 <= workers <= cpus,
                f"{workers} Ray workers need as many CPUs, but the Ray cluster has {cpus}",
            )
            actor = ray.remote(num_cpus=1)(Rollouts)
            self.workers = [actor.remote(*units.args(w, self.chunk_size)) for w in range(workers)]
            # every actor has built its envs (ray.get raises the error of one that could not)
            ray.get([worker.__ray_ready__.remote() for worker in self.workers])
        except BaseException:
            self.close()
            raise

    def _submit(self, worker: Any, *message: Any) -> Any:
        return worker.run.remote(*message)

    def _wait(self, handles: list[Any]) -> list[Any]:
        return self._ray.wait(handles, num_returns=1)[0]

    def _collect(self, handle: Any) -> RolloutResult:
        return self._ray.get(handle)

    def close(self) -> None:
        for worker in self.workers:
            self._ray.kill(worker)
        self.workers = []
        if self._owns_ray and self._ray.is_initialized():
            self._ray.shutdown()


def _connect_ray(address: str | None, num_cpus: int | None) -> bool:
    """Start Ray here (``address`` None, ``num_cpus`` CPUs) or join the cluster at ``address``.

    Returns whether this call initialised Ray (and so should shut it down); a Ray the caller
    already initialised is used as it is.
    """
    try:
        import ray
    except ImportError as err:
        raise RlpipeError(f"the Ray backend needs Ray; install it with: {RAY_INSTALL}") from err
    if ray.is_initialized():
        return False
    if address not in (None, "auto"):
        _check_reachable(address)
    try:
        ray.init(
            address=address,
            num_cpus=num_cpus if address is None else None,
            include_dashboard=False,
            log_to_driver=False,
        )
    except ConnectionError as err:
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise RlpipeError(f"cannot connect to Ray at {address}: {message}") from err
    return True


def _check_reachable(address: str) -> None:
    """Fail in one line, within seconds, when nothing listens at a ``host:port`` Ray address.

    ``ray.init`` would retry an unreachable address for minutes.
    """
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host:
        host, port = port, str(RAY_PORT)
    check(port.isdigit(), f"Ray address {address!r} must be host:port, ray://host:port or auto")
    try:
        socket.create_connection((host, int(port)), timeout=5).close()
    except OSError as err:
        raise RlpipeError(
            f"cannot reach a Ray cluster at {address} ({err.strerror or err}); start one with "
            "`ray start --head` there, or fix the address"
        ) from err
