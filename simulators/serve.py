"""Serve a byte-stream device model on a pty or a loopback TCP socket, with faults on demand.

A *device model* is sans-IO: ``receive(data) -> reply bytes``. The server owns the transport and a
thread; a :class:`Faults` object, changeable while running, injects latency, split writes, dropped and
corrupted bytes, and disconnects, so drivers are tested against the failure modes of real cables.
"""
from __future__ import annotations

import os
import random
import select
import socket
import termios
import threading
import time
import tty
from dataclasses import dataclass, field
from typing import Protocol


class StreamDevice(Protocol):
    """A sans-IO device model: bytes from the host in, bytes to the host out."""

    def receive(self, data: bytes) -> bytes: ...
    def reset(self) -> None: ...


@dataclass
class Faults:
    """Faults applied to the simulator's replies (all off by default).

    latency_s: delay before each reply; split_at: write replies in chunks of this many bytes with
    ``split_gap_s`` between them; drop_probability / corrupt_probability: per reply byte;
    mute: swallow every reply (a device that stopped answering); garbage: bytes sent before the next reply;
    unplugged: the cable is pulled: bytes from the host never reach the device and nothing comes back (unlike
    ``mute``, the device executes nothing); clear it to plug the cable back in.
    """

    latency_s: float = 0.0
    split_at: int | None = None
    split_gap_s: float = 0.002
    drop_probability: float = 0.0
    corrupt_probability: float = 0.0
    mute: bool = False
    garbage: bytes = b""
    unplugged: bool = False
    seed: int = 0
    _rng: random.Random = field(default_factory=random.Random, repr=False)

    def __post_init__(self) -> None:
        self._rng.seed(self.seed)

    def clear(self) -> None:
        self.latency_s = 0.0
        self.split_at = None
        self.drop_probability = self.corrupt_probability = 0.0
        self.mute = False
        self.garbage = b""
        self.unplugged = False

    def apply(self, reply: bytes) -> list[bytes]:
        """Return the chunks to write for ``reply`` after the byte-level faults."""
        if self.mute or not reply:
            return []
        out = bytearray(self.garbage)
        self.garbage = b""
        for b in reply:
            if self.drop_probability and self._rng.random() < self.drop_probability:
                continue
            if self.corrupt_probability and self._rng.random() < self.corrupt_probability:
                b ^= 1 << self._rng.randrange(8)
            out.append(b)
        if self.split_at:
            n = max(1, self.split_at)
            return [bytes(out[i:i + n]) for i in range(0, len(out), n)]
        return [bytes(out)]


class _Server:
    url: str

    def __init__(self, device: StreamDevice, faults: Faults | None) -> None:
        self.device = device
        self.faults = faults or Faults()
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def _reply(self, data: bytes, write) -> None:
        if self.faults.unplugged:       # lost on the wire: the device never sees these bytes
            return
        with self._lock:
            reply = self.device.receive(data)
        chunks = self.faults.apply(reply)
        if chunks and self.faults.latency_s:
            time.sleep(self.faults.latency_s)
        for i, chunk in enumerate(chunks):
            if i and self.faults.split_gap_s:
                time.sleep(self.faults.split_gap_s)
            write(chunk)

    def start(self) -> "_Server":
        self._thread = threading.Thread(target=self._run, name=f"sim:{self.url}", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class PtyServer(_Server):
    """Serve ``device`` on a new pseudo-terminal; ``url`` is the slave's path (open it with pyserial)."""

    def __init__(self, device: StreamDevice, faults: Faults | None = None) -> None:
        super().__init__(device, faults)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave, termios.TCSANOW)
        tty.setraw(self._master, termios.TCSANOW)
        self.url = os.ttyname(self._slave)

    def _run(self) -> None:
        while not self._stop.is_set():
            r, _, _ = select.select([self._master], [], [], 0.05)
            if not r:
                continue
            try:
                data = os.read(self._master, 4096)
            except OSError:
                time.sleep(0.01)
                continue
            if data:
                self._reply(data, lambda b: os.write(self._master, b))

    def close(self) -> None:
        super().close()
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpServer(_Server):
    """Serve ``device`` on ``host:port`` (port 0 picks a free one); ``url`` is ``socket://host:port``.

    One client at a time; when a client disconnects the next one is accepted, so a driver can reconnect.
    ``disconnect()`` drops the current client, as a pulled cable would.
    """

    def __init__(self, device: StreamDevice, host: str = "127.0.0.1", port: int = 0,
                 faults: Faults | None = None) -> None:
        super().__init__(device, faults)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind((host, port))
        self._sock.listen(4)
        self.host, self.port = self._sock.getsockname()[:2]
        self.url = f"socket://{self.host}:{self.port}"
        self._client: socket.socket | None = None

    def disconnect(self) -> None:
        client = self._client
        if client is not None:
            try:
                client.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def _run(self) -> None:
        self._sock.settimeout(0.05)
        while not self._stop.is_set():
            try:
                client, _ = self._sock.accept()
            except (socket.timeout, OSError):
                continue
            client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client.settimeout(0.05)
            self._client = client
            with client:
                while not self._stop.is_set():
                    try:
                        data = client.recv(4096)
                    except socket.timeout:
                        continue
                    except OSError:
                        break
                    if not data:
                        break
                    try:
                        self._reply(data, client.sendall)
                    except OSError:
                        break
            self._client = None

    def close(self) -> None:
        super().close()
        self._sock.close()


def serve(device: StreamDevice, url: str, faults: Faults | None = None) -> _Server:
    """Start serving ``device`` on ``url``: ``pty`` (a new pty) or ``tcp://host:port`` (port 0 = any)."""
    if url == "pty":
        return PtyServer(device, faults).start()
    if url.startswith("tcp://"):
        host, _, port = url[len("tcp://"):].rpartition(":")
        return TcpServer(device, host or "127.0.0.1", int(port or 0), faults).start()
    raise ValueError(f"simulator URL {url!r}: expected 'pty' or 'tcp://HOST:PORT'")
