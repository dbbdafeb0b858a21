"""LED sphere over Modbus: the driver against the simulator over Modbus TCP and Modbus RTU (socat pty pair),
the limit and error mapping, and acceptance with Debian's ``mbpoll`` as a third-party master."""
from __future__ import annotations

import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from drivers.contracts import LightSource, Polarization
from drivers.errors import (ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, LimitError,
                            ProtocolError)
from drivers.led_sphere_modbus import LedSphereModbus, open_led_sphere_modbus, parse_modbus_url
from drivers.led_sphere_modbus import registers as rm
from simulators.led_sphere_modbus import LedSphereModbusModel, LedSphereModbusSim

N_LEDS = 100            # > 2 upload windows of 40 LEDs
SOCAT = shutil.which("socat")
MBPOLL = shutil.which("mbpoll")
needs_socat = pytest.mark.skipif(SOCAT is None, reason="socat not installed (Debian: apt-get install socat)")
needs_mbpoll = pytest.mark.skipif(MBPOLL is None, reason="mbpoll not installed (Debian: apt-get install mbpoll)")
TRANSPORTS = ["tcp", pytest.param("rtu", marks=needs_socat)]
LIMITS = {"max_total_current_a": 5.0, "max_mean_duty": 0.6}
ROOT = Path(__file__).resolve().parents[2]


class LightLog:
    def __init__(self) -> None:
        self.events: list[tuple[np.ndarray, Polarization]] = []

    def __call__(self, rgb: np.ndarray, pol: Polarization) -> None:
        self.events.append((rgb, pol))

    @property
    def last(self) -> tuple[np.ndarray, Polarization]:
        assert self.events, "no light change was reported"
        return self.events[-1]


_LOG = LightLog()


@pytest.fixture(scope="module")
def served() -> Iterator[LedSphereModbusSim]:
    with LedSphereModbusSim(N_LEDS, _LOG, slot_count=16, rtu=SOCAT is not None) as sim:
        yield sim


@pytest.fixture
def sim(served: LedSphereModbusSim) -> Iterator[LedSphereModbusSim]:
    """The shared simulator, in its power-on state, with an empty light log; restored afterwards."""
    served.reset()
    _LOG.events.clear()
    yield served
    served.model.max_total_current_a = None
    served.model.commit_busy_s = 0.0
    served.reset()


@pytest.fixture
def log(sim: LedSphereModbusSim) -> LightLog:
    return _LOG


def _url(sim: LedSphereModbusSim, transport: str) -> str:
    url = sim.tcp_url if transport == "tcp" else sim.rtu_url
    assert url is not None
    return url


@pytest.fixture(params=TRANSPORTS)
def driver(request: pytest.FixtureRequest, sim: LedSphereModbusSim) -> Iterator[LedSphereModbus]:
    d = open_led_sphere_modbus(_url(sim, request.param), timeout_s=0.5, **LIMITS)
    yield d
    d.close()


def _pattern(seed: int, scale: int = 20000) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(0, scale, size=(N_LEDS, 3), dtype=np.uint16)


# -- driver vs simulator, both transports ------------------------------------------------------------------

def test_identify_reads_the_identity_block(driver: LedSphereModbus) -> None:
    assert isinstance(driver, LightSource)
    ident = driver.identify()
    assert ident.model == "SSS-LEDSPHERE-MB"
    assert ident.firmware == "1.2"
    assert ident.serial_number == "SIM00001"
    assert ident.extra["slot_count"] == 16 and ident.extra["window_registers"] == rm.WINDOW_REGISTERS
    assert driver.led_count == N_LEDS


def test_upload_then_select_shows_the_pattern(driver: LedSphereModbus, sim: LedSphereModbusSim,
                                              log: LightLog) -> None:
    pattern = _pattern(1)
    driver.upload_pattern(3, pattern)
    np.testing.assert_array_equal(sim.model.slot_pattern(3), pattern)
    assert log.events == [], "uploading to a slot that is not shown must not change the light"
    driver.select_slot(3)
    rgb, pol = log.last
    np.testing.assert_allclose(rgb, pattern / 65535.0)
    assert pol is Polarization.NONE
    status = driver.status()
    assert status.active_slot == 3 and status.lit and status.fault_flags == 0
    assert status.temperature_c == pytest.approx(25.0)
    assert status.current_a == pytest.approx(pattern.sum() / 65535 * 0.02, abs=1e-3)


