"""Monte Carlo reference renderer for homogeneous translucent media (issue 8).

Random walks with exponential free flights, isotropic or Henyey-Greenstein scattering, a smooth dielectric
(Fresnel, total internal reflection) or index-matched boundary, unbiased Russian roulette, inside analytic shapes
or closed triangle meshes (own BVH), compiled with numba, seeded and thread-count independent.

- :func:`render` -- images (pinhole / orthographic cameras; point lights, environment maps, gradient patterns)
  with a per-pixel standard error.
- :func:`pencil_beam_profile` -- R(r) of a half-space or slab under a pencil beam (and total R_d, angular
  distribution), :func:`exchange_fraction` (reciprocity), :func:`energy_balance` (closed objects).

Modules: media, shapes, optics, rng, walk, nee, lights, cameras, render, profile. See each docstring for
the estimators and references (Wang, Jacques, Zheng 1995 MCML; van de Hulst 1980; Jensen et al. 2001;
d'Eon 2012; Pharr, Jakob, Humphreys PBR 3rd ed.).
"""
from ._cache import ensure_fresh_cache

ensure_fresh_cache()

from .cameras import OrthographicCamera  # noqa: E402
from .lights import GradientPattern, uniform_environment  # noqa: E402
from .media import Medium, optical_medium  # noqa: E402
from .profile import (DirectionSet, EnergyBalance, PencilBeamProfile, energy_balance, exchange_fraction,  # noqa: E402
                      pencil_beam_profile, simulate_photons)
from .render import MCImage, render  # noqa: E402
from .shapes import Box, HalfSpace, Mesh, Slab, Sphere  # noqa: E402

__all__ = ["Medium", "optical_medium", "HalfSpace", "Slab", "Sphere", "Box", "Mesh", "OrthographicCamera",
           "GradientPattern", "uniform_environment", "MCImage", "render", "DirectionSet", "PencilBeamProfile",
           "EnergyBalance", "pencil_beam_profile", "exchange_fraction", "energy_balance", "simulate_photons"]
