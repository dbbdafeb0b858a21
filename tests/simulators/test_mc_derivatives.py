"""The Monte Carlo renderer's parameter derivatives (``render(..., derivatives=True)``, perturbation Monte Carlo).

Oracle: central finite differences of whole renders at log sigma_s' +- h and log sigma_a +- h with the same seed
(common random numbers: the difference is much less noisy than either render), h = 0.05 (truncation error
~h^2/6 x the third derivative: < 0.1 % here). The score-function estimate and the difference quotient are
independent estimators of the same derivative; compared over the object's pixels summed, within 4 standard
errors of the score estimate plus 2 % for the difference quotient's own noise. Also checked: the derivatives
are 0 off the object, the default render carries none, and the radiance is unchanged by asking for them (the
derivative estimates draw no random numbers).

Measured (2000 spp, 12 x 12 px, skin1-R): box/point light/eta 1.3 -0.9 % (d log sigma_s') and +0.5 %
(d log sigma_a); box/environment/eta 1.0 +5.4 % (+-3.2 % standard error) and -0.6 %; sphere/point light/eta 1.3
+0.6 % and 0.0 %. Per-pixel relative standard error of d/d log sigma_s' ~17-27 % at 2000 spp (the score
N - sigma_s L has a spread ~sqrt(N)), of d/d log sigma_a ~3 %.
"""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from estimation.camera import PinholeCamera
from estimation.single_image import EnvironmentMap, PointLights
from simulators.mc import Box, Medium, Mesh, Sphere, render

SSP, SA = 0.74, 0.032  # skin1-R
SPP = 600
H = 0.05


def _camera() -> PinholeCamera:
    return PinholeCamera.looking_at(width_px=10, height_px=10, fx_px=10 * 450 / (1.9 * 20), position_mm=(250, -300, 220),
                                    target_mm=(0, 0, 0))


def _sky() -> EnvironmentMap:
    th = np.pi * (np.arange(16) + 0.5) / 16
    ph = 2 * np.pi * (np.arange(32) + 0.5) / 32
    t, p = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1)
    sun = np.array([0.6, -0.6, 0.55]) / np.linalg.norm([0.6, -0.6, 0.55])
    return EnvironmentMap(np.where(d[..., 2] > 0, 0.15, 0.03) + 1.5 * np.clip(d @ sun, 0, None) ** 3, max_size=16)


def _dented() -> trimesh.Trimesh:
    """A non-convex closed mesh (a bipyramid with its top pushed in): camera paths leave and re-enter it."""
    a, z0 = 10.0, -4.0
    v = np.array([[-a, -a, z0], [a, -a, z0], [a, a, z0], [-a, a, z0], [0, 0, z0 - 6.0], [0, 0, z0 - 22.0]])
    f = [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4], [1, 0, 5], [2, 1, 5], [3, 2, 5], [0, 3, 5]]
    return trimesh.Trimesh(v, np.array(f), process=False)


POINT = PointLights(np.array([[350.0, -600.0, 500.0]]), np.array([[1e6]]))
CASES = {
    "box-point-eta1.3": (lambda: Box((-10,) * 3, (10,) * 3), lambda: POINT, 1.3),
    "box-env-eta1.0": (lambda: Box((-10,) * 3, (10,) * 3), _sky, 1.0),
    "sphere-point-eta1.3": (lambda: Sphere((0, 0, 0), 10.0), lambda: POINT, 1.3),
    "dented-env-eta1.3": (lambda: Mesh(_dented()), _sky, 1.3),
    "dented-point-eta1.0": (lambda: Mesh(_dented()), lambda: POINT, 1.0),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_score_derivatives_match_finite_differences(name):
    make_shape, make_light, eta = CASES[name]
    shape, light, cam = make_shape(), make_light(), _camera()
    base = render(shape, [Medium.from_reduced(SSP, SA, eta=eta)], cam, light, spp=SPP, seed=5, derivatives=True)
    plain = render(shape, [Medium.from_reduced(SSP, SA, eta=eta)], cam, light, spp=SPP, seed=5)
    assert plain.d_log_sigma is None and plain.d_log_sigma_stderr is None
    np.testing.assert_array_equal(base.radiance, plain.radiance)
    m = base.mask
    assert m.sum() > 20 and np.all(base.d_log_sigma[~m] == 0)
    for j, (fs, fa) in enumerate(((np.exp(H), 1.0), (1.0, np.exp(H)))):
        up = render(shape, [Medium.from_reduced(SSP * fs, SA * fa, eta=eta)], cam, light, spp=SPP, seed=5)
        dn = render(shape, [Medium.from_reduced(SSP / fs, SA / fa, eta=eta)], cam, light, spp=SPP, seed=5)
        fd = float(((up.radiance - dn.radiance)[m, 0]).sum() / (2 * H))
        score = float(base.d_log_sigma[m, 0, j].sum())
        se = float(np.sqrt((base.d_log_sigma_stderr[m, 0, j] ** 2).sum()))
        assert abs(score - fd) <= 4 * se + 0.02 * abs(fd), (name, j, score, fd, se)
    # signs: more absorption darkens every pixel's sum; the radiance responds to both parameters
    assert base.d_log_sigma[m, 0, 1].sum() < 0
