"""Start of the sphere reference loop where the fast model has none: a coarse scan of reference renders.

:func:`estimation.gradient_correction.estimate_sphere_with_reference` starts from the exact inversion of the
truncated half-space Jensen dipole on the sphere and corrects its defect render by render. That start exists only
while the sphere is a diffuser. A sphere whose transport mean free path l' is of the order of its radius is
partly a *ball lens*: light that enters on the lit side crosses the body and leaves on the far side, so the
diffuse normals of the gradient method point away from the light and the median shortening S = v.n / (tau1/tau0)
is near zero or negative. Measured: ketchup red on a 5 mm sphere (sigma_s' 0.18 /mm, sigma_a 0.061 /mm, eta 1.3:
radius x sigma_t' = 1.2) observes S = -0.23, and the Monte Carlo reference at the truth reproduces it (A 0.57,
S -0.24 against the frame's 0.566, -0.232); the dipole's inversion has no solution there and returns sigma_s'
0.002 /mm (1 % of the truth), from which the defect correction climbs one trust radius (a factor e) per render
and ends at -50 % (4 renders) or -80 % (8 renders) in D.

For such channels (observed S below :data:`SCAN_SHORTENING_MAX`) the loop starts from a scan instead
(analysis by synthesis with a coarse dictionary, as Gkioulekas et al. 2013 start their inverse volume rendering
from the best entry of a material dictionary): the reference is rendered on a 3 x 3 grid of optical radius
tau = radius x sigma_t' (:data:`SCAN_OPTICAL_RADIUS`) and albedo alpha' (:data:`SCAN_ALBEDO`) — one render per grid
point serves every scanned channel at once, the other channels sit at their own start — and each channel takes
the grid point nearest to its observables in their noise (chi^2 of (log A, log b)), then a local linear model of
the renders around it (least squares over that point and its grid neighbours) gives the start x* and the
reference's own Jacobian J_ref there (the loop's defect Jacobian starts as K = J_ref - J_fast instead of 0). The
step from the grid point is clipped to one grid spacing. Cost: 9 renders, cheap in this regime (short paths at
low optical radius: ~2-4 s at 64 spp on the acceptance's 32 px sphere).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["SCAN_SHORTENING_MAX", "SCAN_OPTICAL_RADIUS", "SCAN_ALBEDO", "SphereScan", "needs_scan", "scan_start"]

#: a channel whose observed median shortening is below this is outside the dipole's range (a lens-like sphere)
SCAN_SHORTENING_MAX = 0.1
#: grid of the scan: radius x sigma_t' (optical radius) and reduced albedo alpha'
SCAN_OPTICAL_RADIUS = (0.4, 1.2, 3.6)
SCAN_ALBEDO = (0.6, 0.85, 0.96)


@dataclass(frozen=True)
class SphereScan:
    """The scan's outcome per channel: ``x_start`` (C, 2) log (sigma_s', sigma_a) (the caller's start where not
    scanned), ``J_ref`` (C, 2, 2) the renders' local Jacobian d(log A, log b)/d x (NaN where not scanned or not
    determined), ``chi2_best`` (C,) the best grid point's chi^2, ``scanned`` (C,) bool, ``renders``,
    ``seconds``."""

    x_start: Array
    J_ref: Array
    chi2_best: Array
    scanned: NDArray[np.bool_]
    renders: int
    seconds: float

    def as_dict(self) -> dict[str, Any]:
        p = np.exp(self.x_start)
        return {"scanned": self.scanned.tolist(), "renders": self.renders, "seconds": self.seconds,
                "start_sigma_s_prime_per_mm": np.where(self.scanned, p[:, 0], np.nan).tolist(),
                "start_sigma_a_per_mm": np.where(self.scanned, p[:, 1], np.nan).tolist(),
                "chi2_best": self.chi2_best.tolist(),
                "grid": {"optical_radius": list(SCAN_OPTICAL_RADIUS), "alpha_prime": list(SCAN_ALBEDO)}}


def needs_scan(shortening: Array, usable: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """(C,) channels whose observed shortening is below :data:`SCAN_SHORTENING_MAX` (usable ones only)."""
    s = np.asarray(shortening, dtype=np.float64)
    return np.asarray(usable, dtype=bool) & np.isfinite(s) & (s < SCAN_SHORTENING_MAX)


def _grid_log_params(radius_mm: float) -> Array:
    """(9, 2) log (sigma_s', sigma_a) of the grid, row-major over (optical radius, albedo)."""
    out = []
    for tau in SCAN_OPTICAL_RADIUS:
        st = tau / radius_mm
        for a in SCAN_ALBEDO:
            out.append((np.log(a * st), np.log((1.0 - a) * st)))
    return np.asarray(out, dtype=np.float64)


def scan_start(u_obs: Array, sd_obs: Array, render: Callable[[Array], tuple[Array, Array]], x_default: Array,
               scan: NDArray[np.bool_], radius_mm: float) -> SphereScan:
    """Scan the grid for the channels in ``scan``. ``u_obs`` (C, 2) observed (log A, log b), ``sd_obs`` their
    standard deviations; ``render(x (C, 2)) -> (u_ref (C, 2), sd_ref (C, 2))`` one reference render at log
    parameters x; ``x_default`` (C, 2): where the other channels are rendered (and the start they keep)."""
    t0 = time.perf_counter()
    grid = _grid_log_params(float(radius_mm))
    n_g, n_ch = len(grid), u_obs.shape[0]
    U = np.full((n_g, n_ch, 2), np.nan)
    S = np.zeros((n_g, n_ch, 2))
    for g in range(n_g):
        x = np.where(scan[:, None], grid[g][None, :], x_default)
        U[g], S[g] = render(x)
    sd = np.hypot(sd_obs[None], S)
    sd = np.where(sd > 0, sd, 1e-3)
    with np.errstate(invalid="ignore"):
        chi2 = np.sum(((U - u_obs[None]) / sd) ** 2, axis=2)          # (G, C)
    chi2 = np.where(np.isfinite(chi2), chi2, np.inf)
    x_start = x_default.copy()
    J_ref = np.full((n_ch, 2, 2), np.nan)
    best_chi2 = np.full(n_ch, np.nan)
    n_a = len(SCAN_ALBEDO)
    spacing = np.abs(np.array([grid[n_a, 0] - grid[0, 0], grid[1, 1] - grid[0, 1]]))
    for c in np.flatnonzero(scan):
        b = int(np.argmin(chi2[:, c]))
        if not np.isfinite(chi2[b, c]):
            continue
        best_chi2[c] = chi2[b, c]
        i, j = divmod(b, n_a)
        nb = [b] + [ii * n_a + jj for ii, jj in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1))
                    if 0 <= ii < len(SCAN_OPTICAL_RADIUS) and 0 <= jj < n_a]
        nb = [g for g in nb if np.all(np.isfinite(U[g, c]))]
        x_c = grid[b].copy()
        if len(nb) >= 3:
            A = np.c_[np.ones(len(nb)), grid[nb] - grid[b]]
            coef, *_ = np.linalg.lstsq(A, U[nb, c], rcond=None)       # (3, 2): u ~ u0 + J^T dx
            J = coef[1:].T                                            # (2 outputs, 2 params)
            if np.all(np.isfinite(J)) and abs(np.linalg.det(J)) > 1e-6:
                dx = np.linalg.solve(J, u_obs[c] - coef[0])
                x_c = grid[b] + np.clip(dx, -spacing, spacing)
                J_ref[c] = J
        x_start[c] = x_c
    return SphereScan(x_start, J_ref, best_chi2, np.asarray(scan, dtype=bool).copy(), n_g,
                      time.perf_counter() - t0)
