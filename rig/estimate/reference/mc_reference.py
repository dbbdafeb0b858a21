"""A Monte Carlo reference renderer for :func:`estimation.model_correction.estimate_with_reference`.

It simulates the measurement: the Monte Carlo renderer (:func:`simulators.mc.render`) draws the object in its
known geometry, seen by the capture's camera under the capture's lights, and the image is sampled at the patch
centres exactly as the observations were (:func:`rig.estimate.pixel_map.sample_at_points`: a 3 x 3 window mean and its
standard error, NaN where a window pixel is off the object or outside ``valid_px``). Sampling effects (windows
that straddle an edge, pixel footprints) therefore enter the reference and the observations alike and cancel in
the correction kappa = reference / fast model.

The renders are not free: one per iteration, ``spp`` paths per pixel of the whole frame. :attr:`renders`
keeps the statistics of each (seconds, paths per second) for the reports.

:class:`GradientsMonteCarloReference` does the same for the gradient (diffusion) estimate on a known sphere
(:func:`estimation.gradient_correction.estimate_sphere_with_reference`): it renders the whole gradient capture by
Monte Carlo (:func:`simulators.scene.render_gradient_capture` with ``render_mode="mc"``) and reduces it to the
sphere observables with the same map computation, region and summary as the observations
(:meth:`GradientsMonteCarloReference.observables`).
"""
from __future__ import annotations

from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any, Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from estimation.diffusion import SphereEstimate, estimate_sphere
from estimation.gradient_correction import SphereObservables
from estimation.gradients import GradientMaps
from estimation.single_image import Patches

from rig.estimate.pixel_map import sample_at_points

__all__ = ["MonteCarloReference", "GradientsMonteCarloReference", "PixelSubsetCamera", "render_with"]

#: the render function :class:`MonteCarloReference` calls (None: :func:`simulators.mc.render`); set by
#: :func:`render_with`, e.g. by ``rig.estimate.batch`` to split each render into row chunks across Dask workers
_RENDER: ContextVar[Callable[..., Any] | None] = ContextVar("rig_mc_reference_render", default=None)


@contextmanager
def render_with(fn: Callable[..., Any] | None) -> Iterator[None]:
    """Within the block, :class:`MonteCarloReference` renders with ``fn`` (the signature of
    :func:`simulators.mc.render`; it must return the same image, e.g. the same render in chunks of rows)."""
    token = _RENDER.set(fn)
    try:
        yield
    finally:
        _RENDER.reset(token)


class _SampleCountLevels:
    """The sample-count levels both references share (issue 19: render at ``spp_levels[level]``, the loops move up
    a level when the cheaper one's noise is too large). Needs the attributes ``spp``, ``spp_levels``, ``level``."""

    spp: int
    spp_levels: tuple[int, ...]
    level: int

    def _check_levels(self) -> None:
        levels = tuple(int(x) for x in self.spp_levels)
        if levels and (min(levels) < 2 or list(levels) != sorted(set(levels)) or levels[-1] != int(self.spp)):
            raise ValueError(f"spp_levels must be strictly ascending sample counts >= 2 ending at spp = {self.spp}; "
                             f"got {list(self.spp_levels)}")
        self.spp_levels = levels

    @property
    def n_levels(self) -> int:
        """Number of sample-count levels (1 without ``spp_levels``)."""
        return max(1, len(self.spp_levels))

    def set_level(self, level: int) -> None:
        """Render at ``spp_levels[level]`` from now on (0: the cheapest; ``n_levels - 1``: ``spp``)."""
        if not 0 <= int(level) < self.n_levels:
            raise ValueError(f"level must lie in [0, {self.n_levels - 1}]; got {level}")
        self.level = int(level)

    @property
    def current_spp(self) -> int:
        """The sample count of the next render."""
        return self.spp_levels[self.level] if self.spp_levels else int(self.spp)


