"""A loopback OptiTrack Motive server: it answers a NatNet client's connect request and streams rigid-body
frames over UDP, written from the NatNet packet layout (the NatNet SDK's PacketClient and its
NatNetClient.py sample; docs/tracking.md, "Motion capture"). Tests and ``race --hil --mocap`` stream
the simulator's poses through it to the real client library (tracking.natnet).

Messages: a 4-byte header (uint16 message id, uint16 payload bytes), little-endian throughout.

* NAT_CONNECT (0) from a client -> NAT_SERVERINFO (1): application name (256 bytes, NUL-padded), server
  version and NatNet version (4 uint8 each); from NatNet 3.0 also the high-resolution clock frequency
  (uint64), the data port (uint16), multicast flag (uint8) and multicast group (4 bytes).
* NAT_KEEPALIVE (10) and NAT_REQUEST_MODELDEF (4): the client stays registered; model definitions are
  answered with an empty NAT_MODELDEF (5) (0 data sets).
* NAT_FRAMEOFDATA (7), unicast to every registered client's command address (or, multicast, to the group on
  the data port): frame number (int32); marker
  sets, legacy unlabeled markers, rigid bodies, skeletons (2.1+), assets (4.1+), labeled markers (2.3+),
  force plates (2.9+) and devices (2.11+), each an int32 count, from 4.1 followed by the data set's size
  in bytes; a rigid body is id (int32), position (3 float32), quaternion qx qy qz qw (4 float32), before
  3.0 its markers, mean marker error (float32, 2.0+) and parameters (int16, 2.6+, bit 0 = tracking valid).
  Suffix: timecode and sub-frame (uint32 each), timestamp (float64 seconds, 2.7+), from 3.0 the
  mid-exposure, data-received and transmit stamps (uint64 clock ticks), from 4.0 the precision timestamp
  (uint32 seconds, uint32 fraction), then the frame parameters (int16: bit 0 recording, bit 1 models
  changed).

Faults: ``stall()`` / ``resume()`` stop and restart the stream with the server still answering;
``close()`` takes the server away (the client's next datagrams are refused).
"""
from __future__ import annotations

import select
import socket
import struct
import threading
import time

NAT_CONNECT, NAT_SERVERINFO, NAT_REQUEST_MODELDEF, NAT_MODELDEF = 0, 1, 4, 5
NAT_FRAMEOFDATA, NAT_KEEPALIVE = 7, 10
CLOCK_HZ = 10_000_000  # the high-resolution stamps' tick rate (QueryPerformanceFrequency of a Windows host)


def _ge(version: tuple[int, int], major: int, minor: int = 0) -> bool:
    return tuple(version) >= (major, minor)


def _data_set(version, count: int, body: bytes) -> bytes:
    """A data set of the frame: its count, from 4.1 its size in bytes, then its records."""
    return struct.pack("<i", count) + (struct.pack("<i", len(body)) if _ge(version, 4, 1) else b"") + body


def frame_packet(version: tuple[int, int], frame_number: int, timestamp_s: float, bodies) -> bytes:
    """A NAT_FRAMEOFDATA message. ``bodies``: (id, (x, y, z), (qx, qy, qz, qw), tracked, mean error m)."""
    rb = b""
    for rid, pos, rot, tracked, error in bodies:
        rb += struct.pack("<i3f4f", rid, *pos, *rot)
        if not _ge(version, 3):
            rb += struct.pack("<i", 0)  # markers of the rigid body (moved to the model definitions in 3.0)
        if _ge(version, 2):
            rb += struct.pack("<f", error)
        if _ge(version, 2, 6):
            rb += struct.pack("<h", 1 if tracked else 0)
    body = struct.pack("<i", frame_number)
    body += _data_set(version, 0, b"")          # marker sets
    body += _data_set(version, 0, b"")          # legacy unlabeled markers
    body += _data_set(version, len(bodies), rb)  # rigid bodies
    for since, major, minor in (("skeletons", 2, 1), ("assets", 4, 1), ("labeled markers", 2, 3),
                                ("force plates", 2, 9), ("devices", 2, 11)):
        if _ge(version, major, minor):
            body += _data_set(version, 0, b"")
    body += struct.pack("<II", 0, 0)  # timecode, sub-frame
    body += struct.pack("<d", timestamp_s) if _ge(version, 2, 7) else struct.pack("<f", timestamp_s)
    if _ge(version, 3):
        ticks = int(round(timestamp_s * CLOCK_HZ))
        body += struct.pack("<QQQ", ticks, ticks, ticks)  # mid-exposure, data received, transmit
    if _ge(version, 4):
        secs = int(timestamp_s)
        body += struct.pack("<II", secs, int((timestamp_s - secs) * 2 ** 32) & 0xFFFFFFFF)
    body += struct.pack("<h", 0)
    return struct.pack("<HH", NAT_FRAMEOFDATA, len(body)) + body