def test_polarization_and_all_off(driver: LedSphereModbus, sim: LedSphereModbusSim, log: LightLog) -> None:
    driver.upload_pattern(0, _pattern(2))
    driver.select_slot(0)
    driver.set_polarization(Polarization.CROSS)
    assert log.last[1] is Polarization.CROSS and driver.status().polarization is Polarization.CROSS
    driver.all_off()
    rgb, pol = log.last
    assert not rgb.any() and pol is Polarization.CROSS
    status = driver.status()
    assert status.active_slot is None and not status.lit and status.current_a == 0
    n = len(log.events)
    driver.all_off()                       # idempotent: accepted, no light change
    assert len(log.events) == n and sim.active_slot is None


def test_sparse_pattern_sends_only_windows_with_lit_leds(driver: LedSphereModbus,
                                                         sim: LedSphereModbusSim) -> None:
    driver.identify()
    pattern = np.zeros((N_LEDS, 3), np.uint16)
    pattern[85] = (100, 200, 300)                      # third window (LEDs 80-99)
    before = sim.requests_received
    driver.upload_pattern(7, pattern)
    # FC16 [slot, 0, window 0-39], FC16 [80, window 80-99], FC06 commit; the all-zero window 40-79 is skipped
    assert sim.requests_received - before == 3
    np.testing.assert_array_equal(sim.model.slot_pattern(7), pattern)


def test_new_upload_starts_from_an_empty_buffer(driver: LedSphereModbus, sim: LedSphereModbusSim) -> None:
    driver.upload_pattern(1, _pattern(3))
    sparse = np.zeros((N_LEDS, 3), np.uint16)
    sparse[0] = (1, 2, 3)
    driver.upload_pattern(1, sparse)
    np.testing.assert_array_equal(sim.model.slot_pattern(1), sparse)   # nothing left over from before


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pattern=hnp.arrays(np.uint16, (N_LEDS, 3),
                          elements=st.sampled_from([0, 0, 0, 1, 255, 32768, 65535])),
       slot=st.integers(0, 15))
def test_any_pattern_within_limits_arrives_intact(sim: LedSphereModbusSim, pattern: np.ndarray,
                                                  slot: int) -> None:
    with open_led_sphere_modbus(sim.tcp_url or "", timeout_s=0.5, max_total_current_a=100.0,
                                max_mean_duty=1.0) as d:
        d.upload_pattern(slot, pattern)
    np.testing.assert_array_equal(sim.model.slot_pattern(slot), pattern)
    assert sim.model.is_committed(slot)


# -- limits: refused before anything is sent ------------------------------------------------------------------

@pytest.mark.parametrize("transport", TRANSPORTS)
@pytest.mark.parametrize("value, limit", [(60000, "max_total_current_a"), (40000, "max_mean_duty")])
def test_over_limit_pattern_is_refused_and_nothing_is_sent(sim: LedSphereModbusSim, transport: str,
                                                           value: int, limit: str) -> None:
    # 100 LEDs x 3 x 60000/65535 x 0.02 A = 5.49 A > 5 A; 40000/65535 = 0.61 mean duty > 0.6 (and 3.66 A)
    d = open_led_sphere_modbus(_url(sim, transport), timeout_s=0.5, **LIMITS)
    try:
        before = sim.packets_received
        with pytest.raises(LimitError, match=limit) as info:
            d.upload_pattern(0, np.full((N_LEDS, 3), value, np.uint16))
        assert isinstance(info.value, ValueError)
        time.sleep(0.05)
        assert sim.packets_received == before, "a refused pattern must not put a byte on the wire"
        assert not sim.model.is_committed(0)
    finally:
        d.close()


def test_slot_out_of_range_is_refused_without_a_write(driver: LedSphereModbus, sim: LedSphereModbusSim) -> None:
    driver.identify()
    before = sim.packets_received
    with pytest.raises(LimitError):
        driver.select_slot(16)
    with pytest.raises(LimitError):
        driver.upload_pattern(-1, np.zeros((N_LEDS, 3), np.uint16))
    with pytest.raises(ValueError, match="100"):
        driver.upload_pattern(0, np.zeros((N_LEDS - 1, 3), np.uint16))
    assert sim.packets_received == before


