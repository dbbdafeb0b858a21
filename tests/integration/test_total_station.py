"""Total station: geocompy and our TotalStationFeed against the GeoCOM simulator over TCP and a pty.

geocompy's ``GeoCom`` sleeps about 1 s while connecting, so each transport connects once per module.
"""
from __future__ import annotations

import math
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest
import serial
from geocompy.communication import SerialConnection
from geocompy.geo import GeoCom
from geocompy.geo.gctypes import GeoComCode

from drivers.contracts import PositionFeed, SurveyedPoint
from drivers.errors import ConnectionLost, DeviceBusy, DeviceRejected, DeviceTimeout, ProtocolError
from drivers.total_station import TotalStationFeed, codec, open_total_station
from simulators.serve import serve
from simulators.total_station import GeoComModel

REPO = Path(__file__).resolve().parents[2]

TRUTH = {
    "north": (0.0, 900.0, 0.0),
    "east": (700.0, 200.0, 150.0),
    "west": (-650.0, 150.0, -200.0),
    "top": (0.0, 300.0, 700.0),
}
STATION = (200.0, -2500.0, 300.0)
YAW_DEG = 25.0
# what the rig config knows: a few mm off the truth (ATR fine-points the rest)
APPROX = {name: (x + 2.0, y - 3.0, z + 1.5) for name, (x, y, z) in TRUTH.items()}
NOISE_MM = 0.3
ANGLE_NOISE_RAD = 2.4e-6


def sigma_mm(target: str) -> float:
    """1-sigma 3D error: slope-distance noise plus two angular components at the target's range."""
    d = math.dist(TRUTH[target], STATION)
    return math.sqrt(NOISE_MM ** 2 + 2 * (ANGLE_NOISE_RAD * d) ** 2)


def assert_near_truth(point: SurveyedPoint, target: str) -> None:
    err = math.dist(point.xyz_mm, TRUTH[target])
    assert err <= 3 * sigma_mm(target), f"{target}: {point.xyz_mm} is {err:.3f} mm from {TRUTH[target]}"


def make_model(**kw) -> GeoComModel:
    return GeoComModel(TRUTH, STATION, YAW_DEG, noise_mm=NOISE_MM, angle_noise_rad=ANGLE_NOISE_RAD, **kw)


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def tcp_rig():
    """geocompy's own GeoCom over socket:// to the simulator, wrapped by TotalStationFeed."""
    model = make_model(seed=1, instrument_station_enh_m=(1000.0, 5000.0, 250.0), instrument_height_m=1.6,
                       reflector_height_m=0.05)
    server = serve(model, "tcp://127.0.0.1:0")
    port = serial.serial_for_url(server.url, timeout=1.0)
    conn = SerialConnection(port)
    geocom = GeoCom(conn)
    connect_rpcs = [r.rpc for r in model.requests]
    feed = TotalStationFeed(geocom, station_xyz_mm=STATION, station_yaw_deg=YAW_DEG, targets=APPROX,
                            timeout_s=1.0, edm_wait_s=0.2, connection=conn)
    yield SimpleNamespace(model=model, server=server, conn=conn, geocom=geocom, feed=feed,
                          connect_rpcs=connect_rpcs)
    feed.close()
    server.close()


@pytest.fixture(scope="module")
def pty_rig():
    """Our factory over a pty, with CRC-16 checksums on every frame."""
    model = make_model(seed=2, checksum=True)
    server = serve(model, "pty")
    feed = open_total_station(server.url, station_xyz_mm=STATION, station_yaw_deg=YAW_DEG, targets=APPROX,
                              checksum=True, timeout_s=1.0, edm_wait_s=0.2)
    yield SimpleNamespace(model=model, server=server, feed=feed)
    feed.close()
    server.close()


@pytest.fixture
def tcp(tcp_rig):
    tcp_rig.model.reset()
    tcp_rig.server.faults.clear()
    yield tcp_rig
    tcp_rig.server.faults.clear()
    tcp_rig.model.clear_faults()


@pytest.fixture
def pty(pty_rig):
    pty_rig.model.reset()
    yield pty_rig
    pty_rig.model.clear_faults()


# ------------------------------------------------------------------- acceptance: geocompy <-> simulator
def test_geocompy_connect_sequence_is_answered(tcp_rig):
    assert tcp_rig.connect_rpcs == [0, 108, 5004, 5003, 110, 5034]
    assert tcp_rig.geocom.precision == 15


