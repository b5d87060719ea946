"""Every NumPy twin (what ARS's population rollouts run) computes what its torch module does.

The cases come from the code, not from a hand-written list: every ``nn.Module`` class defined
in rlpipe that implements :class:`rlpipe.models.NumpyForward`, and every activation in
:data:`rlpipe.algos.ars.population.NUMPY_ACTIVATIONS`. A new twin class without an example
below fails its case.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch
from torch import nn

import rlpipe  # noqa: F401  (imports every rlpipe module, so every twin class is defined)
from rlpipe.algos.ars import numpy_layer
from rlpipe.algos.ars.population import NUMPY_ACTIVATIONS
from rlpipe.models import ArgmaxAction, ClampAction, NumpyForward
from rlpipe.normalizer import Normalizer

SIZE = 6


def merged_normalizer() -> Normalizer:
    """A normaliser whose statistics came from several merges (loc and scale far from 0, 1)."""
    norm = Normalizer(SIZE)
    generator = torch.Generator().manual_seed(0)
    for rows in (1, 30, 7):
        norm.observe(torch.randn(rows, SIZE, generator=generator) * 4 + 3)
    return norm


# an instance of each rlpipe module class with a NumPy twin
EXAMPLES: dict[type[nn.Module], Callable[[], nn.Module]] = {
    Normalizer: merged_normalizer,
    ClampAction: lambda: ClampAction(-torch.linspace(0.5, 2, SIZE), torch.linspace(0.1, 3, SIZE)),
    ArgmaxAction: ArgmaxAction,
}


def twin_classes() -> list[type[nn.Module]]:
    """The ``nn.Module`` classes defined in rlpipe that implement ``NumpyForward``."""
    found, todo = set(), [nn.Module]
    while todo:
        for cls in todo.pop().__subclasses__():
            todo.append(cls)
            if cls.__module__.startswith("rlpipe.") and issubclass(cls, NumpyForward):
                found.add(cls)
    return sorted(found, key=lambda cls: f"{cls.__module__}.{cls.__qualname__}")


TWINS = twin_classes() + list(NUMPY_ACTIVATIONS)


def test_the_twins_are_found():
    assert TWINS
    assert {Normalizer, ClampAction, ArgmaxAction, nn.ReLU, nn.Tanh} <= set(TWINS)


@pytest.mark.parametrize("cls", TWINS, ids=[cls.__name__ for cls in TWINS])
def test_numpy_twin_computes_the_torch_forward(cls):
    if cls in NUMPY_ACTIVATIONS:
        module = cls()
    else:
        assert cls in EXAMPLES, f"add an example of {cls.__name__} to EXAMPLES"
        module = EXAMPLES[cls]()
        assert isinstance(module, NumpyForward)
    twin = numpy_layer(module)
    generator = torch.Generator().manual_seed(1)
    for rows in (1, 9):
        x = torch.randn(rows, SIZE, generator=generator) * 5
        expected = module(x).numpy()
        got = twin(x.numpy())
        assert isinstance(got, np.ndarray) and got.dtype == expected.dtype
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6)