# -- Modbus exception codes -> typed errors --------------------------------------------------------------------

def test_exception_2_illegal_address(driver: LedSphereModbus) -> None:
    with pytest.raises(DeviceRejected) as info:
        driver.read_registers(50, 1)                     # between the identity and status blocks
    assert info.value.code == 2 and info.value.name == "ILLEGAL_DATA_ADDRESS"
    assert not isinstance(info.value, DeviceBusy)
    with pytest.raises(DeviceRejected) as info:
        driver.write_registers(rm.reg("LED_COUNT").address, [5])   # read-only register
    assert info.value.code == 2


def test_exception_3_illegal_value(driver: LedSphereModbus, sim: LedSphereModbusSim) -> None:
    with pytest.raises(DeviceRejected) as info:
        driver.select_slot(4)                            # in range, but never committed
    assert info.value.code == 3 and info.value.name == "ILLEGAL_DATA_VALUE"
    with pytest.raises(DeviceRejected) as info:
        driver.write_registers(rm.reg("POLARIZATION").address, [7])
    assert info.value.code == 3
    sim.model.max_total_current_a = 0.5                  # the device's own limit, tighter than the driver's
    with pytest.raises(DeviceRejected) as info:
        driver.upload_pattern(2, _pattern(4))            # ~1.8 A: refused at commit
    assert info.value.code == 3 and not sim.model.is_committed(2)


def test_exception_4_over_temperature(driver: LedSphereModbus, sim: LedSphereModbusSim, log: LightLog) -> None:
    driver.upload_pattern(5, _pattern(5))
    driver.select_slot(5)
    sim.model.set_temperature_c(72.5)
    assert not log.last[0].any(), "over-temperature must darken the LEDs"
    status = driver.status()
    assert status.over_temperature and status.fault_flags & rm.FaultBit.OVER_TEMPERATURE
    assert status.temperature_c == pytest.approx(72.5) and status.active_slot is None
    with pytest.raises(DeviceRejected) as info:
        driver.select_slot(5)
    assert info.value.code == 4
    sim.model.set_temperature_c(None)
    driver.select_slot(5)
    assert driver.status().fault_flags == 0 and log.last[0].any()


def test_exception_6_busy_maps_to_device_busy(driver: LedSphereModbus, sim: LedSphereModbusSim) -> None:
    sim.model.commit_busy_s = 0.6
    driver.upload_pattern(6, _pattern(6))
    with pytest.raises(DeviceBusy) as info:
        driver.select_slot(6)
    assert info.value.code == 6 and isinstance(info.value, DeviceRejected)
    assert driver.read_registers(rm.reg("BUSY").address, 1) == [1]
    driver.all_off()                                     # always accepted, also when busy
    deadline = time.monotonic() + 3.0
    while driver.read_registers(rm.reg("BUSY").address, 1) == [1]:
        assert time.monotonic() < deadline, "BUSY never cleared"
        time.sleep(0.02)
    driver.select_slot(6)
    assert sim.active_slot == 6
    sim.model.force_busy = True
    with pytest.raises(DeviceBusy):
        driver.upload_pattern(6, _pattern(7))


def test_rejected_fc16_changes_nothing(driver: LedSphereModbus) -> None:
    driver.write_registers(rm.reg("UPLOAD_SLOT").address, [2, 0, 9, 9, 9])
    assert driver.read_registers(rm.reg("STAGED_LEDS").address, 1) == [1]
    # slot 3, offset 90, 40 LEDs: LEDs 100-129 do not exist -> the whole request is refused
    with pytest.raises(DeviceRejected) as info:
        driver.write_registers(rm.reg("UPLOAD_SLOT").address, [3, 90] + [1] * rm.WINDOW_REGISTERS)
    assert info.value.code == 3
    assert driver.read_registers(rm.reg("UPLOAD_SLOT").address, 2) == [2, 0]
    assert driver.read_registers(rm.reg("STAGED_LEDS").address, 1) == [1]
    assert driver.read_registers(rm.reg("UPLOAD_WINDOW").address, 3) == [9, 9, 9]


