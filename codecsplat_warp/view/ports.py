"""Choosing the viewer's port before its server starts: a port in use is an error, not a silent move elsewhere
(viser itself would take the next free port)."""

from __future__ import annotations

import errno
import socket

from ..errors import PortInUseError, ViewerError

PORT_SEARCH = 1000
"""Ports tried from the default up for ``--port 0``."""


def port_is_free(host: str, port: int) -> bool:
    """Whether a server can listen on ``host``:``port`` now (binds and closes a socket there, address reuse on as
    the server's own). ViewerError when ``host`` is not an address of this machine."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        raise ViewerError(f"--host {host!r} is not a host name or address: {exc.strerror}") from None
    family, kind, proto, _, address = infos[0]
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(address)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return False
            raise ViewerError(f"cannot listen on {host}:{port}: {exc.strerror}") from None
    return True


def choose_port(host: str, port: int, first: int) -> int:
    """The port to serve on: ``port`` itself (PortInUseError when it is taken), or for ``port`` 0 the first free one
    from ``first`` up. ViewerError for a port outside 0-65535 or a host that is not this machine's."""
    if not 0 <= port <= 65535:
        raise ViewerError(f"--port must be in 0-65535, got {port}")
    if port:
        if not port_is_free(host, port):
            raise PortInUseError(f"port {port} on {host} is in use: pass --port 0 for the next free port, or another "
                                 "--port")
        return port
    for candidate in range(first, min(first + PORT_SEARCH, 65536)):
        if port_is_free(host, candidate):
            return candidate
    raise PortInUseError(f"ports {first}-{first + PORT_SEARCH - 1} on {host} are all in use: pass a --port")
