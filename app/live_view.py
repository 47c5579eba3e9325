"""`race --viewer [URL]` and `race --serve [PORT]`: watch a race in Rerun while it runs (recording.live).

Everything is checked before the race starts (exit code 2 naming the flag): the URL's form, that a
viewer answers there (a local one on the default port is started when none does and a display
exists), that the port to serve on is free. docs/racing.md, "Live view and operator stop".
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import time

from app.cli import UserError
from recording.integrity import rerun_executable
from recording.live import DEFAULT_SERVE_PORT, DEFAULT_VIEWER_PORT, DEFAULT_VIEWER_URL, LiveView, viewer_address

VIEWER_START_TIMEOUT_S = 15.0
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def add_live_arguments(p) -> None:
    g = p.add_argument_group("live view (docs/racing.md, \"Live view and operator stop\")")
    g.add_argument("--viewer", nargs="?", const=DEFAULT_VIEWER_URL, default=None, metavar="URL",
                   help=f"stream the recording to a Rerun viewer while it is written (the .rrd file stays "
                        f"complete); URL of the viewer's gRPC server (default {DEFAULT_VIEWER_URL}: a local "
                        f"viewer, started if none runs there and a display exists)")
    g.add_argument("--serve", nargs="?", const=DEFAULT_SERVE_PORT, default=None, type=int, metavar="PORT",
                   help=f"host a gRPC server for Rerun viewers on this port (default {DEFAULT_SERVE_PORT}, every "
                        f"interface); watch from any machine with `rerun rerun+http://HOST:PORT/proxy` while "
                        f"the race runs")


def display_problem() -> str | None:
    """Why no viewer window can open here (Linux without DISPLAY/WAYLAND_DISPLAY), or None."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY/WAYLAND_DISPLAY not set)"
    return None


def answers(host: str, port: int, timeout_s: float = 1.0) -> bool:
    """Does something accept TCP connections at host:port?"""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False


def live_view(args) -> LiveView | None:
    """The live view of --viewer/--serve (None without either), checked; may start a local viewer."""
    url, port = getattr(args, "viewer", None), getattr(args, "serve", None)
    if url is None and port is None:
        return None
    if port is not None:
        if not 1 <= port <= 65535:
            raise UserError(f"--serve: the port must be in 1..65535, got {port}")
        _check_port_free(port)
    if url is not None:
        try:
            host, viewer_port = viewer_address(url)
        except ValueError as exc:
            raise UserError(f"--viewer: {exc}") from None
        if port is not None and host in LOCAL_HOSTS and viewer_port == port:
            raise UserError(f"--viewer {url} and --serve {port}: the race cannot be its own viewer; "
                            f"serve on another port")
        if not answers(host, viewer_port):
            if url != DEFAULT_VIEWER_URL:
                raise UserError(f"--viewer: no Rerun viewer answers at {url}; start one there (`rerun` listens on "
                                f"{DEFAULT_VIEWER_PORT}, `rerun --serve-grpc --port P` without a window)")
            _start_local_viewer()
    return LiveView(viewer_url=url, serve_port=port)


def _check_port_free(port: int) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("0.0.0.0", port))
        except OSError as exc:
            raise UserError(f"--serve: port {port} is not free ({exc.strerror}); "
                            f"choose another with --serve PORT") from None


def viewer_executable(flag: str, hint: str) -> str:
    """The `rerun` viewer of rerun-sdk; UserError (naming ``flag``, ending with ``hint``) without one."""
    exe = rerun_executable()
    if exe is None:
        raise UserError(f"{flag}: no Rerun viewer found (the `rerun` executable of rerun-sdk); {hint}")
    return exe


def _start_local_viewer() -> None:
    """Start `rerun` on the default port (as rr.spawn does) and wait until it listens."""
    hint = (f"start a viewer where one can show (`rerun --serve-grpc --port {DEFAULT_VIEWER_PORT}` here, or "
            f"`rerun` on a machine with a display and --viewer rerun+http://THAT_HOST:{DEFAULT_VIEWER_PORT}/proxy), "
            f"or use --serve and connect a viewer to the race")
    problem = display_problem()
    if problem:
        raise UserError(f"--viewer: no Rerun viewer answers at {DEFAULT_VIEWER_URL} and {problem} to start one; {hint}")
    exe = viewer_executable("--viewer", hint)
    try:
        subprocess.Popen([exe, "--port", str(DEFAULT_VIEWER_PORT), "--expect-data-soon"], start_new_session=True,
                         stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    except OSError as exc:
        raise UserError(f"--viewer: cannot start {exe}: {exc}") from None
    deadline = time.monotonic() + VIEWER_START_TIMEOUT_S
    while not answers("127.0.0.1", DEFAULT_VIEWER_PORT, 0.2):
        if time.monotonic() > deadline:
            raise UserError(f"--viewer: started {exe} but it did not listen on port {DEFAULT_VIEWER_PORT} within "
                            f"{VIEWER_START_TIMEOUT_S:.0f} s; {hint}")
        time.sleep(0.2)


def announce(view: LiveView | None) -> None:
    """Say where the race can be watched."""
    if view is None:
        return
    if view.viewer_url is not None:
        print(f"live view: streaming to the Rerun viewer at {view.viewer_url}")
    if view.serve_port is not None:
        print(f"live view: serving on port {view.serve_port}; watch with "
              f"`rerun {view.serve_url(socket.gethostname())}` (or {view.serve_url('127.0.0.1')} on this machine)")

