"""The psychometric functions of the threshold procedures and the simulated observers, chosen by
name (questplus' habit: `func="weibull"`), and the QUEST+ stimulus rule they share.

Intensities x and thresholds t are in dB re 1 µm peak displacement. Every function gives
P(correct) of an n-AFC trial with guess rate γ = 1/n and lapse rate δ, and its threshold t is the
same quantity: the level detected with probability 1 - 1/e beyond guessing, so
(P(t) - γ) / (1 - γ - δ) = 1 - 1/e for either function and any n.

- weibull: P = 1 - δ - (1 - γ - δ) exp(-10^(β (x - t) / 20)), β the shape (questplus' Weibull on
  the dB scale, `stim_scale="dB"`);
- logistic: P = γ + (1 - γ - δ) / (1 + exp(-(x - m) / s)), s the spread in dB and
  m = t - s ln(e - 1) (its midpoint), so that t is defined as the Weibull's.

The arguments broadcast (numpy arrays), float64.
"""

from __future__ import annotations

import math

import numpy as np

LN_E_MINUS_1 = math.log(math.e - 1.0)


def weibull(x_db, threshold_db, slope, guess, lapse):
    z = np.power(10.0, slope * (np.asarray(x_db, dtype=np.float64) - threshold_db) / 20.0)
    return 1.0 - lapse - (1.0 - guess - lapse) * np.exp(-z)


def logistic(x_db, threshold_db, slope, guess, lapse):
    """`slope` is the spread s in dB (the logistic's scale), not a Weibull shape."""
    m = threshold_db - slope * LN_E_MINUS_1
    return guess + (1.0 - guess - lapse) / (1.0 + np.exp(-(np.asarray(x_db, dtype=np.float64) - m) / slope))


FUNCTIONS = {"weibull": weibull, "logistic": logistic}


def p_correct(func: str, x_db, threshold_db, slope, guess, lapse):
    """P(correct) of the psychometric function named `func` (FUNCTIONS)."""
    try:
        f = FUNCTIONS[func]
    except KeyError:
        raise ValueError(f"psychometric function {func!r}: one of {', '.join(FUNCTIONS)}") from None
    return f(x_db, threshold_db, slope, guess, lapse)


TINY = 1e-300  # below this a probability is 0: subnormal numbers make matrix products ~10x slower
TINY_ENTROPY = 1e-200  # and an entropy (so that posterior x entropy stays far from subnormal)


def flush(p: np.ndarray, tiny: float = TINY) -> np.ndarray:
    """p with the values below `tiny` set to 0, in place."""
    p[p < tiny] = 0.0
    return p


def central_interval(mass: np.ndarray, points: np.ndarray, step: float, level: float = 0.95) -> np.ndarray:
    """The central `level` of the masses `mass` (runs, n) on the regular grid `points` (n,), `step`
    apart, (runs, 2): each point's mass spread evenly over its cell, so the cumulative mass at a
    cell's upper edge is the sum up to its point (taking it at the point itself put both ends half
    a step low)."""
    m = np.atleast_2d(mass)
    edges = np.append(points - step / 2, points[-1] + step / 2)
    c = np.cumsum(m, axis=-1) / m.sum(axis=-1, keepdims=True)
    c = np.concatenate([np.zeros((c.shape[0], 1)), c], axis=-1)
    q = ((1 - level) / 2, (1 + level) / 2)
    return np.array([np.interp(q, ci, edges) for ci in c]).reshape(-1, 2)


def binary_entropy(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, TINY, 1.0)
    q = np.clip(1.0 - p, TINY, 1.0)
    return flush(-(p * np.log(p) + q * np.log(q)), TINY_ENTROPY)


def information(post: np.ndarray, p_correct_table: np.ndarray) -> np.ndarray:
    """The QUEST+ rule's criterion: per stimulus, the expected reduction of the entropy of the
    parameters of interest by the trial's answer (their mutual information with it), the
    nuisance parameters marginalised. The next stimulus is the one of most information, i.e. of
    least expected posterior entropy of the parameters of interest (Watson 2017).

    post: (..., n_interest, n_nuisance), a normalised posterior (a batch of runs in front);
    p_correct_table: (n_stim, n_interest, n_nuisance). Returns (..., n_stim):
    I = h(Σ_T P̄_T) - Σ_T p_T h(P̄_T / p_T), with p_T the interest's marginal, P̄_T = Σ_k post_Tk P_sTk
    and h the binary entropy."""
    pbar = np.einsum("stk,...tk->...st", p_correct_table, post)
    p_t = post.sum(axis=-1)[..., None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        cond = np.where(p_t > 0, pbar / p_t, 0.5)
    return binary_entropy(pbar.sum(axis=-1)) - np.sum(p_t * binary_entropy(cond), axis=-1)


def information_flat(post: np.ndarray, p_correct_table: np.ndarray, entropy_table: np.ndarray) -> np.ndarray:
    """information() when every parameter is of interest (no nuisance): post (..., n_theta),
    p_correct_table (n_theta, n_stim) and its binary entropy (precomputed, the same shape);
    h(post P) - post h(P), two matrix products (the joint procedure's grid is too large for the
    general form)."""
    return binary_entropy(post @ p_correct_table) - post @ entropy_table
