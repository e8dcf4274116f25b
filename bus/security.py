"""CURVE authentication for endpoints that cross machines.

Keys are ZeroMQ certificate files (``zmq.auth.create_certificates``; ``dtx keys create``).
A server socket gets its secret key and accepts only clients whose public certificates lie
in ``authorized_keys_dir``; a client needs its own key pair and the server's public key.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator


class SecurityError(ValueError):
    """A key file is missing or unreadable."""


@dataclasses.dataclass(frozen=True)
class CurveConfig:
    """Key files for one node. ``secret_key_file`` is this node's ``.key_secret``;
    ``authorized_keys_dir`` holds the ``.key`` files of peers allowed to connect (servers);
    ``server_key_file`` is the public key of the server a client connects to."""

    secret_key_file: str
    authorized_keys_dir: str = ""
    server_key_file: str = ""


def _load(path: str, need_secret: bool) -> tuple[bytes, bytes | None]:
    if not Path(path).is_file():
        raise SecurityError(f"CURVE key file {path} not found (create keys with `dtx keys create DIR NAME`)")
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (ValueError, OSError) as exc:
        raise SecurityError(f"CURVE key file {path} is not a ZeroMQ certificate: {exc}") from exc
    if need_secret and secret is None:
        raise SecurityError(f"{path} holds no secret key (use the .key_secret file)")
    return public, secret


_authenticators: dict[int, ThreadAuthenticator] = {}


def secure_server(context: zmq.Context, sock: zmq.Socket, config: CurveConfig) -> str:
    """Make ``sock`` a CURVE server; returns its public key (Z85) for the registry."""
    public, secret = _load(config.secret_key_file, need_secret=True)
    if not Path(config.authorized_keys_dir).is_dir():
        raise SecurityError(f"authorized_keys_dir {config.authorized_keys_dir!r} is not a directory")
    authenticator = _authenticators.get(id(context))
    if authenticator is None:
        authenticator = ThreadAuthenticator(context)
        authenticator.start()
        _authenticators[id(context)] = authenticator
    authenticator.configure_curve(domain="*", location=config.authorized_keys_dir)
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_server = True
    return public.decode()


def secure_client(sock: zmq.Socket, config: CurveConfig, server_key: str = "") -> None:
    """Make ``sock`` a CURVE client of the server whose public key is given or in a file."""
    public, secret = _load(config.secret_key_file, need_secret=True)
    if not server_key:
        server_key = _load(config.server_key_file, need_secret=False)[0].decode()
    sock.curve_secretkey = secret
    sock.curve_publickey = public
    sock.curve_serverkey = server_key.encode()


def stop_authenticator(context: zmq.Context) -> None:
    """Stop ``context``'s authenticator thread, before the context itself goes."""
    authenticator = _authenticators.pop(id(context), None)
    if authenticator is not None:
        authenticator.stop()