def test_geocompy_reads_coordinates_over_tcp(tcp):
    g, model = tcp.geocom, tcp.model
    hz, v, d = model.true_angles("east")
    assert g.aut.turn_to(hz, v).error == GeoComCode.OK
    assert g.tmc.do_measurement().error == GeoComCode.OK
    resp = g.tmc.get_coordinate()
    assert resp.error == GeoComCode.OK
    coord, _t, coord_cont, _tc = resp.params
    tol_m = 3 * sigma_mm("east") / 1000
    assert (coord.x, coord.y, coord.z) == pytest.approx(model.true_enh("east"), abs=tol_m)
    assert (coord_cont.x, coord_cont.y, coord_cont.z) == pytest.approx((coord.x, coord.y, coord.z))
    simple = g.tmc.get_simple_measurement()
    assert simple.error == GeoComCode.OK
    assert float(simple.params[0]) == pytest.approx(hz, abs=1e-4)
    assert float(simple.params[1]) == pytest.approx(v, abs=1e-4)
    assert simple.params[2] == pytest.approx(d, abs=3 * NOISE_MM / 1000)


def test_geocompy_angles_abort_and_unknown_rpc(tcp):
    g = tcp.geocom
    hz, v, _ = tcp.model.true_angles("north")
    assert g.aut.turn_to(hz, v).error == GeoComCode.OK
    angles = g.tmc.get_angle_inclination()
    assert angles.error == GeoComCode.OK and len(angles.params) == 9
    assert float(angles.params[0]) == pytest.approx(hz, abs=1e-4)
    assert float(angles.params[1]) == pytest.approx(v, abs=1e-4)
    assert g.abort().error == GeoComCode.OK                   # "c" answered with "?"
    assert g.request(12345).error == GeoComCode.COM_PROC_UNAVAIL
    assert g.com.nullprocess().error == GeoComCode.OK          # still in step afterwards


def test_geocompy_reads_coordinates_over_pty_with_checksums(pty):
    g, model = pty.feed.geocom, pty.model
    hz, v, _ = model.true_angles("top")
    with pty.feed.lock:
        assert g.aut.turn_to(hz, v).error == GeoComCode.OK
        assert g.tmc.do_measurement().error == GeoComCode.OK
        resp = g.tmc.get_coordinate()
    assert resp.error == GeoComCode.OK
    coord = resp.params[0]
    assert (coord.x, coord.y, coord.z) == pytest.approx(model.true_enh("top"), abs=3 * sigma_mm("top") / 1000)
    assert model.requests and all(r.crc is not None for r in model.requests)


# --------------------------------------------------------------------------------------- the feed
def test_feed_satisfies_position_feed(tcp):
    assert isinstance(tcp.feed, PositionFeed)


def test_identify(tcp):
    ident = tcp.feed.identify()
    assert (ident.kind, ident.model, ident.serial_number, ident.firmware) == ("total_station", "TS60", "123456",
                                                                             "4.20.0")
    assert ident.extra["geocom_version"] == "1.50.0"


@pytest.mark.parametrize("target", sorted(TRUTH))
def test_measure_targets_within_three_sigma_over_tcp(tcp, target):
    point = tcp.feed.measure(target)
    assert point.name == target and point.warning is None
    assert_near_truth(point, target)
    rpcs = [r.rpc for r in tcp.model.requests]
    assert rpcs[-3:] == [9027, 2008, 2082]
    assert codec.parse_int(tcp.model.requests[-3].params[3]) == 1     # ATR fine-pointing requested


def test_instrument_station_setup_is_removed(tcp):
    tcp.feed.measure("north")
    assert tcp.feed.instrument_origin_enh_m == pytest.approx((1000.0, 5000.0, 250.0 + 1.6 - 0.05))


@pytest.mark.parametrize("target", ["north", "west"])
def test_measure_over_pty_with_checksums(pty, target):
    point = pty.feed.measure(target)
    assert_near_truth(point, target)
    assert all(r.crc is not None for r in pty.model.requests)


@pytest.mark.parametrize(("code", "name"), [(1283, "TMC_NO_FULL_CORRECTION"), (1284, "TMC_ACCURACY_GUARANTEE")])
def test_warning_codes_give_a_usable_point(tcp, code, name):
    tcp.model.next_return_code(code, rpc=2082)
    point = tcp.feed.measure("east")
    assert point.warning == name
    assert_near_truth(point, "east")
    assert tcp.feed.measure("east").warning is None            # one-shot


def test_warnings_from_several_steps_are_all_reported(tcp):
    tcp.model.next_return_code(1283, rpc=2008)
    tcp.model.next_return_code(1284, rpc=2082)
    point = tcp.feed.measure("west")
    assert point.warning == "TMC_NO_FULL_CORRECTION, TMC_ACCURACY_GUARANTEE"
    assert_near_truth(point, "west")


