"""The single-image method exactly as published, dense — a reference for benchmarks/single_image.py.

Mukaigawa, Suzuki, Yagi 2009, "Analysis of Subsurface Scattering under Generic Illumination" (seed 000),
Eq. 10-29, implemented literally and independently of :mod:`estimation.single_image` (only the dipole profile
of :mod:`estimation.dipole` and the Fresnel factor are shared):

- l_j = pi L_o(P_j) / F_t(eta, w_o) (Eq. 11) and c_k = E_t(P_k) A_k (Eq. 12, patch area folded in);
- the full distance matrix d_jk between the m_obs observed and all m patches, held densely (8 m_obs m bytes);
- every pair quantized with the linear-interpolation weights of Eq. 19-21 and summed into a dense
  W (m_obs x n) (Eq. 23-27; the self pair d = 0 lands on node 0: point-sampled, as published);
- r = pinv(W) l with :func:`numpy.linalg.pinv` (Eq. 28);
- the dipole fitted to all n values of r by unweighted least squares (Eq. 29), in (log sigma_s', log sigma_a)
  with the same bounds and starting grid as the estimator under test, so that only the construction of W
  and the solve differ.

The quantization and the sum into W run over row blocks of the dense distance matrix (the temporaries of one
block stay below ~100 MB); the distance matrix itself is dense, so memory and time are O(m_obs m).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize
from scipy.spatial.distance import cdist

from estimation.dipole import dipole_coefficients, profile_from_coefficients
from estimation.fresnel import fresnel_transmittance

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DenseResult:
    """Parameters (one channel), the binned profile r = pinv(W) l and the cost of the literal solve."""

    sigma_s_prime_per_mm: float
    sigma_a_per_mm: float
    profile_values: Array
    seconds: float
    distance_matrix_bytes: int


def distance_matrix_bytes(n_observed: int, n_patches: int) -> int:
    """Memory of the dense distance matrix (float64) of the literal method."""
    return 8 * int(n_observed) * int(n_patches)


def literal_dense_pinv(observed_radiance: ArrayLike, centers_mm: ArrayLike, areas_mm2: ArrayLike,
                       cos_out: ArrayLike, visible: ArrayLike, irradiance: ArrayLike, eta: float,
                       bins_mm: ArrayLike, *, sigma_a_floor_per_mm: float = 1e-7) -> DenseResult:
    """Eq. 10-29 on one channel: dense d_jk, dense W, ``numpy.linalg.pinv``, Eq. 29 fit.

    ``observed_radiance`` (m_obs,) of the visible patches in index order, ``irradiance`` E_t (m,) of all
    patches, ``bins_mm`` the quantized distances d'_1 = 0 < ... < d'_n (Eq. 17-18; pass the estimator's bins
    to compare on the same quantization).
    """
    t0 = time.perf_counter()
    x = np.asarray(centers_mm, dtype=np.float64).reshape(-1, 3)
    vis = np.flatnonzero(np.asarray(visible, dtype=bool))
    ft = fresnel_transmittance(float(eta), np.asarray(cos_out, dtype=np.float64)[vis])
    l_vec = np.pi * np.asarray(observed_radiance, dtype=np.float64).reshape(-1) / ft  # Eq. 11
    c = np.asarray(irradiance, dtype=np.float64).reshape(-1) * np.asarray(areas_mm2, dtype=np.float64)  # Eq. 12
    nodes = np.asarray(bins_mm, dtype=np.float64)
    n = nodes.size
    d = cdist(x[vis], x)  # the dense m_obs x m distance matrix
    w_mat = np.zeros((vis.size, n))
    block = max(1, 2_000_000 // max(x.shape[0], 1))
    for s in range(0, vis.size, block):
        db = d[s:s + block]
        i = np.clip(np.searchsorted(nodes, db, side="right") - 1, 0, n - 2)  # Eq. 19
        beta = np.clip((nodes[i + 1] - db) / (nodes[i + 1] - nodes[i]), 0.0, 1.0)  # Eq. 21
        rows = (np.arange(db.shape[0])[:, None] * n + i).ravel()
        acc = np.bincount(rows, (beta * c).ravel(), minlength=db.shape[0] * n)  # Eq. 26-27: sum_k c_k w_jk
        acc += np.bincount(rows + 1, ((1.0 - beta) * c).ravel(), minlength=db.shape[0] * n)
        w_mat[s:s + block] = acc.reshape(db.shape[0], n)
    r = np.linalg.pinv(w_mat) @ l_vec  # Eq. 28
    ssp, sa = _fit_eq29(r, nodes, float(eta), sigma_a_floor_per_mm)
    return DenseResult(ssp, sa, r, time.perf_counter() - t0, distance_matrix_bytes(vis.size, x.shape[0]))


def _fit_eq29(r: Array, nodes: Array, eta: float, sa_floor: float) -> tuple[float, float]:
    """argmin sum_i (R'_i - R(d'_i))^2 (Eq. 29) in log parameters: 21 x 21 grid start, bounded least squares
    from it and from sigma_a x e^(+-2) (the estimator's starting rule)."""
    lb = np.array([np.log(1e-3), np.log(sa_floor)])
    ub = np.array([np.log(1e3), np.log(50.0)])

    def model(theta: Array) -> Array:  # (T, 2) -> (n, T)
        co = dipole_coefficients(np.exp(theta[:, 0])[:, None], np.exp(theta[:, 1])[:, None], eta)
        return profile_from_coefficients(co, nodes[None, :]).T

    g_s = np.linspace(np.log(0.01), np.log(100.0), 21)
    g_a = np.linspace(max(np.log(1e-6), lb[1]), np.log(10.0), 21)
    grid = np.array(np.meshgrid(g_s, g_a, indexing="ij")).reshape(2, -1).T
    ssr = np.sum((model(grid) - r[:, None]) ** 2, axis=0)
    x0 = grid[int(np.nanargmin(ssr))]
    best = None
    for start in (x0, np.clip(x0 + [0.0, 2.0], lb, ub), np.clip(x0 - [0.0, 2.0], lb, ub)):
        res = optimize.least_squares(lambda t: model(t[None, :])[:, 0] - r, start, bounds=(lb, ub), method="trf",
                                     xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=400)
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None
    return float(np.exp(best.x[0])), float(np.exp(best.x[1]))
