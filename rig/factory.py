"""Config -> devices. A device whose URL is ``sim`` gets its simulator started on a real transport
(the LED sphere and the trigger box on ptys, the total station on loopback TCP) and its driver then talks
to it over the wire exactly as it would to hardware. Triggers without a byte stream are simulated at their
own transport: a HID box (``trigger.driver = "hid"``) by ``FakeHidTriggerBox`` at the ``HidTransport`` seam,
a serial-line release (``"serial-release"``) by a pyserial ``loop://`` port whose DTR line is watched by
the simulated camera (``SimulatedReleaseCable``)."""
from __future__ import annotations

import logging
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from serial.urlhandler import protocol_loop

from drivers.camera.folder import FolderCamera
from drivers.contracts import Camera, Trigger
from drivers.led_sphere.driver import open_led_sphere_serial
from drivers.total_station.driver import open_total_station
from drivers.trigger.esper import OUTPUT_COUNT as ESPER_OUTPUTS
from drivers.trigger.esper import open_esper_trigger
from drivers.trigger.hid_box import HidTrigger, open_hid_trigger
from drivers.trigger.serial_release import SerialRelease, open_serial_release

from .config import CameraConfig, RigConfig, TriggerConfig
from .geometry import RigGeometry, rig_geometry
from .runner import Devices

__all__ = ["ROLES", "SimulatedRig", "SimulatedReleaseCable", "open_camera", "open_device", "open_devices", "open_trigger",
           "rig_geometry", "skip_exposure_waits", "start_simulators"]  # rig_geometry: re-exported for hil/ and the CLI


class _Stopper:
    def __init__(self, obj: Any) -> None:
        self.obj = obj

    def close(self) -> None:
        self.obj.stop()


class _Cleanup:
    def __init__(self, tmp: tempfile.TemporaryDirectory) -> None:
        self.tmp = tmp

    def close(self) -> None:
        self.tmp.cleanup()


@dataclass
class SimulatedRig:
    """The simulators of one rig, running on real transports."""

    urls: dict[str, str]
    drop_folder: Path
    truth: dict[str, Any]
    _closers: list[Any] = field(default_factory=list)
    servers: dict[str, Any] = field(default_factory=dict)   # role -> simulator server (fault hooks, model)
    # role -> in-process transport a driver uses instead of a URL (FakeHidTriggerBox, SimulatedReleaseCable)
    transports: dict[str, Any] = field(default_factory=dict)
    camera: Any = None      # the SimulatedCamera (calibration attaches its targets to it)

    def close(self) -> None:
        for c in reversed(self._closers):
            try:
                c.close()
            except Exception:
                pass


class SimulatedReleaseCable(protocol_loop.Serial):
    """A pyserial ``loop://`` port whose far end is the simulated camera's remote-release socket.

    ``SerialRelease`` drives it like a real port (``loop://`` mirrors RTS->CTS and DTR->DSR). The camera
    watches the shutter line: DTR asserted opens the shutter, DTR released closes it, and ``on_fire`` gets the
    time DTR was high in whole milliseconds, rounded down (the simulated shutter's resolution): the host
    times this exposure, so a late wake-up of the host lengthens it, as it would a real one. Created with
    both lines low, then opened, as ``open_serial_release`` does with real ports.
    """

    def __init__(self, on_fire: Callable[[float], None] | None = None) -> None:
        self.on_fire = on_fire
        self.fired: list[float] = []                  # exposure_s of every shot, for tests
        self.focused: list[bool] = []                 # whether RTS (focus) was asserted when DTR rose
        self.callback_errors: list[BaseException] = []
        self._t_open: float | None = None
        self._line_lock = threading.Lock()
        super().__init__()                            # not opened yet: set the lines low first
        self.rts = False
        self.dtr = False
        self.port = "loop://"
        self.open()

    def _update_dtr_state(self) -> None:
        super()._update_dtr_state()
        with self._line_lock:
            if self._dtr_state and self._t_open is None:
                self._t_open = time.monotonic()
                self.focused.append(bool(self._rts_state))
                return
            if self._dtr_state or self._t_open is None:
                return
            exposure_s = max(1, int((time.monotonic() - self._t_open) * 1000.0)) / 1000.0
            self._t_open = None
            self.fired.append(exposure_s)
        if self.on_fire is not None:
            try:
                self.on_fire(exposure_s)
            except Exception as exc:  # noqa: BLE001 - a camera-side bug must not break the trigger
                self.callback_errors.append(exc)


