"""Simulated LED sphere with a Modbus interface, served over Modbus TCP and Modbus RTU (on a pty).

Two layers:

* :class:`LedSphereModbusModel` — the device's behaviour, no I/O: ``read(address)`` gives a register's
  value, ``write(address, values)`` applies one Modbus write request atomically (all registers or none)
  and returns a Modbus exception code or ``None``. The register map comes from
  :mod:`drivers.led_sphere_modbus.registers`.
* :class:`LedSphereModbusSim` — serves the model through pymodbus 3.16's *real* servers: a
  ``SimDevice`` whose register list is generated from the map and whose async ``action`` hook hands every
  request to the model (writes are validated/applied, reads are refreshed from the model). A
  ``ModbusTcpServer`` listens on 127.0.0.1 and/or a ``ModbusSerialServer`` (RTU framer) owns one end of a
  ``socat`` pty pair; the other end is what a master opens. Both servers share one model, so the same
  device is reachable both ways at once. The asyncio loop runs in a background thread.

``python -m simulators.led_sphere_modbus --tcp 127.0.0.1:5020 --rtu`` prints the URL(s) and serves
until interrupted.

Note: ``os.openpty()`` is not enough for RTU: pymodbus's serial server *and* the master (pymodbus or
mbpoll) both open their end by path, and a pty master has no path; socat gives both ends a path.
"""
from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt
from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.contracts import Polarization
from drivers.led_sphere_modbus import registers as rm

LightCallback = Callable[[npt.NDArray[np.float64], Polarization], None]

_ADDR: dict[int, tuple[rm.Register, int]] = {
    r.address + i: (r, i) for r in rm.REGISTERS for i in range(r.count)
}
_WINDOW = rm.reg("UPLOAD_WINDOW")
_READ_FCS = {1, 2, 3, 4}


@dataclass
class _State:
    """Everything a write can change; copied for all-or-nothing writes."""

    selected: int
    polarization: int
    watchdog_ms: int
    latched_faults: int
    upload_slot: int
    upload_offset: int
    staging: npt.NDArray[np.uint16]          # (N, 3)
    staged: npt.NDArray[np.bool_]            # (N,)
    committed: npt.NDArray[np.bool_]         # (slots,)
    slot_updates: dict[int, npt.NDArray[np.uint16]] = field(default_factory=dict)
    busy_until: float = 0.0

    def scratch(self) -> _State:
        return replace(self, staging=self.staging.copy(), staged=self.staged.copy(),
                       committed=self.committed.copy(), slot_updates={})