@dataclass
class MonteCarloReference(_SampleCountLevels):
    """``reference(sigma_s', sigma_a, eta, seed) -> (radiance (K, C), stderr (K, C))`` over all patches.

    ``shape``: a :mod:`simulators.mc` shape (Box, Sphere, Slab, Mesh, ...) in the rig frame (mm); ``camera``:
    the capture's camera (PinholeCamera / OrthographicCamera); ``lights``: the capture's lights in the units of
    the observations (PointLights, EnvironmentMap, ...); ``patches``: the estimator's patches; ``valid_px``
    (H, W) bool, optional: pixels the observations were allowed to use (e.g. those a mesh face covers);
    ``g``: Henyey-Greenstein anisotropy of the reference medium (sigma_s' is held, sigma_s = sigma_s'/(1-g)).
    """

    shape: Any
    camera: Any
    lights: Any
    patches: Patches
    spp: int = 128
    window_px: int = 3
    valid_px: NDArray[np.bool_] | None = None
    g: float = 0.0
    derivatives: bool = True
    #: the derivative in log sigma_s' as a paired forward difference of this step (0: the score-function estimate;
    #: simulators.mc.render's ``fd_log_sigma_s``)
    fd_log_sigma_s: float = 0.1
    renders: list[dict[str, Any]] = field(default_factory=list)
    #: adaptive sample counts (issue 19): ascending, ending at ``spp``; () = ``spp`` alone. The loop
    #: (:func:`estimation.model_correction.estimate_with_reference`) renders first at the cheapest level, then at the
    #: one whose noise matches the fit's
    spp_levels: tuple[int, ...] = ()
    level: int = -1   # index into spp_levels (-1: the last, the full count)
    #: images rendered ahead by :meth:`prefetch`, each for the one call with its arguments (not copied by replace)
    _ahead: dict[tuple[Any, ...], Any] = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.spp < 2:
            raise ValueError("spp must be >= 2 (the correction needs a standard error)")
        self._check_levels()
        if self.valid_px is not None:
            want = (self.camera.height_px, self.camera.width_px)
            if np.shape(self.valid_px) != want:
                raise ValueError(f"valid_px has shape {np.shape(self.valid_px)}; expected the camera's {want}")

    def __call__(self, sigma_s_prime_per_mm: Any, sigma_a_per_mm: Any, eta: float, seed: int
                 ) -> tuple[NDArray[np.float64], ...]:
        """(radiance, stderr) over all patches, and with ``derivatives`` also d radiance / d (log sigma_s',
        log sigma_a) (K, C, 2) and its stderr, from the same paths (:func:`simulators.mc.render`)."""
        from simulators.mc import render

        from rig.feedback import numba_notice
        numba_notice()

        ssp, sa, media, kw = self._render_args(sigma_s_prime_per_mm, sigma_a_per_mm, eta, seed)
        spp = kw["spp"]
        img = self._ahead.pop(self._key(ssp, sa, eta, kw), None)
        if img is None:
            img = (_RENDER.get() or render)(self.shape, media, self.camera, self.lights, **kw)
        valid = img.mask if self.valid_px is None else img.mask & np.asarray(self.valid_px, dtype=bool)
        valid = np.broadcast_to(valid[..., None], img.radiance.shape)
        obs, sig = sample_at_points(img.radiance, img.stderr ** 2, valid, self.camera, self.patches.centers_mm,
                                    self.window_px)
        paths = int(img.mask.sum()) * spp * len(media)
        self.renders.append({"seed": int(seed), "seconds": img.seconds, "paths": paths, "spp": spp,
                             "paths_per_s": paths / max(img.seconds, 1e-9), "derivatives": bool(self.derivatives),
                             "sigma_s_prime_per_mm": ssp.tolist(), "sigma_a_per_mm": sa.tolist()})
        if not self.derivatives or img.d_log_sigma is None:
            return obs, sig
        # at fixed g, d/d log sigma_s' = d/d log sigma_s (sigma_s = sigma_s' / (1 - g))
        parts = [sample_at_points(img.d_log_sigma[..., j], img.d_log_sigma_stderr[..., j] ** 2, valid, self.camera,
                                  self.patches.centers_mm, self.window_px) for j in range(2)]
        d = np.stack([p[0] for p in parts], axis=2)
        d_se = np.stack([p[1] for p in parts], axis=2)
        return obs, sig, d, d_se

    def _render_args(self, sigma_s_prime_per_mm: Any, sigma_a_per_mm: Any, eta: float, seed: int
                     ) -> tuple[NDArray[np.float64], NDArray[np.float64], list[Any], dict[str, Any]]:
        from simulators.mc import Medium

        ssp = np.atleast_1d(np.asarray(sigma_s_prime_per_mm, dtype=np.float64))
        sa = np.atleast_1d(np.asarray(sigma_a_per_mm, dtype=np.float64))
        media = [Medium.from_reduced(float(s), float(a), g=self.g, eta=float(eta)) for s, a in zip(ssp, sa)]
        return ssp, sa, media, dict(spp=int(self.current_spp), seed=int(seed), derivatives=self.derivatives,
                                    fd_log_sigma_s=self.fd_log_sigma_s)

    @staticmethod
    def _key(ssp: NDArray[np.float64], sa: NDArray[np.float64], eta: float, kw: dict[str, Any]) -> tuple[Any, ...]:
        return (ssp.tobytes(), sa.tobytes(), float(eta), kw["spp"], kw["seed"])

    def prefetch(self, calls: list[tuple[Any, Any, float, int]]) -> None:
        """Render the images of these calls (``(sigma_s', sigma_a, eta, seed)`` each, as :meth:`__call__` takes them,
        at the current sample count) at once where the render function set by :func:`render_with` has a ``many``
        method (``rig.estimate.batch_chunks.RenderChunks``: in parallel on a Dask cluster), each kept for the one later call
        with the same arguments; else nothing (each call renders when made). A render is a function of its
        arguments and seed: the numbers are the same either way."""
        many = getattr(_RENDER.get(), "many", None)
        if many is None or len(calls) < 2:
            return
        args = [self._render_args(*c) for c in calls]
        imgs = many([(self.shape, media, self.camera, self.lights, kw) for _, _, media, kw in args])
        self._ahead = {self._key(ssp, sa, c[2], kw): img for (ssp, sa, _, kw), c, img in zip(args, calls, imgs)}