def uses_simulators(config: RigConfig) -> bool:
    """Whether any device URL of ``config`` names the simulators ("sim")."""
    return "sim" in (config.sphere.url, config.trigger.url, config.camera.folder, config.total_station.url)


def start_simulators(config: RigConfig, geometry: RigGeometry, workdir: Path | None = None
                     ) -> SimulatedRig:
    """Start every simulator the config asks for (URL ``sim``). The simulated camera drops its frames under
    ``workdir`` (default: a temporary folder removed by :meth:`SimulatedRig.close`)."""
    from simulators.camera import SensorModel, SimulatedCamera
    from simulators.led_sphere import LedSphereModel, Ticker
    from simulators.scene import SphereObject
    from simulators.serve import serve
    from simulators.total_station import GeoComModel
    from simulators.trigger import EsperTriggerModel, FakeHidTriggerBox

    sc, cam = config.scene, config.camera
    own = None if workdir is not None else tempfile.TemporaryDirectory(prefix="sssrig-simcam-")
    drop = Path(workdir if workdir is not None else own.name) / "drop"
    obj = SphereObject(sc.center_mm, sc.radius_mm, sc.sigma_s_prime_per_mm, sc.sigma_a_per_mm, sc.eta,
                       tessellation=sc.tessellation)
    sensor = SensorModel(cam.gain_dn_per_unit, cam.black_level_dn, cam.white_level_dn,
                         cam.read_noise_dn, cam.electrons_per_dn)
    from simulators.mc_capture import MCSettings

    simcam = SimulatedCamera(obj, geometry.camera, geometry.led_positions_mm,
                             config.sphere.led_intensity, drop, sensor, seed=sc.seed, render_mode=sc.render,
                             mc=MCSettings(spp=sc.mc_spp, seed=sc.seed))
    if sc.render == "mc":
        from .feedback import numba_notice
        numba_notice()
    renderer = ("the Jensen dipole (fast renderer)" if sc.render == "fast" else
                f"Monte Carlo light transport ({sc.mc_spp} paths per pixel)")
    rig = SimulatedRig({}, drop, truth={
        "shape": sc.shape, "radius_mm": sc.radius_mm, "center_mm": list(sc.center_mm),
        "material": sc.material, "sigma_s_prime_per_mm": list(sc.sigma_s_prime_per_mm),
        "sigma_a_per_mm": list(sc.sigma_a_per_mm), "eta": sc.eta, "renderer": renderer})
    if own is not None:
        rig._closers.append(_Cleanup(own))    # the simulators' own folder goes with them (rig.close())
    rig._closers.append(simcam)
    rig.camera = simcam
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
            rig.servers["sphere"] = srv
        if config.trigger.url == "sim" and config.trigger.driver == "hid":
            box = FakeHidTriggerBox(on_fire=simcam.on_fire)
            rig.transports["trigger"] = box
            rig.urls["trigger"] = "in-process FakeHidTriggerBox (HidTransport seam)"
        elif config.trigger.url == "sim" and config.trigger.driver == "serial-release":
            cable = SimulatedReleaseCable(on_fire=simcam.on_fire)
            rig._closers.append(cable)
            rig.transports["trigger"] = cable
            rig.urls["trigger"] = "loop://"
        elif config.trigger.url == "sim":
            srv = serve(EsperTriggerModel(on_fire=simcam.on_fire), "pty")
            rig._closers.append(srv)
            rig.urls["trigger"] = srv.url
            rig.servers["trigger"] = srv
        if config.total_station.url == "sim":
            targets = dict(geometry.targets)
            gs = config.total_station
            model = GeoComModel(targets, station_xyz_mm=gs.station_xyz_mm,
                                station_yaw_deg=gs.station_yaw_deg, noise_mm=gs.noise_mm,
                                seed=sc.seed, checksum=gs.crc)
            srv = serve(model, "tcp://127.0.0.1:0")
            rig._closers.append(srv)
            rig.urls["total_station"] = srv.url
            rig.servers["total_station"] = srv
        if cam.folder == "sim":
            rig.urls["camera"] = str(drop)
    except BaseException:
        rig.close()
        raise
    return rig


def skip_exposure_waits(devices: Devices, sim: SimulatedRig | None) -> None:
    """The simulated camera renders a frame at once: the trigger driver need not wait the exposure out, and
    the simulated ESPER box is then not busy for it (it would answer the next ``S`` BUSY)."""
    if hasattr(devices.trigger, "wait_for_exposure"):
        devices.trigger.wait_for_exposure = False
    server = sim.servers.get("trigger") if sim is not None else None
    if server is not None and hasattr(server.device, "busy_during_exposure"):
        server.device.busy_during_exposure = False


