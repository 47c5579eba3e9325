"""OptiTrack Motive over NatNet: the ``natnet`` client library (PyPI, MIT; the ``mocap`` extra) in a
receive thread that keeps the newest frame, mapped onto the loop's clock (docs/tracking.md, "Motion
capture").

* ``natnet://SERVER[:PORT][?multicast=GROUP]``: Motive's command port (default 1510), its data port the next
  one. Unicast by default (Motive: Streaming pane, Transmission Type Unicast); ``?multicast=239.255.42.99``
  (Motive's default group) joins Motive's multicast stream on the data port instead. The client binds the
  local address that routes to SERVER.
* Clock: Motive stamps each frame with its own timestamp (seconds since it started). The frame's time on
  the loop's clock is that stamp plus the smallest (arrival - stamp) seen over the last ``offset_window``
  frames, less ``latency_s`` (Motive's exposure-to-send and the network's fixed delay, which arrival times
  cannot tell apart from the clock offset; Motive shows it in its latency readout). Network jitter then
  does not move the frames' times, and the window follows the two clocks' drift.
* Faults, reported as ``events`` (kind ``mocap``) and never raised into the loop: no frame for
  ``stall_after_s`` (the stream stalled or the server went away), a receive or decode error. A server that
  does not answer the connect request within ``connect_timeout_s`` is a :class:`MocapError` at start-up.
"""
from __future__ import annotations

import collections
import socket
import threading
from dataclasses import dataclass
import ipaddress
from urllib.parse import parse_qs, urlsplit

from tracking.mocap import MocapFrame, RigidBodySample

DEFAULT_COMMAND_PORT = 1510


class MocapError(RuntimeError):
    """The mocap source cannot be used (bad URL, no server, the client library missing)."""


@dataclass(frozen=True)
class NatNetAddress:
    host: str
    command_port: int = DEFAULT_COMMAND_PORT
    multicast_group: str | None = None  # None: unicast

    @property
    def url(self) -> str:
        return f"natnet://{self.host}:{self.command_port}" + (
            f"?multicast={self.multicast_group}" if self.multicast_group else "")


def parse_natnet_url(text: str) -> NatNetAddress:
    """``natnet://SERVER[:PORT][?multicast=GROUP]`` -> NatNetAddress; MocapError naming what is wrong."""
    usage = "expected natnet://SERVER[:PORT][?multicast=GROUP], e.g. natnet://192.168.1.20 or natnet://127.0.0.1:1510"
    try:
        parts = urlsplit(str(text))
        port = parts.port
        query = parse_qs(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError as exc:
        raise MocapError(f"{text!r}: {exc}; {usage}") from None
    if parts.scheme != "natnet" or not parts.hostname or parts.path not in ("", "/") or set(query) - {"multicast"}:
        raise MocapError(f"{text!r}: {usage}")
    if port == 0 or (port is not None and port > 65534):
        raise MocapError(f"{text!r}: the command port must be in 1..65534 (the data port is the next one)")
    group = None
    if "multicast" in query:
        group = query["multicast"][-1]
        try:
            if not ipaddress.IPv4Address(group).is_multicast:
                raise ValueError
        except ValueError:
            raise MocapError(f"{text!r}: multicast={group!r} is not an IPv4 multicast group "
                             f"(Motive's default: 239.255.42.99)") from None
    return NatNetAddress(parts.hostname, port or DEFAULT_COMMAND_PORT, group)


def local_address_for(host: str) -> str:
    """The local IP address whose interface routes to ``host`` (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect((host, 9))
            return s.getsockname()[0]
        except OSError as exc:
            raise MocapError(f"natnet://{host}: no route to the server ({exc})") from None


class NatNetSource:
    """Connects on construction (MocapError if the server does not answer) and receives in its own thread.
    ``read()`` returns the newest frame not yet read (None if there is none); ``events()`` the faults
    since the last call. ``clock`` is the loop's monotonic clock (``now()``)."""

    def __init__(self, address: NatNetAddress, clock, latency_s: float = 0.0, stall_after_s: float = 0.1,
                 connect_timeout_s: float = 3.0, offset_window: int = 600, poll_s: float = 0.004) -> None:
        try:
            from natnet import NatNetClient  # the optional `mocap` extra
        except ImportError:
            raise MocapError("the NatNet client library is not installed: pip install .[mocap] (PyPI natnet)") from None
        self.address, self.clock = address, clock
        self.latency_s, self.stall_after_s, self.poll_s = float(latency_s), float(stall_after_s), float(poll_s)
        self._client = NatNetClient(server_ip_address=address.host, local_ip_address=local_address_for(address.host),
                                    command_port=address.command_port, data_port=address.command_port + 1,
                                    use_multicast=address.multicast_group is not None,
                                    **({"multicast_address": address.multicast_group} if address.multicast_group else {}))
        self._client.on_data_frame_received_event.handlers.append(self._on_frame)
        try:
            self._client.connect(timeout=connect_timeout_s)
        except TimeoutError:
            raise MocapError(f"{address.url}: no answer from a NatNet server within {connect_timeout_s:g} s "
                             f"(is Motive streaming, {'multicast' if address.multicast_group else 'unicast'}, "
                             f"on that address and port?)") from None
        except OSError as exc:
            self._client.shutdown()
            raise MocapError(f"{address.url}: {exc}") from None
        info = self._client.server_info
        self.server = f"{info.application_name} {info.server_version}, NatNet {info.nat_net_protocol_version}"
        self._lock = threading.Lock()
        self._offsets: collections.deque = collections.deque(maxlen=offset_window)
        self._newest: MocapFrame | None = None
        self._events: list[tuple[float, str]] = []  # (clock time, text)
        self._last_arrival = self.clock.now()
        self._stalled = False
        self._error: str | None = None
        self.frames = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="NatNetSource", daemon=True)
        self._thread.start()

    def _on_frame(self, data) -> None:
        now = self.clock.now()
        stamp = float(data.suffix.timestamp)
        self._offsets.append(now - stamp)
        t = stamp + min(self._offsets) - self.latency_s
        bodies = {int(rb.id_num): RigidBodySample(tuple(rb.pos), tuple(rb.rot),
                                                  True if rb.tracking_valid is None else bool(rb.tracking_valid))
                  for rb in data.rigid_bodies}
        frame = MocapFrame(t, int(data.prefix.frame_number), bodies)
        with self._lock:
            self._newest = frame
            self._last_arrival = now
            self.frames += 1
            if self._stalled:
                self._stalled = False
                self._events.append((now, "stream resumed"))

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                # Reads both sockets until they are empty (unicast frames arrive on the command socket);
                # the library sends a keep-alive with each call, hence the pace below.
                self._client.update_sync()
                error = None
            except Exception as exc:  # a refused datagram (server gone), a frame that does not decode
                error = f"{type(exc).__name__}: {exc}"
            now = self.clock.now()
            with self._lock:
                if error is not None and error != self._error:
                    self._events.append((now, f"receive error: {error}"))
                self._error = error
                if not self._stalled and now - self._last_arrival > self.stall_after_s:
                    self._stalled = True
                    self._events.append((now, f"no frame for {1e3 * (now - self._last_arrival):.0f} ms "
                                              f"(stream stalled or server gone)"))
            self._stop.wait(self.poll_s)

    def read(self) -> MocapFrame | None:
        with self._lock:
            frame, self._newest = self._newest, None
        return frame

    def events(self) -> list[tuple[float, str]]:
        with self._lock:
            out, self._events = self._events, []
        return out

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        try:
            self._client.shutdown()
        except OSError:
            pass
