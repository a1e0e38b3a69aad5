"""The numbers of the training objective and the learning-rate schedule, as pure functions (numpy).

Wan's flow-matching training schedule (the FlowMatchScheduler of Wan's and DiffSynth-Studio's
training code, with ``shift=5``, ``sigma_min=0``, ``extra_one_step=True``), for N = 1,000 training
timesteps:

    s_i     = 1 - i / N                      i = 0 .. N-1   (a uniform grid from 1 towards 0)
    sigma_i = shift * s_i / (1 + (shift - 1) * s_i)       (= 5 s / (1 + 4 s) for shift 5)
    t_i     = N * sigma_i                                  (the timestep the transformer sees)
    w_i     = N * b_i / sum_j b_j,   b_i = g(t_i) - min_j g(t_j),   g(t) = exp(-2 ((t - N/2) / N)^2)

so the weight is a Gaussian bump in t centred at N/2 = 500, shifted to zero at its lowest grid
point and normalised to mean 1 over the grid. One index i is drawn uniformly per local batch.
"""

from __future__ import annotations

import math

import numpy as np


def shifted_sigmas(num_train_timesteps: int = 1000, shift: float = 5.0) -> np.ndarray:
    """(N,) float64 sigma_i, decreasing from 1 (i = 0) to shift/N / (1 + (shift-1)/N) (i = N-1)."""
    s = 1.0 - np.arange(num_train_timesteps, dtype=np.float64) / num_train_timesteps
    return shift * s / (1.0 + (shift - 1.0) * s)


def training_timesteps(num_train_timesteps: int = 1000, shift: float = 5.0) -> np.ndarray:
    """(N,) float64 t_i = N sigma_i, in (0, N]."""
    return num_train_timesteps * shifted_sigmas(num_train_timesteps, shift)


def training_weights(num_train_timesteps: int = 1000, shift: float = 5.0) -> np.ndarray:
    """(N,) float64 w_i >= 0 with mean 1: the Gaussian bump exp(-2((t - N/2)/N)^2) over t_i, minus its
    minimum on the grid, normalised."""
    n = num_train_timesteps
    t = training_timesteps(n, shift)
    bump = np.exp(-2.0 * ((t - n / 2) / n) ** 2)
    bump = bump - bump.min()
    return bump * (n / bump.sum())


def lr_factor(update: int, warmup_steps: int, horizon_steps: int) -> float:
    """Multiplier of the base learning rate at schedule index ``update``: linear warm-up to 1 at index
    ``warmup_steps``, then a cosine to 0 at index ``horizon_steps`` (0 after). This is transformers'
    ``get_cosine_schedule_with_warmup``. Which index an optimizer update runs at is the trainer's
    ``schedule.first_step``: the release's update k runs at index k - 1 (its first at 0, so at lr 0),
    ``first_step: 1`` runs update k at index k."""
    if warmup_steps > 0 and update <= warmup_steps:
        return update / warmup_steps
    progress = min(1.0, (update - warmup_steps) / (horizon_steps - warmup_steps))
    return 0.5 * (1.0 + math.cos(math.pi * progress))
