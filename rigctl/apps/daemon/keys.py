"""CURVE keys for the daemon and its operators, and the allow-list that decides who gets in.

A key pair is two files in ZeroMQ's certificate format: `NAME.key` (public, safe to copy) and
`NAME.key_secret` (secret, mode 0600). The daemon has one pair; each operator has one pair and
gives the daemon's administrator the public file, which goes into the allow-list folder. With
keys configured, every daemon socket is a CURVE server and a ZAP authenticator admits only the
public keys found in that folder: a client with any other key fails the handshake and receives
nothing at all, not even `status`.

The folder is read again whenever its listing changes (polled every `ALLOW_LIST_POLL_S`): a key
added lets its operator in, a key removed keeps them out of new connections, and the daemon
refuses (`forbidden`) every request that still arrives on a connection made with a removed key.
"""

from __future__ import annotations

import logging
import os
import shutil
import threading
from pathlib import Path
from typing import Any

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from rigctl.core.errors import ConfigError

log = logging.getLogger(__name__)

ALLOW_LIST_POLL_S = 1.0


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


def _listing(folder: Path) -> tuple[Any, ...]:
    """What changes when a key file is added, removed or rewritten."""
    try:
        return tuple(sorted((p.name, st.st_mtime_ns, st.st_size)
                            for p in folder.glob("*.key") for st in [p.stat()]))
    except OSError:
        return ()


class CurveServer:
    """The daemon's CURVE identity plus the authenticator enforcing the allow-list, which it
    reads again when the folder changes. `allowed` holds the Z85 public keys let in now (what a
    connection's ZAP `User-Id` is)."""

    def __init__(self, context: zmq.Context[zmq.Socket[bytes]], secret_key_file: str | Path,
                 allowed_dir: str | Path) -> None:
        self.public, self.secret = load_secret(secret_key_file)
        self.allowed_dir = Path(allowed_dir)
        self.allowed: frozenset[bytes] = frozenset(allowed_public_keys(self.allowed_dir))
        if not self.allowed:
            log.warning("the allow-list %s is empty: no client can connect", self.allowed_dir)
        self._auth = ThreadAuthenticator(context, log=logging.getLogger(__name__ + ".zap"))
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(self.allowed_dir))
        log.info("CURVE on; %d operator key(s) allowed from %s", len(self.allowed),
                 self.allowed_dir)
        self._stop = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="allow-list", daemon=True)
        self._watcher.start()

    def _watch(self) -> None:
        seen = _listing(self.allowed_dir)
        while not self._stop.wait(ALLOW_LIST_POLL_S):
            now = _listing(self.allowed_dir)
            if now != seen:
                seen = now
                self.reload()

    def reload(self) -> None:
        """Read the allow-list folder again (a key that cannot be read keeps the old list)."""
        try:
            keys = frozenset(allowed_public_keys(self.allowed_dir))
        except ConfigError as err:
            log.error("the allow-list was not re-read: %s; the previous one stays", err)
            return
        self._auth.configure_curve(domain="*", location=str(self.allowed_dir))
        added, removed = len(keys - self.allowed), len(self.allowed - keys)
        self.allowed = keys
        log.warning("allow-list %s re-read: %d key(s) allowed (%d added, %d removed)",
                    self.allowed_dir, len(keys), added, removed)

    def admits(self, user_id: str | None) -> bool:
        """Whether a request's connection (its ZAP User-Id: the client's Z85 key) is allowed now."""
        return user_id is not None and user_id.encode() in self.allowed

    def secure(self, sock: zmq.Socket[bytes]) -> None:
        """Make `sock` (before bind) a CURVE server with the daemon's key."""
        sock.curve_secretkey = self.secret
        sock.curve_publickey = self.public
        sock.curve_server = True

    def stop(self) -> None:
        self._stop.set()
        self._watcher.join(timeout=2 * ALLOW_LIST_POLL_S)
        self._auth.stop()


def secure_client(sock: zmq.Socket[bytes], server_public_key: bytes, client_secret_file: str | Path) -> None:
    """Make `sock` (before connect) a CURVE client of a daemon with that public key."""
    public, secret = load_secret(client_secret_file)
    sock.curve_publickey = public
    sock.curve_secretkey = secret
    sock.curve_serverkey = server_public_key