class PixelSubsetCamera:
    """``camera`` with only the pixels of ``mask`` (H, W) looking at the scene: the other pixels' rays are reversed
    (pointing away from everything in front of the camera), so a renderer finds no object there and spends ~nothing
    on them. :func:`simulators.mc.render` seeds each pixel's random stream by its index in the frame, so every pixel
    of ``mask`` is rendered bit-identically to a render of the whole frame (issue 19: render only the pixels the
    sphere summary reads). Every other attribute is the wrapped camera's."""

    def __init__(self, camera: Any, mask: NDArray[np.bool_]) -> None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (int(camera.height_px), int(camera.width_px)):
            raise ValueError(f"mask must be (height_px, width_px) = {(camera.height_px, camera.width_px)}; got "
                             f"{m.shape}")
        self.camera, self.mask = camera, m

    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["camera"], name)

    def pixel_rays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        origins, dirs = self.camera.pixel_rays()
        keep = self.mask.reshape(np.shape(dirs)[:-1] + (1,))
        return origins, np.where(keep, dirs, -np.asarray(dirs))


@dataclass
class GradientsMonteCarloReference(_SampleCountLevels):
    """``reference(sigma_s', sigma_a, eta, seed) -> SphereObservables`` of a gradient capture of a known sphere.

    Renders the capture by Monte Carlo — a :class:`simulators.scene.SphereObject` of ``radius_mm`` at
    ``center_mm`` seen by ``camera`` under ``led_positions_mm`` / ``led_intensity`` driven by ``patterns``
    (``polarizations``, ``exposure_s``, ``sensor`` as in :func:`simulators.scene.render_gradient_capture`, sensor
    noise off: expected values), ``spp`` paths per pixel, every pattern with the given seed — and reduces it
    with :meth:`observables`: ``maps_fn(capture) -> GradientMaps`` (the *same* ``compute_maps`` call, LUT and
    albedo scale as the observations), :func:`estimation.diffusion.estimate_sphere` with the capture's true
    normals and ``erode_px``, and the summary's median albedo / shortening with their intervals. Use
    :meth:`observables` on the observed capture too, so that both go through identical code.
    ``mc``: further :class:`simulators.mc_capture.MCSettings` (its ``spp`` and ``seed`` are replaced).
    :attr:`renders` keeps each render's seconds and parameters. ``render_mode``: "mc" (default; the reference) or
    "fast" (the dipole renderer, no Monte Carlo error: for checking units and map plumbing, not a reference).
    """

    camera: Any
    led_positions_mm: Any
    led_intensity: Any
    patterns: dict[str, Any]
    maps_fn: Callable[[Any], GradientMaps]
    radius_mm: float
    center_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spp: int = 64
    polarizations: tuple[str, ...] = ("cross",)
    exposure_s: float = 1.0
    sensor: Any = None
    erode_px: int = 2
    tessellation: int = 3
    mc: Any = None
    renders: list[dict[str, Any]] = field(default_factory=list)
    render_mode: str = "mc"
    #: adaptive sample counts (issue 19): ascending, ending at ``spp``; () = ``spp`` alone. The loop
    #: (:func:`estimation.gradient_correction.estimate_sphere_with_reference`) starts at the cheapest level
    spp_levels: tuple[int, ...] = ()
    level: int = -1   # index into spp_levels (-1: the last, the full count)
    #: (H, W) pixels to render by Monte Carlo (None: the whole frame); the others stay dark
    #: (:class:`PixelSubsetCamera`): only for reductions that read no other pixel
    render_mask: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        if self.spp < 2:
            raise ValueError("spp must be >= 2 (the Monte Carlo standard error needs two paths per pixel)")
        self._check_levels()
        if self.render_mode not in ("mc", "fast"):
            raise ValueError(f"render_mode must be 'mc' or 'fast'; got {self.render_mode!r}")
        if not self.radius_mm > 0:
            raise ValueError(f"radius_mm must be > 0; got {self.radius_mm!r}")
        if not self.patterns:
            raise ValueError("patterns must name at least one LED pattern")
        if not callable(self.maps_fn):
            raise ValueError("maps_fn must be a callable capture -> GradientMaps")
        if self.erode_px < 0:
            raise ValueError("erode_px must be >= 0")

    def estimate(self, capture: Any) -> SphereEstimate:
        """The sphere estimate of a capture (observed or rendered): maps_fn, then estimate_sphere."""
        maps = self.maps_fn(capture)
        return estimate_sphere(maps, radius_mm=float(self.radius_mm), true_normals=capture.normals,
                               erode_px=int(self.erode_px))

    def observables(self, capture: Any) -> SphereObservables:
        """The region observables of a capture, computed exactly as for the reference renders."""
        return SphereObservables.from_summary(self.estimate(capture).summary)

    def render(self, sigma_s_prime_per_mm: Any, sigma_a_per_mm: Any, eta: float, seed: int,
               spp: int | None = None) -> Any:
        """The Monte Carlo gradient capture (:class:`simulators.scene.GradientCapture`) at these parameters
        (``spp`` paths per pixel; None: :attr:`current_spp`)."""
        from dataclasses import replace

        from simulators.mc_capture import MCSettings
        from simulators.scene import SphereObject, render_gradient_capture

        from rig.feedback import numba_notice
        if self.render_mode == "mc":
            numba_notice()

        ssp = np.broadcast_to(np.asarray(sigma_s_prime_per_mm, dtype=np.float64), (3,))
        sa = np.broadcast_to(np.asarray(sigma_a_per_mm, dtype=np.float64), (3,))
        if not (np.all(np.isfinite(ssp)) and np.all(ssp > 0)):
            raise ValueError(f"sigma_s_prime_per_mm must be finite and > 0; got {ssp.tolist()}")
        if not (np.all(np.isfinite(sa)) and np.all(sa >= 0)):
            raise ValueError(f"sigma_a_per_mm must be finite and >= 0; got {sa.tolist()}")
        n = int(self.current_spp if spp is None else spp)
        settings = MCSettings(spp=n, seed=int(seed)) if self.mc is None else replace(self.mc, spp=n, seed=int(seed))
        obj = SphereObject(tuple(float(c) for c in self.center_mm), float(self.radius_mm),
                           (float(ssp[0]), float(ssp[1]), float(ssp[2])), (float(sa[0]), float(sa[1]), float(sa[2])),
                           float(eta), tessellation=int(self.tessellation))
        camera = (self.camera if self.render_mask is None or self.render_mode != "mc"
                  else PixelSubsetCamera(self.camera, self.render_mask))
        return render_gradient_capture(obj, camera, self.led_positions_mm, self.led_intensity, self.patterns,
                                       polarizations=self.polarizations, exposure_s=self.exposure_s,
                                       sensor=self.sensor, noise=False, render_mode=self.render_mode, mc=settings)

    def __call__(self, sigma_s_prime_per_mm: Any, sigma_a_per_mm: Any, eta: float, seed: int) -> SphereObservables:
        import time

        t0 = time.perf_counter()
        spp = self.current_spp
        cap = self.render(sigma_s_prime_per_mm, sigma_a_per_mm, eta, seed, spp=spp)
        t1 = time.perf_counter()
        obs = self.observables(cap)
        self.renders.append({"seed": int(seed), "render_seconds": t1 - t0, "maps_seconds": time.perf_counter() - t1,
                             "sigma_s_prime_per_mm": np.atleast_1d(sigma_s_prime_per_mm).tolist(),
                             "sigma_a_per_mm": np.atleast_1d(sigma_a_per_mm).tolist(), "spp": int(spp)})
        return obs