def test_watchdog_darkens_a_silent_master(driver: LedSphereModbus, sim: LedSphereModbusSim,
                                          log: LightLog) -> None:
    driver.upload_pattern(0, _pattern(8))
    driver.select_slot(0)
    driver.set_watchdog(0.5)
    for _ in range(5):                                   # polling faster than the watchdog keeps it lit
        time.sleep(0.05)
        assert driver.status().lit
    time.sleep(1.0)
    assert not log.last[0].any()
    status = driver.status()
    assert status.fault_flags == rm.FaultBit.WATCHDOG and status.active_slot is None
    driver.clear_faults(rm.FaultBit.WATCHDOG)
    assert driver.status().fault_flags == 0
    driver.set_watchdog(0)


# -- no answer, no connection ----------------------------------------------------------------------------------

def test_no_answer_over_tcp_is_a_device_timeout() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]
    conns: list[socket.socket] = []
    threading.Thread(target=lambda: conns.append(listener.accept()[0]), daemon=True).start()
    try:
        d = open_led_sphere_modbus(f"modbus-tcp://127.0.0.1:{port}", timeout_s=0.2, **LIMITS)
        t0 = time.monotonic()
        with pytest.raises(DeviceTimeout) as info:
            d.status()
        assert isinstance(info.value, TimeoutError)
        assert time.monotonic() - t0 < 3.0
        d.close()
    finally:
        listener.close()
        for c in conns:
            c.close()


