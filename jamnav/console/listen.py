"""Where the console listens and who may use it: ``HOST:PORT`` (loopback by default), a free
port when the default one is taken, and the token a secure system's console demands.

Kept free of the web server's imports: ``jamnav up`` opens the console's socket before it
starts anything, so that a taken port is a one-line error and not a child that dies, and hands
it to each console it starts.
"""

from __future__ import annotations

import errno
import ipaddress
import secrets
import socket
import stat
from dataclasses import dataclass
from pathlib import Path

from shared import access

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8470
DEFAULT_WEB = f"{DEFAULT_HOST}:{DEFAULT_PORT}"
TOKEN_FILE = "console_token"  # in the run directory, mode 0600


@dataclass(frozen=True)
class WebAddress:
    host: str
    port: int
    taken_default: int | None = None  # the default port, in use, that this one replaces

    @property
    def text(self) -> str:
        return f"[{self.host}]:{self.port}" if ":" in self.host else f"{self.host}:{self.port}"

    def url(self, token: str | None = None) -> str:
        return f"http://{self.text}/" + ("" if token is None else f"?token={token}")

    def accepting(self) -> bool:
        """Whether something listens there: a connection made now is answered once the
        console serves (it listens before it has reached the bus)."""
        try:
            with socket.create_connection((self.host, self.port), timeout=0.5):
                return True
        except OSError:
            return False

    @property
    def loopback(self) -> bool:
        try:
            return ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            return self.host == "localhost"


def parse_web(text: str) -> WebAddress:
    """``HOST:PORT`` (``[IPv6]:PORT``) as an address; ValueError with a one-line reason."""
    host, colon, port = text.rpartition(":")
    host = host.strip("[]")
    if not colon or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ValueError(f"--web {text!r}: expected HOST:PORT, e.g. {DEFAULT_WEB}")
    return WebAddress(host, int(port))


def bind(address: WebAddress) -> socket.socket:
    """A listening socket at ``address`` (OSError if it cannot be had). As a server binds:
    connections of a previous console in TIME_WAIT do not hold the port."""
    family = socket.AF_INET6 if ":" in address.host else socket.AF_INET
    listener = socket.socket(family, socket.SOCK_STREAM)
    try:
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((address.host, address.port))
        listener.listen(128)
    except OSError:
        listener.close()
        raise
    return listener


def open_listener(text: str | None) -> tuple[socket.socket, WebAddress]:
    """The console's listening socket: at ``--web`` if given (a taken port is a ValueError
    with one line), else at the default address, or at a free port beside it when another
    system holds the default one."""
    address = parse_web(text or DEFAULT_WEB)
    try:
        listener = bind(address)
    except OSError as exc:
        if text is not None or exc.errno != errno.EADDRINUSE:
            raise ValueError(f"--web {address.text} cannot be used ({exc.strerror}): "
                             "choose another HOST:PORT, or --no-web") from None
        listener = bind(WebAddress(address.host, 0))
        address = WebAddress(address.host, listener.getsockname()[1], address.port)
    return listener, address


def inherited_listener(fd: int) -> socket.socket:
    """The listening socket a supervisor opened and handed down as file descriptor ``fd``:
    held from the checks before anything starts until the run ends, so that no other
    process can take the port between the check and the console's start, nor between a
    console and its restarted successor."""
    listener = socket.socket(fileno=fd)
    if listener.type != socket.SOCK_STREAM:
        listener.close()
        raise ValueError(f"--listen-fd {fd}: not a listening TCP socket")
    return listener


def new_token(path: Path) -> str:
    """A fresh token, written to ``path`` readable by its owner only."""
    token = secrets.token_urlsafe(24)
    access.write_private(path, token + "\n")
    return token


def read_token(path: Path) -> str:
    """The token in ``path``; like a credentials file, one open to others is refused
    (ValueError with one line)."""
    try:
        mode = path.stat().st_mode
        token = path.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ValueError(f"console token {path}: {exc.strerror}") from None
    if mode & 0o077:
        raise ValueError(f"console token {path}: open to group or others (mode "
                         f"{stat.S_IMODE(mode):04o}); chmod 600 it")
    if len(token) < 16 or not token.isascii() or any(c.isspace() for c in token):
        raise ValueError(f"console token {path}: not a token")
    return token


def token_for(path: Path) -> str:
    """The token kept in ``path``, made there first if there is none yet."""
    return read_token(path) if path.exists() else new_token(path)