@pytest.mark.parametrize(("rpc", "code", "name", "busy"), [
    (2082, 1292, "TMC_DIST_ERROR", False),
    (2082, 1290, "TMC_ANGLE_ERROR", False),
    (2082, 1285, "TMC_ANGLE_OK", False),          # angles only: no distance, not usable
    (9027, 8710, "AUT_NO_TARGET", False),
    (2008, 26, "NOTOK", False),
    (2082, 4242, "GRC_4242", False),              # unknown to geocompy (it says UNDEFINED); number recovered
    (2082, 1293, "TMC_BUSY", True),
    (9027, 1793, "MOT_BUSY", True),
])
def test_error_codes_raise_device_rejected(tcp, rpc, code, name, busy):
    tcp.model.next_return_code(code, rpc=rpc)
    with pytest.raises(DeviceRejected) as info:
        tcp.feed.measure("north")
    assert info.value.code == code and info.value.name == name
    assert isinstance(info.value, DeviceBusy) is busy
    assert_near_truth(tcp.feed.measure("north"), "north")   # the next measurement works again


def test_no_reflector_in_view(tcp):
    ghost = {"ghost": (-900.0, 1200.0, -500.0)}        # no reflector within a few mrad of this direction
    common = dict(station_xyz_mm=STATION, station_yaw_deg=YAW_DEG, targets=ghost, timeout_s=1.0,
                  edm_wait_s=0.2, connection=tcp.conn)
    with pytest.raises(DeviceRejected) as info:
        TotalStationFeed(tcp.geocom, use_atr=False, **common).measure("ghost")
    assert (info.value.code, info.value.name) == (1292, "TMC_DIST_ERROR")
    with pytest.raises(DeviceRejected) as info:
        TotalStationFeed(tcp.geocom, use_atr=True, **common).measure("ghost")
    assert (info.value.code, info.value.name) == (8710, "AUT_NO_TARGET")


def test_unknown_target_lists_known_targets_and_sends_nothing(tcp):
    before = len(tcp.model.requests)
    with pytest.raises(ValueError) as info:
        tcp.feed.measure("sphere")
    assert all(name in str(info.value) for name in TRUTH)
    assert len(tcp.model.requests) == before


def test_muted_simulator_raises_device_timeout_then_recovers(tcp):
    tcp.server.faults.mute = True
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout):
        tcp.feed.measure("top")
    assert time.monotonic() - t0 < 3.0
    tcp.server.faults.mute = False
    assert_near_truth(tcp.feed.measure("top"), "top")


def test_garbled_reply_raises_protocol_error_then_recovers(tcp):
    tcp.server.faults.garbage = b"%R1P,garbage\r\n"
    with pytest.raises(ProtocolError):
        tcp.feed.measure("east")
    assert_near_truth(tcp.feed.measure("east"), "east")


def test_split_replies_are_reassembled(tcp):
    tcp.server.faults.split_at = 7
    tcp.server.faults.split_gap_s = 0.0005
    assert_near_truth(tcp.feed.measure("west"), "west")


def test_threads_share_one_feed(tcp):
    results: dict[str, list[SurveyedPoint]] = {"north": [], "top": []}
    errors: list[BaseException] = []

    def worker(target: str) -> None:
        try:
            for _ in range(3):
                results[target].append(tcp.feed.measure(target))
        except BaseException as exc:   # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(t,)) for t in results]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert not errors
    for target, points in results.items():
        assert len(points) == 3
        for point in points:
            assert_near_truth(point, target)


# --------------------------------------------------------------------------------- factory errors
def test_factory_refuses_silent_port():
    model = make_model()
    with serve(model, "tcp://127.0.0.1:0") as server:
        server.faults.mute = True
        with pytest.raises(DeviceTimeout):
            open_total_station(server.url, station_xyz_mm=STATION, targets=APPROX, timeout_s=0.2,
                               connect_attempts=1)


def test_factory_unreachable_url_is_connection_lost():
    with pytest.raises(ConnectionLost):
        open_total_station("/dev/does-not-exist-ts", station_xyz_mm=STATION, targets=APPROX, timeout_s=0.2)


# ------------------------------------------------------------------------------ feed without I/O
class _StubConnection:
    def __init__(self) -> None:
        self.closed = 0

    def close(self) -> None:
        self.closed += 1


def test_closed_feed_raises_connection_lost_and_close_is_idempotent():
    conn = _StubConnection()
    feed = TotalStationFeed(object(), station_xyz_mm=STATION, targets=APPROX, connection=conn)
    feed.close()
    feed.close()
    assert conn.closed == 1
    with pytest.raises(ConnectionLost):
        feed.measure("north")
    with pytest.raises(ConnectionLost):
        feed.identify()


