"""Sampling noise for the CEM family: colored (power-law) noise and truncated normals."""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr, ndtri


def colored_noise(beta: float, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Gaussian noise with power spectral density ~ 1/f^beta along the last axis.

    Thesis eq. 12-13, after Timmer & Koenig (1995): draw random Fourier
    coefficients whose amplitudes scale as f^(-beta/2) (the zero frequency gets
    the amplitude of the lowest non-zero one), transform back, and divide by
    the exact theoretical standard deviation so that every entry has zero mean
    and unit variance, as the thesis defines C^beta(d, h). beta = 0 is white noise, 1 pink, 2 red (Brownian).

    Args:
        beta: spectral exponent, >= 0.
        shape: output shape; correlations run along the last axis (time).
        rng: random generator (the only source of randomness).
    """
    if beta < 0:
        raise ValueError(f"colored-noise beta must be >= 0, got {beta}")
    length = shape[-1]
    if beta == 0 or length < 2:
        return rng.standard_normal(shape)
    frequencies = np.fft.rfftfreq(length)
    frequencies[0] = frequencies[1]  # the DC term gets the lowest frequency's amplitude
    amplitudes = frequencies ** (-beta / 2.0)

    # Exact standard deviation of the resulting series: every frequency between
    # DC and Nyquist contributes 4 s_k^2 / n^2, the real-only DC (and Nyquist)
    # terms 2 s_k^2 / n^2. (colorednoise's normalisation leaves the DC term
    # out, which over h = 30 steps inflates the variance by 16% at beta = 1
    # and 42% at beta = 3; the thesis defines C^beta with unit variance.)
    weights = np.full(frequencies.size, 4.0)
    weights[0] = 2.0
    if length % 2 == 0:
        weights[-1] = 2.0
    sigma = np.sqrt(np.sum(weights * amplitudes**2)) / length

    coefficient_shape = (*shape[:-1], frequencies.size)
    real = rng.standard_normal(coefficient_shape) * amplitudes
    imaginary = rng.standard_normal(coefficient_shape) * amplitudes
    # A real signal needs real DC (and Nyquist) coefficients; their variance is
    # doubled so that every frequency carries its share of the power.
    imaginary[..., 0] = 0.0
    real[..., 0] *= np.sqrt(2.0)
    if length % 2 == 0:
        imaginary[..., -1] = 0.0
        real[..., -1] *= np.sqrt(2.0)
    return np.fft.irfft(real + 1j * imaginary, n=length, axis=-1) / sigma


def truncated_normal(
    mean: np.ndarray,
    std: np.ndarray,
    low: np.ndarray | float,
    high: np.ndarray | float,
    count: int,
    rng: np.random.Generator,
) -> np.ndarray:
    """``count`` samples of N(mean, std^2) truncated elementwise to [low, high].

    Inverse-CDF sampling: uniform draws between the CDF values of the bounds,
    mapped back through the normal quantile function. Vectorised over all
    elements; ``mean`` and ``std`` broadcast against each other.
    """
    std = np.maximum(std, 1e-8)  # a collapsed distribution still samples its mean
    lower = ndtr((low - mean) / std)
    upper = ndtr((high - mean) / std)
    uniform = rng.uniform(size=(count, *np.broadcast(mean, std).shape))
    samples = mean + std * ndtri(lower + uniform * (upper - lower))
    # Far in the tails the CDF saturates; clipping keeps such draws in bounds.
    return np.clip(samples, low, high)