@needs_socat
def test_no_answer_over_rtu_is_a_device_timeout(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    proc = subprocess.Popen([SOCAT or "socat", f"pty,raw,echo=0,link={a}", f"pty,raw,echo=0,link={b}"],
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 5
        while not (a.exists() and b.exists()):
            assert time.monotonic() < deadline, "socat did not start"
            time.sleep(0.01)
        with open_led_sphere_modbus(f"modbus-rtu://{b}?baudrate=115200", timeout_s=0.2, **LIMITS) as d:
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeout):
                d.identify()
            assert time.monotonic() - t0 < 3.0
    finally:
        proc.terminate()
        proc.wait()


def test_connection_failures_are_connection_lost(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]                        # bound, not listening: connection refused
        with pytest.raises(ConnectionLost, match=str(port)) as info:
            open_led_sphere_modbus(f"modbus-tcp://127.0.0.1:{port}", timeout_s=0.2, **LIMITS)
        assert isinstance(info.value, ConnectionError)
    with pytest.raises(ConnectionLost, match="nonexistent"):
        open_led_sphere_modbus(f"modbus-rtu://{tmp_path}/nonexistent", timeout_s=0.2, **LIMITS)


def test_server_going_away_is_connection_lost() -> None:
    sim = LedSphereModbusSim(4).start()
    try:
        d = open_led_sphere_modbus(sim.url, timeout_s=0.3, **LIMITS)
        assert d.led_count == 4
    finally:
        sim.stop()
    with pytest.raises((ConnectionLost, DeviceTimeout)) as info:
        d.status()
    assert isinstance(info.value, ConnectionLost), f"expected ConnectionLost, got {info.value!r}"
    d.close()


def test_other_device_id_is_refused_by_the_simulator(sim: LedSphereModbusSim) -> None:
    """pymodbus's server answers an unknown device id with exception 4 (a real device on RS-485 would stay
    silent, which the driver reports as DeviceTimeout); either way nothing is changed."""
    with open_led_sphere_modbus(sim.tcp_url or "", device_id=7, timeout_s=0.5, **LIMITS) as d:
        with pytest.raises(DeviceRejected) as info:
            d.all_off()
    assert info.value.code == 4


def test_wrong_reply_is_a_protocol_error() -> None:
    """A reply whose transaction id does not match the request: pymodbus raises, the driver maps it."""
    from pymodbus.exceptions import ModbusIOException

    class Client:
        closed = 0

        def read_holding_registers(self, address: int, *, count: int, device_id: int) -> None:
            raise ModbusIOException("ERROR: request uses transaction id=3 but received 2.")

        def close(self) -> None:
            Client.closed += 1

    d = LedSphereModbus(Client(), timeout_s=0.5, **LIMITS)  # type: ignore[arg-type]
    with pytest.raises(ProtocolError):
        d.status()
    assert Client.closed == 1, "the connection is dropped so that the stale reply cannot be misread"


# -- URLs, the model without I/O, the command line ---------------------------------------------------------------

@pytest.mark.parametrize("url, expected", [
    ("modbus-tcp://127.0.0.1:5020", ("tcp", "127.0.0.1", 5020, "", 115200)),
    ("modbus-tcp://sphere.local", ("tcp", "sphere.local", 502, "", 115200)),
    ("modbus-rtu:///dev/pts/3?baudrate=115200", ("rtu", "", 502, "/dev/pts/3", 115200)),
    ("modbus-rtu:///dev/ttyUSB0?baudrate=19200&parity=E", ("rtu", "", 502, "/dev/ttyUSB0", 19200)),
])
def test_url_parsing(url: str, expected: tuple[object, ...]) -> None:
    u = parse_modbus_url(url)
    assert (u.kind, u.host, u.port, u.device, u.baudrate) == expected


@pytest.mark.parametrize("url", ["tcp://127.0.0.1:502", "modbus-rtu://dev/ttyUSB0", "modbus-tcp://:5020",
                                 "modbus-rtu:///dev/ttyS0?baud=9600", "modbus-rtu:///dev/ttyS0?parity=X",
                                 "modbus-tcp://h:99999"])
def test_bad_urls_are_refused(url: str) -> None:
    with pytest.raises(ValueError):
        parse_modbus_url(url)


def test_model_window_reads_back_the_buffer_at_the_offset() -> None:
    m = LedSphereModbusModel(50, slot_count=2)
    win = rm.reg("UPLOAD_WINDOW").address
    assert m.write(rm.reg("UPLOAD_SLOT").address, [1, 45, 1, 2, 3, 4, 5, 6]) is None
    assert [m.read(win + i) for i in range(6)] == [1, 2, 3, 4, 5, 6]
    assert m.read(win + 15) == 0                        # LED 50 does not exist: reads 0
    assert m.write(win + 15, [1]) == rm.ExceptionCode.ILLEGAL_DATA_VALUE
    assert m.write(rm.reg("UPLOAD_OFFSET").address, [0]) is None
    assert m.read(win) == 0 and m.read(rm.reg("STAGED_LEDS").address) == 2


def test_simulator_command_line_prints_a_working_url() -> None:
    proc = subprocess.Popen([sys.executable, "-m", "simulators.led_sphere_modbus", "--tcp", "127.0.0.1:0",
                             "--leds", "12"], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().strip()
        assert re.fullmatch(r"modbus-tcp://127\.0\.0\.1:\d+", url), url
        with open_led_sphere_modbus(url, timeout_s=1.0, **LIMITS) as d:
            assert d.led_count == 12
    finally:
        proc.terminate()
        assert proc.wait(timeout=10) == 0


# -- acceptance: Debian's mbpoll as the master -----------------------------------------------------------------

def _mbpoll_target(sim: LedSphereModbusSim, transport: str) -> list[str]:
    if transport == "tcp":
        assert sim.tcp_url is not None
        host, port = sim.tcp_url.removeprefix("modbus-tcp://").rsplit(":", 1)
        return ["-m", "tcp", host, "-p", port]
    assert sim.rtu_device is not None
    return ["-m", "rtu", "-b", "115200", "-P", "none", sim.rtu_device]


def mbpoll(sim: LedSphereModbusSim, transport: str, *args: str, ok: bool = True) -> subprocess.CompletedProcess[str]:
    """Run ``mbpoll -a 1 OPTIONS TARGET [VALUES]``; ``args`` = OPTIONS [``"--values"``, VALUES...]."""
    opts, values = list(args), []
    if "--values" in opts:
        i = opts.index("--values")
        opts, values = opts[:i], opts[i + 1:]
    cmd = [MBPOLL or "mbpoll", "-a", "1", *opts, *_mbpoll_target(sim, transport), *values]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=15)
    if ok:
        assert out.returncode == 0, f"{' '.join(cmd)}\n{out.stdout}\n{out.stderr}"
    return out


def _values(stdout: str) -> dict[int, int]:
    """mbpoll's ``[ref]: value`` lines -> {ref: value} (hex or decimal)."""
    return {int(ref): int(val, 0) for ref, val in re.findall(r"^\[(\d+)\]:\s+(0x[0-9A-Fa-f]+|-?\d+)", stdout,
                                                             flags=re.M)}


@needs_mbpoll
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_mbpoll_reads_identity_and_status(sim: LedSphereModbusSim, transport: str) -> None:
    ident = _values(mbpoll(sim, transport, "-r", "1", "-c", "19", "-t", "4:hex", "-1").stdout)
    assert sorted(ident) == list(range(1, 20)), "mbpoll numbers references from 1"
    assert rm.decode_ascii([ident[r] for r in range(1, 9)]) == "SSS-LEDSPHERE-MB"
    assert (ident[9], ident[10], ident[11], ident[12], ident[13], ident[14], ident[15]) == (
        1, 2, rm.PROTOCOL_VERSION, N_LEDS, 3, 16, rm.WINDOW_REGISTERS)
    assert rm.decode_ascii([ident[r] for r in range(16, 20)]) == "SIM00001"
    # status with -0: the reference is the PDU address; FC03 and FC04 (-t 3) give the same values
    for table in ("4", "3"):
        status = _values(mbpoll(sim, transport, "-0", "-r", "100", "-c", "8", "-t", table, "-1").stdout)
        assert sorted(status) == list(range(100, 108))
        assert status[100] == 2500 and status[101] == 0 and status[102] == 0
        assert status[103] == rm.DARK and status[105] == 0


@needs_mbpoll
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_mbpoll_uploads_and_switches_a_pattern(sim: LedSphereModbusSim, transport: str, log: LightLog) -> None:
    # FC16 at address 300 (reference 301): slot 5, offset 0, LED0 red, LED1 green, LED2 blue, LED3 white/2
    leds = [65535, 0, 0, 0, 65535, 0, 0, 0, 65535, 32768, 32768, 32768]
    out = mbpoll(sim, transport, "-r", "301", "--values", "5", "0", *map(str, leds))
    assert "Written 14 references" in out.stdout
    assert _values(mbpoll(sim, transport, "-0", "-r", "106", "-1").stdout) == {106: 4}   # STAGED_LEDS
    mbpoll(sim, transport, "-r", "423", "--values", "1")                                 # commit
    assert log.events == []
    mbpoll(sim, transport, "-r", "201", "--values", "5")                                 # SELECT_SLOT = 5
    rgb, pol = log.last
    expected = np.zeros((N_LEDS, 3))
    expected[:4] = np.array(leds).reshape(4, 3) / 65535.0
    np.testing.assert_allclose(rgb, expected)
    assert sim.active_slot == 5 and pol is Polarization.NONE
    status = _values(mbpoll(sim, transport, "-r", "101", "-c", "8", "-1").stdout)
    assert status[104] == 5 and status[106] == 1                 # ACTIVE_SLOT, LIT (1-based references)
    assert status[102] == round((3 + 3 * 32768 / 65535) * 20)   # CURRENT in mA
    mbpoll(sim, transport, "-r", "202", "--values", "2")         # POLARIZATION = cross
    assert log.last[1] is Polarization.CROSS
    mbpoll(sim, transport, "-r", "201", "--values", "65535")     # SELECT_SLOT = dark
    assert not log.last[0].any() and sim.active_slot is None


@needs_mbpoll
@pytest.mark.parametrize("transport", TRANSPORTS)
def test_mbpoll_sees_exception_responses(sim: LedSphereModbusSim, transport: str) -> None:
    out = mbpoll(sim, transport, "-r", "201", "--values", "9", ok=False)      # slot 9 never committed
    assert out.returncode != 0 and "Illegal data value" in out.stderr
    out = mbpoll(sim, transport, "-r", "51", "-1", ok=False)                  # unmapped address 50
    assert out.returncode != 0 and "Illegal data address" in out.stderr
    out = mbpoll(sim, transport, "-r", "12", "--values", "7", ok=False)       # LED_COUNT is read-only
    assert out.returncode != 0 and "Illegal data address" in out.stderr
    assert sim.active_slot is None and sim.model.led_count == N_LEDS