def test_constructor_validates_without_io():
    for bad in (dict(targets={}), dict(targets=APPROX, timeout_s=0), dict(targets={"a": (1.0, 2.0)}),
                dict(targets={"a": (1.0, 2.0, float("nan"))})):
        with pytest.raises(ValueError):
            TotalStationFeed(object(), station_xyz_mm=STATION, **bad)


def test_aim_angles_follow_the_frame_convention():
    # yaw 0: a target straight along rig +y from the station is due north and level
    feed = TotalStationFeed(object(), station_xyz_mm=(0.0, 0.0, 0.0), targets={"n": (0.0, 3000.0, 0.0),
                            "e_up": (3000.0, 0.0, 3000.0)})
    assert feed.aim_angles("n") == pytest.approx((0.0, math.pi / 2))
    assert feed.aim_angles("e_up") == pytest.approx((math.pi / 2, math.pi / 4))
    # yaw 90: the instrument's E axis points along rig +y
    feed90 = TotalStationFeed(object(), station_xyz_mm=(0.0, 0.0, 0.0), station_yaw_deg=90.0,
                              targets={"y": (0.0, 3000.0, 0.0)})
    assert feed90.aim_angles("y") == pytest.approx((math.pi / 2, math.pi / 2))


# --------------------------------------------------------------------------- simulator, sans-IO
def test_simulator_answers_connect_sequence_byte_exact():
    model = make_model()
    assert model.receive(b"\n\r\n") == b""
    exchanges = [
        (b"%R1Q,0,0:\r\n", b"%R1P,0,0:0\r\n"),
        (b"%R1Q,108,1:\r\n", b"%R1P,0,1:0,15\r\n"),
        (b"%R1Q,5004,2:\r\n", b'%R1P,0,2:0,"TS60"\r\n'),
        (b"%R1Q,5003,3:\r\n", b"%R1P,0,3:0,123456\r\n"),
        (b"%R1Q,110,4:\r\n", b"%R1P,0,4:0,1,50,0\r\n"),
        (b"%R1Q,5034,5:\r\n", b"%R1P,0,5:0,4,20,0\r\n"),
        (b"c\r\n", b"?\r\n"),
        (b"%R1Q,0,32767:\r\n", b"%R1P,0,32767:0\r\n"),             # transaction id echoed
        (b"%R1Q,0:\r\n", b"%R1P,0,0:0\r\n"),                       # omitted id -> 0
        (b"%R1Q,31337,6:\r\n", b"%R1P,3081,6:0\r\n"),              # unknown RPC
        (b"%R1Q,2008,7:1\r\n", b"%R1P,0,7:2\r\n"),                 # wrong parameter count -> IVPARAM
        (b"%R1Q,oops\r\n", b"%R1P,3080,0:0\r\n"),                  # undecodable request
        (b"%R1Q,0,8,1:\r\n", b"%R1P,3101,8," + str(codec.crc16_arc("%R1P,3101,8:0")).encode() + b":0\r\n"),
    ]
    for request, reply in exchanges:
        assert model.receive(request) == reply, request


def test_simulator_buffers_partial_lines():
    whole, split = make_model(), make_model()
    stream = b"%R1Q,0,1:\r\n%R1Q,5004,2:\r\n%R1Q,108,3:\r\n"
    expected = whole.receive(stream)
    got = b"".join(split.receive(stream[i:i + 1]) for i in range(len(stream)))
    assert got == expected and expected.count(b"\r\n") == 3


def test_simulator_checksum_mode():
    model = make_model(checksum=True)
    assert model.receive(b"%R1Q,0,4:\r\n") == b"%R1P,3110,4," + str(codec.crc16_arc("%R1P,3110,4:0")).encode() \
        + b":0\r\n"
    reply = codec.decode_reply(model.receive(codec.encode_request(5004, trid=9, checksum=True)), require_crc=True)
    assert (reply.trid, reply.rc, codec.parse_str(reply.params[0])) == (9, 0, "TS60")


def _shoot(model: GeoComModel, hz: float, v: float, atr: int = 0) -> codec.Reply:
    model.receive(codec.encode_request(9027, (hz, v, 0, atr, 0), trid=1))
    model.receive(codec.encode_request(2008, (1, 1), trid=2))
    return codec.decode_reply(model.receive(codec.encode_request(2108, (100, 1), trid=3)))


