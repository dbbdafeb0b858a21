"""Counter-based random numbers for the numba kernels: SplitMix64 streams keyed by (seed, a, b, c).

Every random walk owns one stream whose start state is a hash of the run's seed and the walk's coordinates
(channel, pixel, sample) or (photon index), so results do not depend on the number of threads or on the order in
which threads pick up work. The generator is SplitMix64 (Steele, Lea, Flood 2014, "Fast splittable pseudorandom
number generators", OOPSLA; passes BigCrush), whose finalizer is also used as the key hash.
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["mix64", "stream", "uniform"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV53 = 1.0 / 9007199254740992.0


@njit(cache=True, inline="always")
def mix64(z):
    """SplitMix64 finalizer (a bijective 64-bit hash)."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True)
def stream(seed, a, b, c):
    """Start state of the stream keyed by (seed, a, b, c) (all non-negative integers)."""
    s = mix64(np.uint64(seed) + _GOLDEN)
    s = mix64(s ^ (np.uint64(a) + _GOLDEN))
    s = mix64(s ^ (np.uint64(b) * _M1 + _GOLDEN))
    s = mix64(s ^ (np.uint64(c) * _M2 + _GOLDEN))
    return s


@njit(cache=True, inline="always")
def uniform(state):
    """Advance ``state`` and return (new_state, u) with u uniform in the open interval (0, 1)."""
    state = state + _GOLDEN
    z = mix64(state)
    return state, (float(z >> _S11) + 0.5) * _INV53