def open_trigger(tc: TriggerConfig, sim: SimulatedRig | None = None) -> Trigger:
    """The [trigger] driver on its configured device, or on the simulator ``sim`` started for it."""
    urls = sim.urls if sim else {}
    transports = sim.transports if sim else {}
    limits = dict(min_exposure_s=tc.min_exposure_s, max_exposure_s=tc.max_exposure_s)
    if tc.url == "sim" and tc.driver != "esper" and "trigger" not in transports:
        raise ValueError(f'trigger driver {tc.driver!r} with url "sim" needs the simulated rig '
                         "(start_simulators) to provide its transport")
    if tc.driver == "hid":
        if "trigger" in transports:
            box = transports["trigger"]
            box.closed = False             # (re)opening the simulated box, as hidapi reopens a real one
            return HidTrigger(box, timeout_s=tc.timeout_s, outputs_mask=tc.outputs_mask,
                              name="hid-trigger (simulated)", **limits)
        return open_hid_trigger(tc.vendor_id or None, tc.product_id or None, serial=tc.serial or None,
                                path=tc.path.encode() if tc.path else None, timeout_s=tc.timeout_s,
                                outputs_mask=tc.outputs_mask, **limits)
    if tc.driver == "serial-release":
        if "trigger" in transports:
            cable = transports["trigger"]
            if not cable.is_open:          # reopened after a close(): both lines are still low
                cable.open()
            return SerialRelease(cable, focus_lead_s=tc.focus_lead_s,
                                 name="serial-release loop:// (simulated)", **limits)
        return open_serial_release(tc.url, focus_lead_s=tc.focus_lead_s, **limits)
    outputs = tuple(bool(tc.outputs_mask >> i & 1) for i in range(ESPER_OUTPUTS))
    return open_esper_trigger(urls.get("trigger", tc.url), timeout_s=tc.timeout_s, outputs=outputs, **limits)


def open_camera(cc: CameraConfig, sim: SimulatedRig | None = None) -> Camera:
    """The [camera] driver: a watched folder (the simulated camera's drop folder for ``folder = "sim"``) or
    a camera through libgphoto2 (optional extra ``sssrig[gphoto]``), downloading into ``folder``."""
    if cc.driver == "gphoto2":
        from drivers.camera.gphoto import open_gphoto_camera

        return open_gphoto_camera(cc.port, cc.model, capture_mode=cc.capture_mode, download_dir=cc.folder,
                                  pattern=cc.pattern, delete_after_download=cc.delete_after_download)
    urls = sim.urls if sim else {}
    return FolderCamera(urls.get("camera", cc.folder), pattern=cc.pattern)


ROLES = ("sphere", "trigger", "camera", "total_station")


def open_device(role: str, config: RigConfig, geometry: RigGeometry, sim: SimulatedRig | None = None) -> Any:
    """Open one device's driver (``role`` one of :data:`ROLES`) on its configured URL or its simulator's."""
    urls = sim.urls if sim else {}
    if role == "sphere":
        s = config.sphere
        limits = dict(max_total_current_a=s.max_total_current_a, max_mean_duty=s.max_mean_duty,
                      led_current_a_per_channel=s.led_current_a_per_channel)
        if s.driver.startswith("modbus"):
            from drivers.led_sphere_modbus import open_led_sphere_modbus
            return open_led_sphere_modbus(urls.get("sphere", s.url), **limits)
        return open_led_sphere_serial(urls.get("sphere", s.url), **limits)
    if role == "trigger":
        return open_trigger(config.trigger, sim)
    if role == "camera":
        return open_camera(config.camera, sim)
    if role == "total_station":
        ts = config.total_station
        return open_total_station(urls.get("total_station", ts.url), station_xyz_mm=ts.station_xyz_mm,
                                  station_yaw_deg=ts.station_yaw_deg, targets=geometry.targets, checksum=ts.crc,
                                  max_error_mm=ts.max_survey_error_mm, logger=logging.getLogger("geocompy"))
    raise ValueError(f"unknown device role {role!r}; expected one of {', '.join(ROLES)}")


def open_devices(config: RigConfig, geometry: RigGeometry, sim: SimulatedRig | None = None
                 ) -> Devices:
    """Open every device's driver on its configured URL (or its simulator's)."""
    opened: list[Any] = []
    try:
        for role in ROLES:
            opened.append(open_device(role, config, geometry, sim))
    except BaseException:
        for dev in opened:
            try:
                dev.close()
            except Exception:
                pass
        raise
    return Devices(*opened)
