"""Coloured exploration noise: unit-variance Gaussian draws correlated in time, with a power
spectrum 1/f^β (Eberhard et al. 2023, "Pink noise is all you need"), for a collecting policy to
use in place of independent (white) draws."""

from __future__ import annotations

import math

import torch


def powerlaw_noise(
    beta: float, shape: tuple[int, ...], steps: int, device: torch.device | str = "cpu"
) -> torch.Tensor:
    """``shape + (steps,)`` Gaussian sequences with power spectrum ∝ 1/f^β along the last
    axis, each of unit variance about its own mean (in expectation): β = 0 white, 1 pink,
    2 red (Brownian, the limit of Ornstein-Uhlenbeck noise). Timmer and König's method (as
    the ``colorednoise`` package): Gaussian Fourier coefficients scaled by f^(-β/2), the
    lowest frequency 1/steps."""
    freqs = torch.fft.rfftfreq(steps, device=device)
    freqs[0] = 1 / steps
    scale = freqs.pow(-beta / 2)
    weights = scale[1:].clone()
    weights[-1] *= (1 + steps % 2) / 2
    sigma = 2 * weights.square().sum().sqrt() / steps  # the signal's expected std
    real = torch.randn(*shape, len(freqs), device=device) * scale
    imag = torch.randn(*shape, len(freqs), device=device) * scale
    imag[..., 0] = 0  # the mean's coefficient is real
    real[..., 0] *= math.sqrt(2)
    if steps % 2 == 0:  # so is the Nyquist frequency's
        imag[..., -1] = 0
        real[..., -1] *= math.sqrt(2)
    return torch.fft.irfft(torch.complex(real, imag), n=steps) / sigma


class ColoredNoise:
    """Standard-normal draws of ``shape`` (e.g. ``(env copies, action dims)``), each entry a
    1/f^β sequence in time: one call, the next step's draws; a fresh sequence of ``steps``
    draws per entry once the last one is used up."""

    def __init__(
        self, beta: float, shape: tuple[int, ...], steps: int, device: torch.device | str = "cpu"
    ) -> None:
        self.beta, self.shape, self.steps, self.device = beta, tuple(shape), steps, device
        self._sequence = torch.empty(0)
        self._next = steps

    def __call__(self) -> torch.Tensor:
        if self._next == self.steps:
            noise = powerlaw_noise(self.beta, self.shape, self.steps, self.device)
            self._sequence, self._next = noise.movedim(-1, 0).contiguous(), 0
        draw = self._sequence[self._next]
        self._next += 1
        return draw