def test_simulator_measures_the_nearest_reflector_within_acceptance():
    model = make_model(seed=3)
    hz, v, d = model.true_angles("west")
    near = _shoot(model, hz + 2e-3, v)          # 2 mrad off: the EDM still returns from the reflector
    assert near.rc == 0 and codec.parse_float(near.params[2]) == pytest.approx(d, abs=0.002)
    assert codec.parse_float(near.params[0]) == pytest.approx(hz + 2e-3, abs=1e-4)   # no ATR: aim angles
    far = _shoot(model, hz + 2e-2, v)           # 20 mrad off: no reflector
    assert far.rc == codec.TMC_DIST_ERROR and far.params == ()
    snapped = _shoot(model, hz + 2e-3, v, atr=1)
    assert codec.parse_float(snapped.params[0]) == pytest.approx(hz, abs=1e-4)    # ATR fine-pointed


def test_simulator_noise_is_seeded_and_reset_restores_state():
    hz, v, _ = make_model().true_angles("north")
    a, b, c = make_model(seed=5), make_model(seed=5), make_model(seed=6)
    first = _shoot(a, hz, v, 1).params
    assert first == _shoot(b, hz, v, 1).params
    assert first != _shoot(c, hz, v, 1).params
    a.next_return_code(1293)
    a.receive(b"%R1Q,0")                                     # half a line in the buffer
    a.reset()
    assert a.receive(b"%R1Q,0,1:\r\n") == b"%R1P,0,1:0\r\n"  # no stale bytes, no pending fault
    assert _shoot(a, hz, v, 1).params == first                # same seed -> same noise again


def test_simulator_fault_hook_respects_rpc_and_count():
    model = make_model()
    model.next_return_code(1293, rpc=2008, count=2)
    assert model.receive(b"%R1Q,0,1:\r\n") == b"%R1P,0,1:0\r\n"       # other RPCs unaffected
    assert model.receive(b"%R1Q,2008,2:1,1\r\n") == b"%R1P,0,2:1293\r\n"
    assert model.receive(b"%R1Q,2008,3:1,1\r\n") == b"%R1P,0,3:1293\r\n"
    assert model.receive(b"%R1Q,2008,4:1,1\r\n") == b"%R1P,0,4:0\r\n"


def test_simulator_main_serves_tcp():
    proc = subprocess.Popen([sys.executable, "-m", "simulators.total_station", "--url", "tcp://127.0.0.1:0",
                             "--duration", "20"], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True)
    try:
        url = proc.stdout.readline().strip()
        assert url.startswith("socket://127.0.0.1:")
        port = serial.serial_for_url(url, timeout=2.0)
        try:
            port.write(codec.encode_request(0, trid=42))
            assert port.read_until(b"\r\n") == b"%R1P,0,42:0\r\n"
        finally:
            port.close()
    finally:
        proc.terminate()
        proc.wait(timeout=5)


# ------------------------------------------------------------------------------ corrupted replies (issue 18)
def _corruption_probe():
    import importlib.util
    path = Path(__file__).resolve().parents[2] / "probes" / "geocom_corruption.py"
    spec = importlib.util.spec_from_file_location("geocom_corruption", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_corrupted_replies_are_never_returned_as_good_with_the_crc_on():
    """Bits flipped in the instrument's replies over TCP: with the GeoCOM CRC (the config's default) and the
    plausibility check no returned coordinate is wrong; without either, the same link returns wrong ones (so
    the check can fail). probes/geocom_corruption.py runs the 300-survey version."""
    probe = _corruption_probe()
    on = probe.run(80, 0.01, crc=True, max_error_mm=50.0, seed=3)
    assert on["silently_wrong"] == 0 and on["retries"] > 0 and on["failed"] < on["surveys"] // 10
    off = probe.run(80, 0.01, crc=False, max_error_mm=None, seed=3)
    assert off["silently_wrong"] > 0


def test_implausible_survey_is_refused(tcp):
    """A point far from its target's expected position raises SurveyImplausible (a ProtocolError: retried,
    never journalled)."""
    from drivers.total_station import driver as ts_driver
    feed = tcp.feed
    moved = {**feed.targets}
    name = next(iter(moved))
    x, y, z = moved[name]
    moved[name] = (x + 8.0, y, z)          # ATR still finds the reflector, 8 mm from where it is expected
    strict = TotalStationFeed(feed.geocom, station_xyz_mm=feed.station_xyz_mm, station_yaw_deg=feed.station_yaw_deg,
                              targets=moved, max_error_mm=3.0, connection=None, timeout_s=2.0)
    with pytest.raises(ts_driver.SurveyImplausible, match="from its expected position"):
        strict.measure(name)