def server_info_packet(version: tuple[int, int], data_port: int, multicast_group: str | None = None,
                       app_name: str = "Motive") -> bytes:
    body = app_name.encode()[:255].ljust(256, b"\0") + bytes((3, 1, 0, 0)) + bytes((*version, 0, 0))
    if _ge(version, 3):
        group = socket.inet_aton(multicast_group or "239.255.42.99")
        body += struct.pack("<QHB4s", CLOCK_HZ, data_port, multicast_group is not None, group)
    return struct.pack("<HH", NAT_SERVERINFO, len(body)) + body


class MotiveEmulator:
    """NatNet server on ``host``:``port`` (command port; ``port`` 0 picks a free one, ``self.port``).
    ``send_frame`` streams one frame: unicast to each client's command address, or with ``multicast_group``
    to that group on the data port (``port`` + 1) out of ``host``'s interface, as Motive's multicast does."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, version: tuple[int, int] = (4, 1),
                 multicast_group: str | None = None) -> None:
        self.version = tuple(version)
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, port))
        self.host, self.port = self._sock.getsockname()
        self.multicast_group = multicast_group
        if multicast_group is not None:
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.host))
            self._sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        self.clients: set = set()
        self.frames_sent = 0
        self._stalled = False
        self._closed = False
        self._lock = threading.Lock()
        self._wake_r, self._wake_w = socket.socketpair()
        self._thread = threading.Thread(target=self._serve, name="MotiveEmulator", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            readable, _, _ = select.select([self._sock, self._wake_r], [], [])
            if self._wake_r in readable:
                return
            try:
                data, addr = self._sock.recvfrom(65536)
            except OSError:
                continue
            if len(data) < 4:
                continue
            message = struct.unpack_from("<H", data)[0]
            with self._lock:
                if message == NAT_CONNECT:
                    self.clients.add(addr)
                    self._sock.sendto(server_info_packet(self.version, self.port + 1, self.multicast_group), addr)
                elif message in (NAT_KEEPALIVE, NAT_REQUEST_MODELDEF):
                    self.clients.add(addr)
                    if message == NAT_REQUEST_MODELDEF:
                        self._sock.sendto(struct.pack("<HHi", NAT_MODELDEF, 4, 0), addr)

    def send_frame(self, frame_number: int, timestamp_s: float, bodies) -> int:
        """Stream one frame to every client (none while stalled or closed); returns the clients reached."""
        packet = frame_packet(self.version, frame_number, timestamp_s, bodies)
        with self._lock:
            if self._stalled or self._closed:
                return 0
            if self.multicast_group is not None:
                self._sock.sendto(packet, (self.multicast_group, self.port + 1))
                self.frames_sent += 1
                return len(self.clients)
            for addr in list(self.clients):
                try:
                    self._sock.sendto(packet, addr)
                except OSError:  # the client went away
                    self.clients.discard(addr)
            self.frames_sent += 1
            return len(self.clients)

    def stall(self) -> None:
        self._stalled = True

    def resume(self) -> None:
        self._stalled = False

    def close(self) -> None:
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._wake_w.send(b"x")
        self._thread.join(timeout=2.0)
        for s in (self._sock, self._wake_r, self._wake_w):
            s.close()

    def wait_for_client(self, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while not self.clients and time.monotonic() < deadline:
            time.sleep(0.01)
        return bool(self.clients)
