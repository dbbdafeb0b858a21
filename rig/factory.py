"""Config -> devices. A device whose URL is ``sim`` gets its simulator started on a real transport
(the LED sphere and the trigger box on ptys, the total station on loopback TCP) and its driver then talks
to it over the wire exactly as it would to hardware."""
from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from drivers.camera.folder import FolderCamera
from drivers.led_sphere.driver import open_led_sphere_serial
from drivers.total_station.driver import open_total_station
from drivers.trigger.esper import open_esper_trigger

from .config import RigConfig
from .geometry import RigGeometry, rig_geometry  # noqa: F401  (re-exported)
from .runner import Devices


class _Stopper:
    def __init__(self, obj: Any) -> None:
        self.obj = obj

    def close(self) -> None:
        self.obj.stop()


@dataclass
class SimulatedRig:
    """The simulators of one rig, running on real transports."""

    urls: dict[str, str]
    drop_folder: Path
    truth: dict[str, Any]
    _closers: list[Any] = field(default_factory=list)

    def close(self) -> None:
        for c in reversed(self._closers):
            try:
                c.close()
            except Exception:
                pass


def start_simulators(config: RigConfig, geometry: RigGeometry, workdir: Path | None = None
                     ) -> SimulatedRig:
    """Start every simulator the config asks for (URL ``sim``)."""
    from simulators.camera import SensorModel, SimulatedCamera
    from simulators.led_sphere import LedSphereModel, Ticker
    from simulators.scene import SphereObject
    from simulators.serve import serve
    from simulators.total_station import GeoComModel
    from simulators.trigger import EsperTriggerModel

    sc, cam = config.scene, config.camera
    drop = Path(workdir or tempfile.mkdtemp(prefix="sssrig-simcam-")) / "drop"
    obj = SphereObject(sc.center_mm, sc.radius_mm, sc.sigma_s_prime_per_mm, sc.sigma_a_per_mm, sc.eta,
                       tessellation=sc.tessellation)
    sensor = SensorModel(cam.gain_dn_per_unit, cam.black_level_dn, cam.white_level_dn,
                         cam.read_noise_dn, cam.electrons_per_dn)
    simcam = SimulatedCamera(obj, geometry.camera, geometry.led_positions_mm,
                             config.sphere.led_intensity, drop, sensor, seed=sc.seed)
    rig = SimulatedRig({}, drop, truth={
        "shape": sc.shape, "radius_mm": sc.radius_mm, "center_mm": list(sc.center_mm),
        "material": sc.material, "sigma_s_prime_per_mm": list(sc.sigma_s_prime_per_mm),
        "sigma_a_per_mm": list(sc.sigma_a_per_mm), "eta": sc.eta})
    rig._closers.append(simcam)
    try:
        if config.sphere.url == "sim" and config.sphere.driver.startswith("modbus"):
            from simulators.led_sphere_modbus import LedSphereModbusSim

            rtu = config.sphere.driver == "modbus-rtu"
            msim = LedSphereModbusSim(len(geometry.led_positions_mm), simcam.on_light_change,
                                      tcp=None if rtu else "127.0.0.1:0", rtu=rtu).start()
            rig._closers.append(_Stopper(msim))
            rig.urls["sphere"] = msim.url
        elif config.sphere.url == "sim":
            model = LedSphereModel(led_count=len(geometry.led_positions_mm),
                                   on_light_change=simcam.on_light_change)
            srv = serve(model, "pty")
            rig._closers.append(srv)
            rig._closers.append(Ticker(model).start())   # the watchdog runs while the host is silent
            rig.urls["sphere"] = srv.url
        if config.trigger.url == "sim":
            srv = serve(EsperTriggerModel(on_fire=simcam.on_fire), "pty")
            rig._closers.append(srv)
            rig.urls["trigger"] = srv.url
        if config.total_station.url == "sim":
            targets = dict(geometry.targets)
            gs = config.total_station
            model = GeoComModel(targets, station_xyz_mm=gs.station_xyz_mm,
                                station_yaw_deg=gs.station_yaw_deg, noise_mm=gs.noise_mm,
                                seed=sc.seed)
            srv = serve(model, "tcp://127.0.0.1:0")
            rig._closers.append(srv)
            rig.urls["total_station"] = srv.url
        if cam.folder == "sim":
            rig.urls["camera"] = str(drop)
    except BaseException:
        rig.close()
        raise
    return rig


def open_devices(config: RigConfig, geometry: RigGeometry, sim: SimulatedRig | None = None
                 ) -> Devices:
    """Open every device's driver on its configured URL (or its simulator's)."""
    urls = sim.urls if sim else {}
    s = config.sphere
    opened: list[Any] = []
    limits = dict(max_total_current_a=s.max_total_current_a, max_mean_duty=s.max_mean_duty,
                  led_current_a_per_channel=s.led_current_a_per_channel)
    try:
        if s.driver.startswith("modbus"):
            from drivers.led_sphere_modbus import open_led_sphere_modbus
            light = open_led_sphere_modbus(urls.get("sphere", s.url), **limits)
        else:
            light = open_led_sphere_serial(urls.get("sphere", s.url), **limits)
        opened.append(light)
        trigger = open_esper_trigger(urls.get("trigger", config.trigger.url))
        opened.append(trigger)
        camera = FolderCamera(urls.get("camera", config.camera.folder))
        opened.append(camera)
        ts = config.total_station
        feed = open_total_station(urls.get("total_station", ts.url), station_xyz_mm=ts.station_xyz_mm,
                                  station_yaw_deg=ts.station_yaw_deg, targets=geometry.targets)
        opened.append(feed)
    except BaseException:
        for dev in opened:
            try:
                dev.close()
            except Exception:
                pass
        raise
    return Devices(light, trigger, camera, feed)