class LedSphereModbusModel:
    """Behaviour of the LED sphere behind its Modbus register map (thread-safe, no I/O)."""

    def __init__(self, led_count: int, on_light_change: LightCallback | None = None, *,
                 slot_count: int = 64, model: str = "SSS-LEDSPHERE-MB", serial_number: str = "SIM00001",
                 firmware: tuple[int, int] = (1, 2), led_current_a_per_channel: float = 0.02,
                 max_total_current_a: float | None = None, commit_busy_s: float = 0.0,
                 ambient_c: float = 25.0) -> None:
        if not 1 <= led_count < rm.DARK:
            raise ValueError(f"led_count must be in 1..65534, got {led_count}")
        if not 1 <= slot_count < rm.DARK:
            raise ValueError(f"slot_count must be in 1..65534, got {slot_count}")
        self.led_count = led_count
        self.slot_count = slot_count
        self.on_light_change = on_light_change
        self.model = model
        self.serial_number = serial_number
        self.firmware = firmware
        self.led_current_a_per_channel = led_current_a_per_channel
        self.max_total_current_a = max_total_current_a   # the device's own hardware limit (None = none)
        self.commit_busy_s = commit_busy_s               # how long a commit keeps the device busy
        self.ambient_c = ambient_c
        self.force_busy = False                          # fault: answer every lighting/upload write with 6
        self._identity = self._identity_registers()
        self._lock = threading.RLock()
        self._last_light: tuple[npt.NDArray[np.float64], Polarization] | None = None
        self.reset()

    # -- state ---------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Back to the power-on state (no committed slots, dark, no faults, no watchdog)."""
        with self._lock:
            n, s = self.led_count, self.slot_count
            self._slots = np.zeros((s, n, 3), np.uint16)
            self._st = _State(selected=rm.DARK, polarization=0, watchdog_ms=0, latched_faults=0,
                              upload_slot=rm.DARK, upload_offset=0, staging=np.zeros((n, 3), np.uint16),
                              staged=np.zeros(n, bool), committed=np.zeros(s, bool))
            self._temperature_override: float | None = None
            self.force_busy = False
            self._last_request = time.monotonic()
            self._watchdog_tripped = False
        self._notify_if_changed()   # a lit sphere going dark on reset is a light change
        self.light_changes = 0

    def _identity_registers(self) -> dict[str, list[int]]:
        return {
            "MODEL": rm.encode_ascii(self.model, rm.reg("MODEL").count),
            "FIRMWARE_MAJOR": [self.firmware[0]], "FIRMWARE_MINOR": [self.firmware[1]],
            "PROTOCOL_VERSION": [rm.PROTOCOL_VERSION], "LED_COUNT": [self.led_count],
            "CHANNELS": [rm.CHANNELS], "SLOT_COUNT": [self.slot_count],
            "WINDOW_REGISTERS": [rm.WINDOW_REGISTERS],
            "SERIAL_NUMBER": rm.encode_ascii(self.serial_number, rm.reg("SERIAL_NUMBER").count),
        }

    @property
    def temperature_c(self) -> float:
        t = self._temperature_override
        return self.ambient_c if t is None else t

    def set_temperature_c(self, value: float | None) -> None:
        """Fault injection: force the board temperature (None = back to ambient). Above
        OVER_TEMPERATURE_C the LEDs go dark at once, as the firmware does."""
        with self._lock:
            self._temperature_override = value
            if self.over_temperature:
                self._st.selected = rm.DARK
        self._notify_if_changed()

    @property
    def over_temperature(self) -> bool:
        return self.temperature_c > rm.OVER_TEMPERATURE_C

    def inject_led_fault(self) -> None:
        """Fault injection: latch the LED-fault bit."""
        with self._lock:
            self._st.latched_faults |= rm.FaultBit.LED_FAULT

    @property
    def busy(self) -> bool:
        return self.force_busy or time.monotonic() < self._st.busy_until

    @property
    def fault_flags(self) -> int:
        return int(self._st.latched_faults | (rm.FaultBit.OVER_TEMPERATURE if self.over_temperature else 0))

    @property
    def active_slot(self) -> int | None:
        return None if self._st.selected == rm.DARK else self._st.selected

    @property
    def polarization(self) -> Polarization:
        return Polarization(self._st.polarization)

    @property
    def watchdog_ms(self) -> int:
        return self._st.watchdog_ms

    def slot_pattern(self, slot: int) -> npt.NDArray[np.uint16]:
        """A copy of what is stored in ``slot`` ((N, 3) uint16)."""
        with self._lock:
            return self._slots[slot].copy()

    def is_committed(self, slot: int) -> bool:
        return bool(self._st.committed[slot])

    @property
    def light(self) -> npt.NDArray[np.float64]:
        """What the LEDs emit now: (N, 3) in [0, 1]."""
        with self._lock:
            sel = self._st.selected
            if sel == rm.DARK or self.over_temperature:
                return np.zeros((self.led_count, 3))
            return self._slots[sel].astype(np.float64) / 65535.0

    def _current_a(self, light: npt.NDArray[np.float64]) -> float:
        return float(light.sum()) * self.led_current_a_per_channel

    # -- register access --------------------------------------------------------------------------------

    def read(self, address: int) -> int:
        """Value of the register at ``address`` (KeyError if unmapped)."""
        r, i = _ADDR[address]
        with self._lock:
            st = self._st
            if r.name in self._identity:
                return self._identity[r.name][i]
            if r.name == "UPLOAD_WINDOW":
                led, ch = st.upload_offset + i // 3, i % 3
                return int(st.staging[led, ch]) if led < self.led_count else 0
            if r.name in ("TEMPERATURE", "CURRENT", "LIT"):
                light = self.light
                if r.name == "TEMPERATURE":
                    return rm.from_i16(int(round(self.temperature_c / r.scale)))
                if r.name == "CURRENT":
                    return min(0xFFFF, int(round(self._current_a(light) * 1000)))
                return int(bool(light.any()))
            simple = {
                "FAULT_FLAGS": self.fault_flags, "ACTIVE_SLOT": st.selected,
                "POLARIZATION_STATE": st.polarization, "STAGED_LEDS": int(st.staged.sum()),
                "BUSY": int(self.busy), "SELECT_SLOT": st.selected, "POLARIZATION": st.polarization,
                "WATCHDOG_MS": st.watchdog_ms, "UPLOAD_SLOT": st.upload_slot,
                "UPLOAD_OFFSET": st.upload_offset, "ALL_OFF": 0, "CLEAR_FAULTS": 0, "UPLOAD_COMMIT": 0,
            }
            return int(simple[r.name])

    def write(self, address: int, values: list[int]) -> int | None:
        """Apply one write request (registers ``address``.. in ascending order, all or nothing).

        Returns a Modbus exception code (:class:`registers.ExceptionCode`) or None on success.
        """
        with self._lock:
            st = self._st.scratch()
            for addr, value in zip(range(address, address + len(values)), values):
                if addr not in _ADDR:
                    return rm.ExceptionCode.ILLEGAL_DATA_ADDRESS
                code = self._write_one(st, addr, int(value))
                if code is not None:
                    return code
            for slot, pattern in st.slot_updates.items():
                self._slots[slot] = pattern
            st.slot_updates = {}
            self._st = st
        self._notify_if_changed()
        return None

    def _write_one(self, st: _State, addr: int, v: int) -> int | None:  # noqa: C901 (a flat dispatch)
        r, i = _ADDR[addr]
        bad, busy = rm.ExceptionCode.ILLEGAL_DATA_VALUE, rm.ExceptionCode.SERVER_DEVICE_BUSY
        if r.access is rm.Access.R:
            return rm.ExceptionCode.ILLEGAL_DATA_ADDRESS
        name = r.name
        if name == "SELECT_SLOT":
            if v == rm.DARK:
                st.selected = v
                return None
            if v >= self.slot_count or not st.committed[v]:
                return bad
            if self.busy:
                return busy
            if self.over_temperature:
                return rm.ExceptionCode.SERVER_DEVICE_FAILURE
            st.selected = v
        elif name == "POLARIZATION":
            if v not in rm.POLARIZATION_VALUES:
                return bad
            st.polarization = v
        elif name == "ALL_OFF":
            if v != rm.ALL_OFF_COMMAND:
                return bad
            st.selected = rm.DARK
        elif name == "WATCHDOG_MS":
            if v > rm.MAX_WATCHDOG_MS:
                return bad
            st.watchdog_ms = v
        elif name == "CLEAR_FAULTS":
            st.latched_faults &= ~v
        elif name == "UPLOAD_SLOT":
            if v != rm.DARK and v >= self.slot_count:
                return bad
            if self.busy:
                return busy
            st.upload_slot = v
            st.staging[:] = 0
            st.staged[:] = False
        elif name == "UPLOAD_OFFSET":
            if v >= self.led_count:
                return bad
            if self.busy:
                return busy
            st.upload_offset = v
        elif name == "UPLOAD_WINDOW":
            led, ch = st.upload_offset + i // 3, i % 3
            if st.upload_slot == rm.DARK or led >= self.led_count:
                return bad
            if self.busy:
                return busy
            st.staging[led, ch] = v
            st.staged[led] = True
        elif name == "UPLOAD_COMMIT":
            if v != rm.COMMIT_COMMAND or st.upload_slot == rm.DARK:
                return bad
            if self.busy:
                return busy
            if self.max_total_current_a is not None and (
                    self._current_a(st.staging / 65535.0) > self.max_total_current_a):
                return bad
            st.slot_updates[st.upload_slot] = st.staging.copy()
            st.committed[st.upload_slot] = True
            st.busy_until = time.monotonic() + self.commit_busy_s
        else:  # pragma: no cover - every writable register is handled above
            raise AssertionError(f"unhandled register {name}")
        return None

    # -- watchdog and notifications ------------------------------------------------------------------

    def kick(self) -> None:
        """A request arrived (the watchdog counts silence from here)."""
        with self._lock:
            self._last_request = time.monotonic()
            self._watchdog_tripped = False

    def poll_watchdog(self) -> None:
        """Darken and latch the watchdog bit if the master has been silent too long."""
        with self._lock:
            wd = self._st.watchdog_ms
            if not wd or self._watchdog_tripped:
                return
            if time.monotonic() - self._last_request < wd / 1000.0:
                return
            self._watchdog_tripped = True
            self._st.selected = rm.DARK
            self._st.latched_faults |= rm.FaultBit.WATCHDOG
        self._notify_if_changed()

    def _notify_if_changed(self) -> None:
        with self._lock:
            light, pol = self.light, self.polarization
            last = self._last_light
            if last is not None and last[1] == pol and np.array_equal(last[0], light):
                return
            self._last_light = (light, pol)
            first = last is None
            if not first:
                self.light_changes += 1
        if not first and self.on_light_change is not None:
            self.on_light_change(light.copy(), pol)


