"""Sampling noise for the CEM family: colored (power-law) noise and truncated normals."""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr, ndtri


NOISE_RELEASES = ("1.1", "2.1")
"""Releases of the colorednoise package whose sampling :func:`colored_noise` follows (see its docstring)."""
DEFAULT_NOISE_RELEASE = "1.1"
"""The release the authors' public iCEM code ran, and with it the thesis's figures (README, "Choices")."""


def colored_noise(
    beta: float, shape: tuple[int, ...], rng: np.random.Generator, release: str = DEFAULT_NOISE_RELEASE
) -> np.ndarray:
    """Gaussian noise with power spectral density ~ 1/f^beta along the last axis.

    Thesis eq. 12-13, after Timmer & Koenig (1995): draw random Fourier
    coefficients whose amplitudes scale as f^(-beta/2) (the zero frequency gets
    the amplitude of the lowest non-zero one), transform back, and normalise
    to (nearly) unit variance as in the thesis's C^beta(d, h); see the note on
    the normalisation below. beta = 0 is white noise, 1 pink, 2 red (Brownian).

    Args:
        beta: spectral exponent, >= 0.
        shape: output shape; correlations run along the last axis (time).
        rng: random generator (the only source of randomness).
        release: which colorednoise release to follow. From 2.1.0 (June 2022) the
            real DC and Nyquist coefficients get twice the variance (below);
            "1.1" leaves them as drawn, as the releases up to 2.0 did, which the
            authors' public iCEM code (2020-21, colorednoise unpinned) ran with.
            At h = 30 and beta = 3, "2.1" gives each sequence's constant offset
            twice the variance (0.41 against 0.21) and the noise a variance of
            1.41 against 1.21.
    """
    if release not in NOISE_RELEASES:
        raise ValueError(f"colored-noise release must be one of {NOISE_RELEASES}, got {release!r}")
    if beta < 0:
        raise ValueError(f"colored-noise beta must be >= 0, got {beta}")
    length = shape[-1]
    if length < 2 or beta == 0:
        # beta = 0 is white noise (eq. 10-13, Fig. 4), and the authors' code drew it with a plain standard normal
        # rather than the package. Through the transform, release 1.1's undoubled DC and Nyquist terms would make
        # it anti-persistent: each sequence's constant offset at half the variance, a negative lag-2 covariance.
        return rng.standard_normal(shape)
    frequencies = np.fft.rfftfreq(length)
    frequencies[0] = frequencies[1]  # the DC term gets the lowest frequency's amplitude
    amplitudes = frequencies ** (-beta / 2.0)

    # Normalisation of Timmer & Koenig's algorithm as packaged in colorednoise
    # (every release): Parseval's sum over the
    # non-zero frequencies, the real Nyquist term counted at half weight. It
    # leaves out the DC term, so the variance is somewhat above 1 (h = 30: 1.06
    # at beta = 0.25, 1.16 at 1, 1.31 at 2, 1.41 at 3; for beta < 1 it tends to
    # 1 as the horizon grows; release "2.1"). We keep it to sample as the thesis's runs did.
    weights = amplitudes[1:].copy()
    if length % 2 == 0:
        weights[-1] /= 2.0
    sigma = 2.0 * np.sqrt(np.sum(weights**2)) / length

    coefficient_shape = (*shape[:-1], frequencies.size)
    real = rng.standard_normal(coefficient_shape) * amplitudes
    imaginary = rng.standard_normal(coefficient_shape) * amplitudes
    # A real signal needs real DC (and Nyquist) coefficients. colorednoise 2.1
    # doubles their variance so that every frequency carries its share of the
    # power; earlier releases did not.
    boost = np.sqrt(2.0) if release == "2.1" else 1.0
    imaginary[..., 0] = 0.0
    real[..., 0] *= boost
    if length % 2 == 0:
        imaginary[..., -1] = 0.0
        real[..., -1] *= boost
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
