"""The simulator server: bytes over a real pty and a real TCP socket, with faults."""
import time

import pytest

from drivers.errors import DeviceTimeout
from drivers.transport import open_transport, read_exact
from simulators.serve import Faults, serve


class Upper:
    def __init__(self):
        self.seen = b""

    def receive(self, data):
        self.seen += data
        return data.upper()

    def reset(self):
        self.seen = b""


@pytest.mark.parametrize("url", ["pty", "tcp://127.0.0.1:0"])
def test_round_trip_and_faults(url):
    dev, faults = Upper(), Faults(seed=1)
    with serve(dev, url, faults) as srv:
        port = open_transport(srv.url, timeout_s=0.2)
        try:
            port.write(b"abc")
            assert read_exact(port, 3, timeout_s=1, what="echo") == b"ABC"
            faults.split_at = 1
            port.write(b"defg")
            assert read_exact(port, 4, timeout_s=1, what="split echo") == b"DEFG"
            faults.split_at, faults.garbage = None, b"\x00\xff"
            port.write(b"h")
            assert read_exact(port, 3, timeout_s=1, what="garbage") == b"\x00\xffH"
            faults.corrupt_probability = 1.0
            port.write(b"i")
            assert read_exact(port, 1, timeout_s=1, what="corrupt") != b"I"
            faults.clear()
            faults.mute = True
            port.write(b"j")
            t0 = time.monotonic()
            with pytest.raises(DeviceTimeout, match="waiting for muted"):
                read_exact(port, 1, timeout_s=0.3, what="muted")
            assert time.monotonic() - t0 < 1.0
        finally:
            port.close()
    assert dev.seen.startswith(b"abcdefg")


def test_serve_rejects_unknown_url():
    with pytest.raises(ValueError, match="expected 'pty' or 'tcp://HOST:PORT'"):
        serve(Upper(), "udp://x")
