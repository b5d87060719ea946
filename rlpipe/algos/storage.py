"""The replay storage of rlpipe's buffers (off-policy loop, MBRL): TorchRL's, with leaner writes."""

from __future__ import annotations

from typing import Any

from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage


class LeafStorage(LazyTensorStorage):
    """TorchRL's ``LazyTensorStorage`` (the same state dict, lengths and cursors) whose writes of
    a TensorDict holding exactly the storage's keys copy each leaf into the storage's tensor at
    the writer's index: TensorDict's ``__setitem__`` checks and routes each write, which on one
    transition costs several times the copies. The first write (which allocates the storage)
    and any other data take TorchRL's path. A loaded state lands on the storage's device."""

    def set(self, cursor: Any, data: Any, *, set_cursor: bool = True) -> None:
        if not self.initialized or self._storage_keys is not None or type(data) is not TensorDict:
            return super().set(cursor, data, set_cursor=set_cursor)
        leaves = list(data.items(True, True))
        targets = [self._storage.get(key, None) for key, _ in leaves]
        if any(t is None for t in targets) or len(targets) != len(self._storage.keys(True, True)):
            return super().set(cursor, data, set_cursor=set_cursor)
        if set_cursor:  # what TorchRL's set records before writing
            self._set_last_cursor(cursor)
            self._get_new_len(data, cursor)
        for target, (_, value) in zip(targets, leaves, strict=True):
            target[cursor] = value
        self._bump_mutation_revision()

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        """TorchRL's load, then the storage on the storage's device: TorchRL keeps the loaded
        tensors where they are, so a checkpoint read onto the CPU (as rlpipe reads them) left
        a resumed CUDA run's buffer there, and its first write failed."""
        super().load_state_dict(state_dict)
        if isinstance(self._storage, TensorDictBase) and self._storage.device != self.device:
            self._storage = self._storage.to(self.device)
