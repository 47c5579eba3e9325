"""A live view of a race: the Rerun sinks a recording streams to besides its file.

A race recording is one Rerun recording stream; with a live view it is sent to the file
(``rr.FileSink``) and to the live sinks in one ``set_sinks`` call, so the file is the same whole
recording whatever the viewers do (a viewer that goes away loses only its own copy):

* ``viewer_url``: a viewer's gRPC server to connect to (``rr.GrpcSink``), e.g. a local ``rerun``
  (which listens on ``rerun+http://127.0.0.1:9876/proxy``) or ``rerun --serve-grpc`` on another host;
* ``serve_port``: a gRPC server hosted by the race process itself (``rr.GrpcServerSink`` on every
  interface); viewers connect to it while the race runs with ``rerun rerun+http://HOST:PORT/proxy``.
  It keeps what was sent (up to ``server_memory_limit``) so a viewer that connects late still gets
  the race from its start; it closes with the recording.

Without a live view nothing here is used (the recorder saves to its file as before).
"""
from __future__ import annotations

from dataclasses import dataclass
from urllib.parse import urlsplit

DEFAULT_VIEWER_PORT = 9876  # where a Rerun viewer listens (rerun's own default)
DEFAULT_VIEWER_URL = f"rerun+http://127.0.0.1:{DEFAULT_VIEWER_PORT}/proxy"
DEFAULT_SERVE_PORT = 9877   # not the viewer's port: a viewer on the race machine and the race's server can coexist
URL_SCHEMES = ("rerun", "rerun+http", "rerun+https")


def viewer_address(url: str) -> tuple[str, int]:
    """(host, port) of a Rerun gRPC URL; ValueError naming what is wrong (the forms ``connect_grpc`` takes:
    scheme rerun://, rerun+http:// or rerun+https://, path /proxy; here with an explicit port)."""
    parts = urlsplit(url)
    if parts.scheme not in URL_SCHEMES:
        raise ValueError(f"{url!r}: the scheme must be one of {', '.join(s + '://' for s in URL_SCHEMES)}")
    if parts.path != "/proxy":
        raise ValueError(f"{url!r}: the path must be /proxy, e.g. {DEFAULT_VIEWER_URL}")
    try:
        port = parts.port
    except ValueError:
        raise ValueError(f"{url!r}: the port must be a number in 0..65535") from None
    if not parts.hostname or port is None:
        raise ValueError(f"{url!r}: name the host and the port, e.g. {DEFAULT_VIEWER_URL}")
    return parts.hostname, port


@dataclass(frozen=True)
class LiveView:
    viewer_url: str | None = None     # stream to the viewer's gRPC server at this URL
    serve_port: int | None = None     # host a gRPC server for viewers on this port
    server_memory_limit: str = "1GiB"  # what the hosted server keeps for late viewers (a race records ~1-20 MB)

    def __post_init__(self) -> None:
        if self.viewer_url is None and self.serve_port is None:
            raise ValueError("a live view needs a viewer URL or a port to serve on")
        if self.viewer_url is not None:
            viewer_address(self.viewer_url)
        if self.serve_port is not None and not 1 <= self.serve_port <= 65535:
            raise ValueError(f"serve port must be in 1..65535, got {self.serve_port}")

    def sinks(self) -> list:
        """The Rerun sinks of the live view (the recorder adds the file's)."""
        import rerun as rr  # only a race with a live view gets here

        out = []
        if self.viewer_url is not None:
            out.append(rr.GrpcSink(self.viewer_url))
        if self.serve_port is not None:
            out.append(rr.GrpcServerSink(port=self.serve_port, server_memory_limit=self.server_memory_limit))
        return out

    def serve_url(self, host: str) -> str | None:
        """The URL a viewer on another machine opens (``rerun URL``) to watch the race served here."""
        return None if self.serve_port is None else f"rerun+http://{host}:{self.serve_port}/proxy"
