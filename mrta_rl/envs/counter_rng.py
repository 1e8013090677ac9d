"""Counter-based random draws of the auction env: every number is a hash of its coordinates.

A draw is a hash of (copy seed, episode number, tick, draw index) (splitmix64 finaliser), never
the next value of a shared generator. A copy's episode therefore depends only on its own seed and
actions, not on the batch size or on when other copies reset, and any implementation that draws
the same hashes reproduces it exactly (``mrta_rl/envs/reference.py`` does).
uint64 arithmetic wraps by design. The hash primitives are compiled with numba and generic: the
compiled kernel (``envs/kernel.py``) calls them on scalars, the functions below on arrays, so each
formula is written once.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_M1, _M2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S30, _S27, _S31, _S11, _S32 = (np.uint64(s) for s in (30, 27, 31, 11, 32))
_LO32 = np.uint64(0xFFFFFFFF)
_UNIT = 1.0 / (1 << 53)


@njit(cache=True)
def mix64(x):
    """Splitmix64 finaliser: a bijective avalanche hash of uint64 values."""
    x = x ^ (x >> _S30)
    x = x * _M1
    x = x ^ (x >> _S27)
    x = x * _M2
    return x ^ (x >> _S31)


@njit(cache=True)
def unit_float(h):
    """Uniform float64 in [0, 1) from the top 53 bits of a hash (exact: fewer than 54 bits)."""
    return (h >> _S11) * _UNIT


@njit(cache=True)
def bounded_uint(h, n):
    """Integer in [0, n) from the low 32 bits of a hash (Lemire multiply-shift; bias < n/2**32).

    Both arguments are uint64 (scalars or arrays); the result is uint64.
    """
    return ((h & _LO32) * n) >> _S32


def bounded_int(h: np.ndarray, n: np.ndarray | int) -> np.ndarray:
    """:func:`bounded_uint` of arrays, as int64."""
    h, n = np.asarray(h, dtype=np.uint64), np.asarray(n, dtype=np.uint64)
    return np.asarray(bounded_uint(h, n), dtype=np.uint64).astype(np.int64)


@njit(cache=True)
def high_bits(h):
    """The high 32 bits of a hash, as the low bits of a new uint64 (for a second bounded_int)."""
    return h >> _S32


def seed_keys(seeds: np.ndarray) -> np.ndarray:
    """Per-copy keys ``[B]`` uint64 from integer seeds."""
    return mix64(np.asarray(seeds, dtype=np.int64).astype(np.uint64) + _GOLDEN)


@njit(cache=True)
def episode_key(seed_key, episode):
    """Key of a copy's ``episode``-th episode (uint64 scalars or arrays); :func:`episode_keys`."""
    return mix64(seed_key ^ mix64(episode + _GOLDEN) ^ (episode * _M2))


@njit(cache=True)
def tick_key(key, tick):
    """Key of tick ``tick`` of the episode with key ``key`` (uint64 scalars or arrays)."""
    return mix64(key ^ (tick * _GOLDEN))


@njit(cache=True)
def task_hash_pair(key, k):
    """The two hashes of the ``k``-th new task of a tick (``k`` from 1, uint64).

    The first draws the priority, the second type and duration.
    """
    h_priority = mix64(key + k * _GOLDEN)
    return h_priority, mix64(h_priority ^ _M2)


def episode_keys(seed_key: np.ndarray, episode: np.ndarray) -> np.ndarray:
    """Keys of each copy's ``episode``-th episode (0-based).

    ``mix64(s + G) ^ mix64(e + G)`` alone is symmetric in the copy seed ``s`` and the episode
    ``e`` (copy ``b``'s episode ``e`` would draw copy ``e``'s episode ``b``), so the episode also
    enters once more as ``e * _M2``. That term is 0 for episode 0, whose streams (the evaluation
    episodes) are therefore those of the symmetric mix.
    """
    return episode_key(np.asarray(seed_key, np.uint64), np.asarray(episode, dtype=np.uint64))


def tick_keys(episode_key: np.ndarray, tick: np.ndarray) -> np.ndarray:
    """Keys of a tick; the tick's arrival count is drawn from ``unit_float`` of this key."""
    return tick_key(episode_key, np.asarray(tick, dtype=np.int64).astype(np.uint64))


def task_hashes(tick_key: np.ndarray, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Two hashes per new task ``[B, width]``: one for the priority, one for type and duration."""
    k = np.arange(1, width + 1, dtype=np.uint64)
    return task_hash_pair(tick_key[:, None], k[None, :])


def poisson_cdf(rate: float) -> np.ndarray:
    """CDF table ``P(N <= k)`` of Poisson(rate), long enough that the tail is below 1e-30.

    The arrival count of a tick is ``searchsorted(cdf, u, side="right")`` for a uniform ``u``.
    """
    k_max = int(math.ceil(rate + 14.0 * math.sqrt(rate) + 30))
    if rate > 0:
        log_p = np.array([k * math.log(rate) - rate - math.lgamma(k + 1) for k in range(k_max + 1)])
    else:
        log_p = np.array([0.0] + [-np.inf] * k_max)
    cdf = np.cumsum(np.exp(log_p))
    cdf[-1] = 1.0 + 1e-9  # the tail beyond k_max (< 1e-30) is folded into the last count
    return cdf
