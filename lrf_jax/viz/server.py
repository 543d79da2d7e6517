"""The viewer's web server: viser imported on demand (the `viz` extra), the address checked
before anything is served, and `Viewer`, the handle `lrf_jax.view` returns.

viser (https://viser.studio) serves a page with a three.js scene and a GUI panel from a thread
of this process; every browser tab that opens the address sees the same scene. It is bound to
127.0.0.1 (this machine only) unless a host is named; it has no password.
"""

from __future__ import annotations

import contextlib
import errno
import io
import ipaddress
import socket
import sys
import time
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
  import viser

__all__ = ["DEFAULT_HOST", "Viewer", "address_problem", "host_warning", "import_viser",
           "is_loopback", "start_server"]

DEFAULT_HOST = "127.0.0.1"
VIZ_INSTALL = "pip install 'lrf_jax[viz]'"
# The errors of a port another program listens on.
_IN_USE = {errno.EADDRINUSE, 10048}  # 10048: WSAEADDRINUSE (Windows)


def import_viser(what: str = "the viewer") -> Any:
  """The viser module, or a `MissingExtraError` naming the `viz` extra.

  Raises:
    MissingExtraError: viser is not installed (an ImportError).
  """
  from lrf_jax.extras import MissingExtraError
  try:
    import viser
  except ImportError as e:
    raise MissingExtraError(f"{what} needs viser, which is not installed: {VIZ_INSTALL} (the "
                            "'viz' extra: viser)", name=e.name) from e
  return viser


def is_loopback(host: str) -> bool:
  """Whether `host` is an address of this machine only ("localhost", 127.x.x.x, ::1)."""
  if host.lower() == "localhost":
    return True
  try:
    return ipaddress.ip_address(host).is_loopback
  except ValueError:
    return False


def host_warning(host: str) -> str | None:
  """The one warning line for a host other machines can reach (None for a loopback one)."""
  if is_loopback(host):
    return None
  return (f"warning: --host {host}: the viewer is served to other machines, without a "
          "password: anyone who reaches this address sees the scans (the default, "
          f"{DEFAULT_HOST}, serves this machine only)")


def address_problem(host: str, port: int | None) -> str | None:
  """Why the viewer cannot listen on `host`:`port` (None: it can; port None: any free port),
  found by binding a socket there for a moment."""
  if port is not None and not 1 <= port <= 65535:
    return f"--port: expected a port number from 1 to 65535, got {port}"
  try:
    infos = socket.getaddrinfo(host, port or 0, type=socket.SOCK_STREAM,
                               flags=socket.AI_PASSIVE)
  except (socket.gaierror, UnicodeError) as e:
    return f"--host: {host!r} is not an address of this machine ({e})"
  family, _, _, _, address = infos[0]
  with socket.socket(family, socket.SOCK_STREAM) as s:
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server's own socket
    try:
      s.bind(address)
    except OSError as e:
      if port is not None and e.errno in _IN_USE:
        return (f"--port: {port} is in use on {host}; pick another port or leave --port out "
                "(a free one is chosen)")
      return f"--host: cannot listen on {host}{'' if port is None else f':{port}'}: " \
             f"{e.strerror or e}"
  return None


def start_server(host: str = DEFAULT_HOST, port: int | None = None, *,
                 title: str = "lrf_jax") -> viser.ViserServer:
  """A viser server listening on `host`:`port` (None: a free port), its share button (a tunnel
  through viser's servers) hidden.

  Raises:
    MissingExtraError: viser is not installed.
    OSError: `port` was taken meanwhile (viser would have moved to the next one).
  """
  viser = import_viser()
  with contextlib.redirect_stdout(io.StringIO()):  # its banner, printed whatever `verbose`
    server = viser.ViserServer(host=host, port=0 if port is None else port, label=title,
                               verbose=False)
  if port is not None and server.get_port() != port:
    _quiet_stop(server)
    raise OSError(f"--port: {port} was taken while the viewer started; pick another port")
  server.gui.configure_theme(show_share_button=False, control_width="large")
  return server


def _quiet_stop(server: Any) -> None:
  """Stop a viser server without its "Server stopped" line on stdout."""
  with contextlib.redirect_stdout(io.StringIO()):
    server.stop()


class Viewer:
  """A running viewer: its viser server and its address (`lrf_jax.view` returns one).

  In a notebook, a `Viewer` as a cell's value shows the page inline (an iframe of `url`);
  `stop()` ends it (so does the end of the Python process). A script calls `wait()` to serve
  until Ctrl-C.

  Attributes:
    server: the `viser.ViserServer` (its `.scene` and `.gui` add more to the page).
    url: the page's address.
  """

  def __init__(self, server: viser.ViserServer, host: str):
    self.server = server
    shown = f"[{host}]" if ":" in host else host
    if host in ("0.0.0.0", "::"):  # every interface: this machine's name for the link
      shown = "localhost"
    self.url = f"http://{shown}:{server.get_port()}/"
    self.stopped = False

  def stop(self) -> None:
    """Stop serving (idempotent)."""
    if not self.stopped:
      self.stopped = True
      _quiet_stop(self.server)

  def wait(self) -> None:
    """Serve until interrupted (Ctrl-C: KeyboardInterrupt), then stop."""
    try:
      while True:
        time.sleep(0.2)
    finally:
      self.stop()

  def open_browser(self) -> bool:
    """Open the page in the default web browser; whether one was found."""
    import webbrowser
    try:
      return webbrowser.open(self.url)
    except webbrowser.Error:
      return False

  def __enter__(self) -> Viewer:
    return self

  def __exit__(self, *exc: Any) -> None:
    self.stop()

  def _repr_html_(self) -> str:
    """The page inline in a notebook."""
    return (f'<iframe src="{self.url}" width="100%" height="600" style="border:none"></iframe>'
            f'<div><a href="{self.url}" target="_blank">{self.url}</a></div>')

  def __repr__(self) -> str:
    return f"Viewer({self.url!r}{', stopped' if self.stopped else ''})"


def print_address(viewer: Viewer, out: Any = None) -> None:
  """The one line that says where the viewer is."""
  print(f"lrf-view: {viewer.url} (Ctrl-C to stop)", file=out or sys.stdout, flush=True)
