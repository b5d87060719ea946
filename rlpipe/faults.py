"""Test-only fault injection: a run sends itself a signal at a named point of its work.

``RLPIPE_FAULT=<point>[@<n>][:<SIGNAL>]`` makes the process send itself ``SIGNAL`` (default
``SIGKILL``) the ``n``-th time (default the first) it reaches ``<point>``; the fault-injection
suite (``pytest -m faults``) uses it to kill runs where a crash would hurt most. Unset, each
point costs one comparison. The points are :data:`POINTS`.
"""

from __future__ import annotations

import os
import signal

POINTS = {
    "train_step": "after a training iteration, before its metrics are logged",
    "checkpoint_write": "a checkpoint's temporary file is written, not yet renamed into place",
    "best_write": "the best evaluation's checkpoint's temporary file is written, not yet renamed",
    "final_checkpoint": "the final checkpoint is written, summary.json not yet",
    "summary": "summary.json's temporary file is written, not yet renamed into place",
    "truncate": "a metrics CSV's trimmed copy is written at resume, not yet renamed into place",
    "eval": "an evaluation is running (after its first env step)",
}
_SPEC = os.environ.get("RLPIPE_FAULT", "")
_counts: dict[str, int] = {}


def point(name: str) -> None:
    """Mark fault point ``name``; the ``RLPIPE_FAULT`` it matches sends its signal now."""
    if not _SPEC:
        return
    assert name in POINTS, name
    where, _, signame = _SPEC.partition(":")
    target, _, nth = where.partition("@")
    if target != name:
        return
    _counts[name] = _counts.get(name, 0) + 1
    if _counts[name] == int(nth or 1):
        os.kill(os.getpid(), signal.Signals[signame or "SIGKILL"])