def _parse_hostport(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


class LedSphereModbusSim:
    """The LED sphere model served by pymodbus's TCP server and/or RTU server on a socat pty pair.

    ``start()`` / ``stop()`` (or use as a context manager); ``.url`` is what
    :func:`drivers.led_sphere_modbus.open_led_sphere_modbus` opens (``tcp_url`` / ``rtu_url`` for each).
    Fault injection and inspection go through ``.model``.
    """

    def __init__(self, led_count: int, on_light_change: LightCallback | None = None, *,
                 device_id: int = 1, tcp: str | None = "127.0.0.1:0", rtu: bool = False,
                 baudrate: int = 115200, **model_kwargs: object) -> None:
        if tcp is None and not rtu:
            raise ValueError("serve at least one of tcp=HOST:PORT or rtu=True")
        self.model = LedSphereModbusModel(led_count, on_light_change, **model_kwargs)  # type: ignore[arg-type]
        self.device_id = device_id
        self._tcp = _parse_hostport(tcp) if tcp is not None else None
        self._rtu = rtu
        self.baudrate = baudrate
        self.tcp_url: str | None = None
        self.rtu_url: str | None = None
        self.rtu_device: str | None = None          # the master's end of the pty pair
        self.requests_received = 0                  # Modbus request PDUs decoded by either server
        self.packets_received = 0                   # raw receive events (any bytes at all)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[object] = []
        self._watchdog_task: asyncio.Task[None] | None = None
        self._socat: subprocess.Popen[bytes] | None = None
        self._tmpdir: str | None = None

    # Read-only conveniences; fault injection and everything else go through ``.model``.
    @property
    def light(self) -> npt.NDArray[np.float64]:
        return self.model.light

    @property
    def active_slot(self) -> int | None:
        return self.model.active_slot

    @property
    def polarization(self) -> Polarization:
        return self.model.polarization

    def reset(self) -> None:
        """Power-on state of the device (the servers keep running)."""
        self.model.reset()

    @property
    def url(self) -> str:
        url = self.tcp_url or self.rtu_url
        if url is None:
            raise RuntimeError("simulator not started")
        return url

    @property
    def urls(self) -> list[str]:
        return [u for u in (self.tcp_url, self.rtu_url) if u]

    # -- pymodbus glue ---------------------------------------------------------------------------------

    def _sim_device(self) -> SimDevice:
        simdata = [SimData(r.address, values=[0] * r.count, datatype=DataType.REGISTERS,
                           readonly=r.access is rm.Access.R) for r in rm.REGISTERS]
        return SimDevice(self.device_id, simdata=simdata, action=self._action)

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      current_registers: list[int], set_values: list[int] | list[bool] | None
                      ) -> ExcCodes | None:
        """pymodbus calls this before it reads (set_values None) or writes (set_values) registers that
        exist and are writable. A write goes to the model; the written values are replaced by what the
        model reads back (commands read 0); a read refreshes the registers from the model."""
        model = self.model
        model.kick()
        if set_values is not None and function_code not in _READ_FCS:
            code = model.write(address, [int(v) for v in set_values])
            if code is not None:
                return ExcCodes(int(code))
            for i in range(len(set_values)):
                set_values[i] = model.read(address + i)
            return None
        for i in range(count):
            addr = address + i
            if addr in _ADDR:
                current_registers[addr - start_address] = model.read(addr)
        return None

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        if not sending:
            self.packets_received += 1
        return data

    def _trace_pdu(self, sending: bool, pdu):  # type: ignore[no-untyped-def]
        if not sending:
            self.requests_received += 1
        return pdu

    async def _start_servers(self) -> None:
        traces = {"trace_packet": self._trace_packet, "trace_pdu": self._trace_pdu}
        if self._tcp is not None:
            server = ModbusTcpServer(self._sim_device(), address=self._tcp, **traces)
            await server.serve_forever(background=True)
            self._servers.append(server)
            host, port = server.transport.sockets[0].getsockname()[:2]  # type: ignore[union-attr]
            self.tcp_url = f"modbus-tcp://{host}:{port}"
        if self._rtu:
            assert self._tmpdir is not None
            server = ModbusSerialServer(self._sim_device(), port=os.path.join(self._tmpdir, "device"),
                                        baudrate=self.baudrate, reconnect_delay=0.1, **traces)
            await server.serve_forever(background=True)
            self._servers.append(server)
        self._watchdog_task = asyncio.get_running_loop().create_task(self._watchdog())

    async def _watchdog(self) -> None:
        while True:
            await asyncio.sleep(0.01)
            self.model.poll_watchdog()

    async def _stop_servers(self) -> None:
        if self._watchdog_task is not None:
            self._watchdog_task.cancel()
        for server in self._servers:
            await server.shutdown()  # type: ignore[attr-defined]
        self._servers.clear()

    def _start_socat(self) -> None:
        socat = shutil.which("socat")
        if socat is None:
            raise RuntimeError("RTU simulation needs socat (Debian: apt-get install socat)")
        self._tmpdir = tempfile.mkdtemp(prefix="ledsphere-rtu-")
        dev, master = os.path.join(self._tmpdir, "device"), os.path.join(self._tmpdir, "master")
        self._socat = subprocess.Popen(
            [socat, f"pty,raw,echo=0,link={dev}", f"pty,raw,echo=0,link={master}"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 5.0
        while not (os.path.exists(dev) and os.path.exists(master)):
            if self._socat.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("socat did not create the pty pair")
            time.sleep(0.005)
        self.rtu_device = os.path.realpath(master)
        self.rtu_url = f"modbus-rtu://{self.rtu_device}?baudrate={self.baudrate}"

    # -- lifecycle -------------------------------------------------------------------------------------

    def start(self) -> LedSphereModbusSim:
        if self._loop is not None:
            raise RuntimeError("already started")
        try:
            if self._rtu:
                self._start_socat()
            self._loop = asyncio.new_event_loop()
            self._thread = threading.Thread(target=self._loop.run_forever, name="led-sphere-modbus-sim",
                                            daemon=True)
            self._thread.start()
            asyncio.run_coroutine_threadsafe(self._start_servers(), self._loop).result(timeout=10)
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Shut the servers down, stop the loop thread and socat. Idempotent."""
        loop, self._loop = self._loop, None
        if loop is not None:
            if loop.is_running():
                try:
                    asyncio.run_coroutine_threadsafe(self._stop_servers(), loop).result(timeout=5)
                finally:
                    loop.call_soon_threadsafe(loop.stop)
            if self._thread is not None:
                self._thread.join(timeout=5)
            if not loop.is_running():
                loop.close()
        if self._socat is not None:
            self._socat.terminate()
            try:
                self._socat.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self._socat.kill()
                self._socat.wait()
            self._socat = None
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
        self.tcp_url = self.rtu_url = self.rtu_device = None

    def __enter__(self) -> LedSphereModbusSim:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m simulators.led_sphere_modbus",
                                     description="Serve a simulated Modbus LED sphere.")
    parser.add_argument("--tcp", metavar="HOST:PORT", help="serve Modbus TCP (port 0 = any free port)")
    parser.add_argument("--rtu", action="store_true", help="serve Modbus RTU on a socat pty pair")
    parser.add_argument("--leds", type=int, default=120, help="LED count (default 120)")
    parser.add_argument("--slots", type=int, default=64, help="pattern slots (default 64)")
    parser.add_argument("--device-id", type=int, default=1, help="Modbus device (unit/slave) id")
    parser.add_argument("--baudrate", type=int, default=115200)
    args = parser.parse_args(argv)
    if args.tcp is None and not args.rtu:
        parser.error("give --tcp HOST:PORT and/or --rtu")
    sim = LedSphereModbusSim(args.leds, slot_count=args.slots, device_id=args.device_id, tcp=args.tcp,
                             rtu=args.rtu, baudrate=args.baudrate)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with sim:
        for url in sim.urls:
            print(url, flush=True)
        try:
            stop.wait()
        except KeyboardInterrupt:
            pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
