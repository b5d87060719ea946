"""benchmarks/denormals.py's count of subnormal parameters, which must not trust the CPU's
comparisons while subnormals are flushed (they compare as zeros then)."""

from __future__ import annotations

import importlib

import torch
from conftest import benchmarks_importable


def test_subnormals_are_counted_from_their_bits_even_when_flushed():
    with benchmarks_importable():
        denormals = importlib.import_module("denormals")
    layer = torch.nn.Linear(2, 3)
    bits = torch.tensor([[0x00000001, 0], [0x3F800000, 0x807FFFFF], [0x00800000, 0x80000000]])
    with torch.no_grad():  # a smallest and a largest negative subnormal among normals and zeros
        layer.weight.view(torch.int32).copy_(bits.to(torch.int32))
        layer.bias.view(torch.int32).copy_(torch.tensor([0x00400000, 1, 2], dtype=torch.int32))
    torch.set_flush_denormal(True)
    assert denormals.subnormals(layer) == (5, 9)
