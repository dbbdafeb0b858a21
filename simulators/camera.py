"""The simulated camera: renders the virtual scene under the sphere's current light and drops a DNG.

It listens to the LED-sphere simulator (``on_light_change``) and the trigger simulator (``on_fire``). On
each fire it snapshots the light state (what the sensor integrates during the exposure), then renders in a
worker thread and writes ``frame_NNNNN.dng`` atomically into ``drop_folder``, as tethering software would:
the folder-watching camera driver picks it up. Noise: Poisson photon noise (``electrons_per_dn``) plus
Gaussian read noise, on each photosite of an RGGB mosaic; 14-bit DNG with a black level.

``render_mode``: "fast" (default; the Jensen dipole, :func:`simulators.scene.render_object`) or "mc" (the
subsurface light by Monte Carlo, :mod:`simulators.mc_capture`, options ``mc``; seeded by ``mc.seed``, so a frame
re-taken is the same frame). The last shot's Monte Carlo standard error is kept in ``last_stderr``.
"""
from __future__ import annotations

import hashlib
import queue
import threading
from pathlib import Path

import numpy as np
import numpy.typing as npt

from drivers.contracts import Polarization
from estimation.camera import PinholeCamera

from .dng import write_cfa_dng
from .mc_capture import MCSettings, check_render_mode
from .scene import SceneObject, render_object
from .sensor import SensorModel, expose


class SimulatedCamera:
    """Couples the LED and trigger simulators to a renderer and a drop folder."""

    def __init__(self, obj: SceneObject, camera: PinholeCamera, led_positions_mm: npt.ArrayLike,
                 led_intensity: npt.ArrayLike, drop_folder: str | Path, sensor: SensorModel,
                 *, seed: int = 0, render_mode: str = "fast", mc: MCSettings | None = None) -> None:
        self.obj = obj
        self.render_mode = check_render_mode(render_mode)
        self.mc = mc if mc is not None else MCSettings(seed=int(seed))
        self.last_stderr: npt.NDArray[np.float64] | None = None   # "mc": radiance stderr of the last render
        self.camera = camera
        self.led_positions_mm = np.asarray(led_positions_mm, float)
        self.led_intensity = np.asarray(led_intensity, float)
        self.drop_folder = Path(drop_folder)
        self.drop_folder.mkdir(parents=True, exist_ok=True)
        self.sensor = sensor
        self.seed = int(seed)
        self.rng = np.random.default_rng(seed)   # for callers rendering their own shots (simulators/targets.py)
        self._emission = np.zeros((len(self.led_positions_mm), 3))
        self._polarization = Polarization.NONE
        self._lock = threading.Lock()
        self._count = 0
        self._jobs: queue.Queue = queue.Queue()
        self._worker = threading.Thread(target=self._work, name="simcam", daemon=True)
        self._worker.start()

    # --- callbacks from the other simulators -------------------------------------------------
    def on_light_change(self, led_rgb: npt.ArrayLike, polarization: Polarization) -> None:
        with self._lock:
            self._emission = np.asarray(led_rgb, float) * self.led_intensity
            self._polarization = Polarization(polarization)

    def on_fire(self, exposure_s: float) -> None:
        with self._lock:
            job = (self._count, self._emission.copy(), self._polarization, float(exposure_s))
            self._count += 1
        self._jobs.put(job)

    # --- rendering -----------------------------------------------------------------------------
    def shot_rng(self, emission: npt.ArrayLike, polarization: Polarization, exposure_s: float
                 ) -> np.random.Generator:
        """The noise generator of one shot: seeded by the camera's seed and the shot itself (LED emission,
        polarizer, exposure to 1 us). A frame re-taken after a crash (``rig resume``) is therefore
        byte-identical to the one an uninterrupted session takes, whatever the simulator rendered before.
        The same shot twice gives the same noise: average different shots, not repeats, to reduce it."""
        h = hashlib.blake2b(digest_size=8)
        h.update(np.ascontiguousarray(np.asarray(emission, np.float64)).tobytes())
        h.update(Polarization(polarization).name.encode())
        h.update(f"{round(float(exposure_s) * 1e6)}".encode())
        return np.random.default_rng([self.seed & 0xFFFFFFFF, int.from_bytes(h.digest(), "little")])

    def render_raw(self, emission: npt.ArrayLike, polarization: Polarization, exposure_s: float
                   ) -> npt.NDArray[np.uint16]:
        res = render_object(self.obj, self.camera, self.led_positions_mm, np.asarray(emission, float),
                            polarization, render_mode=self.render_mode, mc=self.mc)
        self.last_stderr = res.stderr
        return expose(res.radiance, exposure_s, self.sensor, self.shot_rng(emission, polarization, exposure_s))

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            index, emission, pol, exposure_s = job
            try:
                raw = self.render_raw(emission, pol, exposure_s)
                write_cfa_dng(self.drop_folder / f"frame_{index:05d}.dng", raw,
                              black_level=self.sensor.black_level_dn,
                              white_level=self.sensor.white_level_dn, exposure_s=exposure_s)
            except Exception as exc:  # pragma: no cover - surfaced to the driver as a missing frame
                (self.drop_folder / f"frame_{index:05d}.error.txt").write_text(repr(exc))
            finally:
                self._jobs.task_done()

    def close(self) -> None:
        self._jobs.put(None)
        self._worker.join(timeout=60)
