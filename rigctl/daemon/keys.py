"""CURVE keys for the daemon and its operators, and the allow-list that decides who gets in.

A key pair is two files in ZeroMQ's certificate format: `NAME.key` (public, safe to copy) and
`NAME.key_secret` (secret, mode 0600). The daemon has one pair; each operator has one pair and
gives the daemon's administrator the public file, which goes into the allow-list folder. With
keys configured, every daemon socket is a CURVE server and a ZAP authenticator admits only the
public keys found in that folder: a client with any other key fails the handshake and receives
nothing at all, not even `status`.
"""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from rigctl.errors import ConfigError

log = logging.getLogger(__name__)


def new_keypair(directory: str | Path, name: str) -> tuple[Path, Path]:
    """Write `NAME.key` and `NAME.key_secret` into `directory`; returns (public, secret) paths.
    Refuses to overwrite an existing pair."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    public, secret = directory / f"{name}.key", directory / f"{name}.key_secret"
    if public.exists() or secret.exists():
        raise ConfigError(f"a key pair named {name!r} already exists in {directory}")
    public_path, secret_path = zmq.auth.create_certificates(directory, name)
    os.chmod(secret_path, 0o600)
    return Path(public_path), Path(secret_path)


def load_secret(path: str | Path) -> tuple[bytes, bytes]:
    """(public, secret) Z85 keys from a `.key_secret` file."""
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as err:
        raise ConfigError(f"cannot read the secret key {path}: {err}") from None
    if secret is None:
        raise ConfigError(f"{path} holds no secret key (give the .key_secret file)")
    return public, secret


def load_public(path: str | Path) -> bytes:
    """The Z85 public key from a `.key` (or `.key_secret`) file."""
    try:
        public, _ = zmq.auth.load_certificate(str(path))
    except (OSError, ValueError) as err:
        raise ConfigError(f"cannot read the public key {path}: {err}") from None
    return public


def allow(public_key_file: str | Path, allowed_dir: str | Path) -> Path:
    """Copy an operator's public key into the allow-list folder; returns the new file."""
    load_public(public_key_file)  # refuse anything that is not a key
    if str(public_key_file).endswith(".key_secret"):
        raise ConfigError("give the operator's public .key file, never the secret one")
    allowed_dir = Path(allowed_dir)
    allowed_dir.mkdir(parents=True, exist_ok=True)
    target = allowed_dir / Path(public_key_file).name
    shutil.copyfile(public_key_file, target)
    return target


def allowed_public_keys(allowed_dir: str | Path) -> list[bytes]:
    """Every public key in the allow-list folder."""
    folder = Path(allowed_dir)
    if not folder.is_dir():
        raise ConfigError(f"the allow-list folder {folder} does not exist")
    return [load_public(p) for p in sorted(folder.glob("*.key"))]


class CurveServer:
    """The daemon's CURVE identity plus the authenticator enforcing the allow-list."""

    def __init__(self, context: zmq.Context, secret_key_file: str | Path,
                 allowed_dir: str | Path) -> None:
        self.public, self.secret = load_secret(secret_key_file)
        self.allowed_dir = Path(allowed_dir)
        n_allowed = len(allowed_public_keys(self.allowed_dir))
        if n_allowed == 0:
            log.warning("the allow-list %s is empty: no client can connect", self.allowed_dir)
        self._auth = ThreadAuthenticator(context, log=logging.getLogger(__name__ + ".zap"))
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(self.allowed_dir))
        log.info("CURVE on; %d operator key(s) allowed from %s", n_allowed, self.allowed_dir)

    def secure(self, sock: zmq.Socket) -> None:
        """Make `sock` (before bind) a CURVE server with the daemon's key."""
        sock.curve_secretkey = self.secret
        sock.curve_publickey = self.public
        sock.curve_server = True

    def stop(self) -> None:
        self._auth.stop()


def secure_client(sock: zmq.Socket, server_public_key: bytes, client_secret_file: str | Path) -> None:
    """Make `sock` (before connect) a CURVE client of a daemon with that public key."""
    public, secret = load_secret(client_secret_file)
    sock.curve_publickey = public
    sock.curve_secretkey = secret
    sock.curve_serverkey = server_public_key
