"""Fine relief: the local spectral ratio of the diffuse against the specular normal map (:func:`relief_mtf`) and the
one-length fit of the dipole's MTF to it (:func:`fit_relief`) (``estimation.diffusion``).
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import optimize

from ..dipole import hankel_transform, reduced_albedo_from_total_reflectance
from .models import Array


# --------------------------------------------------------------------------------------------------------------
# fine relief: local spectral ratio (diffuse vs specular normal maps)
# --------------------------------------------------------------------------------------------------------------
def _tangent_components(true_normals: Array) -> NDArray[np.intp]:
    """Indices of the two rig-frame components that carry the relief (largest variance of the true normals)."""
    return np.argsort(true_normals.reshape(-1, 3).var(axis=0))[-2:]


def _window(h: int, w: int, window: str) -> Array:
    if window == "hann":
        return np.outer(np.hanning(h), np.hanning(w))
    if window == "none":
        return np.ones((h, w))
    raise ValueError(f"unknown window {window!r}; valid: hann, none")


def _unit_diffuse(Dn: Array, c: int) -> Array:
    return Dn[..., c, :] / np.linalg.norm(Dn[..., c, :], axis=-1, keepdims=True)


def relief_mtf(diffuse_normals: ArrayLike, true_normals: ArrayLike, pixel_mm: float, *, n_bins: int | None = None,
               window: str = "hann") -> tuple[Array, Array, Array]:
    """Diagnostic estimate of the blur's modulation transfer M(k) = R^(k)/R^(0) from one window of normal maps.

    ``diffuse_normals`` (h, w, 3 channels, 3) and ``true_normals`` (h, w, 3) (specular normals) over a small,
    fully valid window of roughly flat-on-average relief, pixel size ``pixel_mm`` on the surface. The two
    tangential components (largest variance) of both maps are windowed and Fourier transformed;
    M(k) = Re<D T*> / <|T|^2> per annulus (a cross-spectral estimate, unbiased under noise in D). Annuli are one
    fundamental frequency 2 pi/(N pixel_mm) wide up to Nyquist unless ``n_bins`` is given. Returns
    (k [rad/mm] (n_bins,), M (n_bins, 3), weight (n_bins,) = summed |T|^2). Window leakage averages M over ~2
    bins, so use windows much wider than l' (>= 8 l'); :func:`fit_relief` has no such bias.
    """
    Dn = np.asarray(diffuse_normals, dtype=np.float64)
    Tn = np.asarray(true_normals, dtype=np.float64)
    h, w = Tn.shape[:2]
    if Dn.shape != (h, w, 3, 3):
        raise ValueError("diffuse_normals must be (h, w, 3, 3) matching true_normals (h, w, 3)")
    if not (np.isfinite(Dn).all() and np.isfinite(Tn).all()):
        raise ValueError("the window must be fully valid (no NaN)")
    win = _window(h, w, window)
    ky = 2 * np.pi * np.fft.fftfreq(h, d=pixel_mm)
    kx = 2 * np.pi * np.fft.fftfreq(w, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    nb = int(n_bins) if n_bins is not None else min(h, w) // 2
    edges = np.linspace(0.0, np.pi / pixel_mm, nb + 1)
    edges[0] = 0.5 * (edges[1] - edges[0])  # drop the DC term
    centres = 0.5 * (edges[1:] + edges[:-1])
    num = np.zeros((nb, 3))
    den = np.zeros(nb)
    b = np.digitize(kk.ravel(), edges) - 1
    valid = (b >= 0) & (b < nb)
    for comp in _tangent_components(Tn):
        t = Tn[..., comp] - Tn[..., comp].mean()
        Tf = np.fft.fft2(t * win)
        p = (np.abs(Tf) ** 2).ravel()
        den += np.bincount(b[valid], weights=p[valid], minlength=nb)[:nb]
        for c in range(3):
            d = _unit_diffuse(Dn, c)[..., comp]
            Df = np.fft.fft2((d - d.mean()) * win)
            cr = np.real(Df * np.conj(Tf)).ravel()
            num[:, c] += np.bincount(b[valid], weights=cr[valid], minlength=nb)[:nb]
    with np.errstate(invalid="ignore", divide="ignore"):
        M = np.where(den[:, None] > 0, num / den[:, None], np.nan)
    return centres, M, den


def fit_relief(diffuse_normals: ArrayLike, true_normals: ArrayLike, pixel_mm: float, albedo: ArrayLike,
               eta: float, *, margin_px: int | None = None, window: str = "hann", fdr: str = "fit",
               l_bounds_mm: tuple[float, float] = (1e-3, 1e2)) -> Array:
    """l' [mm] per channel from fine relief: the diffuse normal map is the true one filtered by M(k).

    For each channel, alpha' comes from ``albedo`` (3,) (inversion of R_d, eta fixed); then the one length l'
    minimizes || w * (d_t - M_l' (x) n_t) ||^2 over the two tangential components, where (x) filters the
    (reflect-padded) true normal map by the Jensen MTF R^(k)/R^(0) in the Fourier domain and w is the window
    restricted to pixels at least ``margin_px`` (default a quarter of the window) from the edge: a diffuse
    normal depends on the relief within a few l_d = 1/sigma_tr around it, which the map must contain. Because the
    model is windowed exactly like the data, window leakage does not bias it (unlike the binned ratio of
    :func:`relief_mtf`); by Parseval this is the spectral-ratio fit weighted by the relief power. Requirements:
    pixel << l', and margin >~ 2 l_d. Bounded scalar minimization in log l'; NaN where the albedo is not usable.
    """
    Dn = np.asarray(diffuse_normals, dtype=np.float64)
    Tn = np.asarray(true_normals, dtype=np.float64)
    h, w = Tn.shape[:2]
    if Dn.shape != (h, w, 3, 3) or not (np.isfinite(Dn).all() and np.isfinite(Tn).all()):
        raise ValueError("need finite diffuse_normals (h, w, 3, 3) and true_normals (h, w, 3)")
    alb = np.broadcast_to(np.asarray(albedo, dtype=np.float64).reshape(-1), (3,))
    m = min(h, w) // 4 if margin_px is None else int(margin_px)
    if not 0 <= 2 * m < min(h, w) - 2:
        raise ValueError("margin_px leaves no pixels")
    win = np.zeros((h, w))
    win[m:h - m, m:w - m] = _window(h - 2 * m, w - 2 * m, window)
    ph, pw = h // 2, w // 2
    comps = _tangent_components(Tn)
    padded = [np.pad(Tn[..., c] - Tn[..., c].mean(), ((ph, ph), (pw, pw)), mode="reflect") for c in comps]
    H2, W2 = padded[0].shape
    ky = 2 * np.pi * np.fft.fftfreq(H2, d=pixel_mm)
    kx = 2 * np.pi * np.fft.fftfreq(W2, d=pixel_mm)
    kk = np.sqrt(ky[:, None] ** 2 + kx[None, :] ** 2)
    spectra = [np.fft.fft2(p) for p in padded]
    out = np.full(3, np.nan)
    for c in range(3):
        if not np.isfinite(alb[c]) or alb[c] <= 0:
            continue
        al = float(reduced_albedo_from_total_reflectance(min(alb[c], 1.0), eta, fdr=fdr))
        d = _unit_diffuse(Dn, c)
        data = [(d[..., comp] - d[..., comp].mean()) for comp in comps]

        def cost(lnl: float) -> float:
            st = float(np.exp(-lnl))
            M = hankel_transform(kk, al * st, (1.0 - al) * st, eta, fdr=fdr)
            M = M / hankel_transform(0.0, al * st, (1.0 - al) * st, eta, fdr=fdr)
            tot = 0.0
            for spec, dat in zip(spectra, data):
                pred = np.real(np.fft.ifft2(M * spec))[ph:ph + h, pw:pw + w]
                pred = pred - pred.mean()
                tot += float(np.sum((win * (dat - pred)) ** 2))
            return tot

        res = optimize.minimize_scalar(cost, bounds=(np.log(l_bounds_mm[0]), np.log(l_bounds_mm[1])),
                                       method="bounded", options={"xatol": 1e-5})
        out[c] = float(np.exp(res.x))
    return out
