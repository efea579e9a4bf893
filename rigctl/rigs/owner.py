"""One owner per rig: a process that drives a rig (the daemon, `rigctl execute`) holds an exclusive
lock on every one of its devices, so that a second one is refused before it connects to anything.

The locks are keyed by the devices (each actuator's and sensor's URL, as the rig kind lists them),
not by the rig file's name: two rig files naming the same supplies are the same rig, and a rig
that shares one device with another is refused too. Each device is a file in the lock folder
(`RIGCTL_LOCK_DIR`, else `/run/lock/rigctl`, the machine's lock folder, which a service's
`PrivateTmp=` does not hide as it hides /tmp; `/tmp/rigctl-locks` where there is no /run/lock),
each file writable by everyone so the daemon's user and an operator's see the same locks, held
with `flock`: the kernel drops a lock when its
process dies, however it dies, so a lock left behind by a crash is free to take at once, and the
file's content (who, pid, since, where it answers control requests) is only ever read while
the lock is held by the process it names.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

from rigctl.core.config import RigConfig
from rigctl.core.errors import ConfigError

TRIES = 5


class RigInUse(ConfigError):
    """Another process owns (a device of) the rig: nothing was connected (exit 2)."""


@dataclass(frozen=True)
class Holder:
    """Who owns a device: as the lock file says."""

    owner: str  # "rigctl daemon", "rigctl execute"
    pid: int
    since: str  # UTC, ISO 8601
    control: str | None = None  # where the owner answers control requests (e-stop), if anywhere

    def describe(self) -> str:
        return f"{self.owner}, pid {self.pid}, since {self.since}"


def lock_dir() -> Path:
    if os.environ.get("RIGCTL_LOCK_DIR"):
        return Path(os.environ["RIGCTL_LOCK_DIR"])
    return Path("/run/lock/rigctl") if Path("/run/lock").is_dir() else Path("/tmp/rigctl-locks")


def device_keys(rig: RigConfig) -> list[str]:
    """The rig's devices as lock keys: their URLs in one spelling (TCPIP:: or tcp://), sorted (the
    order locks are taken in, so two processes never wait on each other crosswise)."""
    from rigctl.core.transport import canonical_url
    from rigctl.rigs import rig_kind

    return sorted({canonical_url(d.url) for d in rig_kind(rig.rig.kind).devices(rig) if d.url})


def _path(key: str) -> Path:
    return lock_dir() / (hashlib.sha1(key.encode()).hexdigest()[:16] + ".lock")


class RigLock:
    """Held from `acquire()` (or `with`) to `release()`; refuses with `RigInUse` naming the holder."""

    def __init__(self, rig: RigConfig, owner: str, control: str | None = None) -> None:
        self.rig = rig
        self.holder = Holder(owner, os.getpid(), time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                             control)
        self._files: list[int] = []

    def acquire(self) -> RigLock:
        folder = lock_dir()
        try:
            if not folder.is_dir():
                folder.mkdir(parents=True, exist_ok=True)
                os.chmod(folder, 0o1777)  # whatever the umask (a unit's is 0027): every user's
        except OSError as err:
            raise ConfigError(f"cannot create the rig lock folder {folder}: {err.strerror}; set "
                              "RIGCTL_LOCK_DIR to a writable folder") from None
        try:
            for key in device_keys(self.rig):
                self._take(key)
        except BaseException:
            self.release()
            raise
        return self

    def _take(self, key: str) -> None:
        path = _path(key)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as err:
            raise ConfigError(f"cannot open the rig lock {path}: {err.strerror}; set "
                              "RIGCTL_LOCK_DIR to a folder every rigctl user can write") from None
        if os.fstat(fd).st_uid == os.getuid():
            os.fchmod(fd, 0o666)  # the next owner may be another user (the daemon's, an operator)
        for attempt in range(TRIES):  # a `holder_of` looking in holds it for a moment
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                held = _read(fd)
                if held is not None or attempt == TRIES - 1:
                    os.close(fd)
                    who = held.describe() if held is not None else "another process"
                    raise RigInUse(f"rig in use by {who} (device {key}); stop it first, or "
                                   "make it safe with `rigctl estop`") from None
                time.sleep(0.01)
        self._files.append(fd)
        self._write(fd, key)

    def _write(self, fd: int, key: str) -> None:
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({**self.holder.__dict__, "device": key}).encode(), 0)

    def name_control(self, endpoint: str) -> None:
        """Where the owner answers control requests, once it knows (a daemon binds first)."""
        self.holder = replace(self.holder, control=endpoint)
        for fd, key in zip(self._files, device_keys(self.rig)):
            self._write(fd, key)

    def release(self) -> None:
        while self._files:
            fd = self._files.pop()
            try:
                os.ftruncate(fd, 0)
            finally:
                os.close(fd)  # closing drops the flock

    def __enter__(self) -> RigLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()


def _read(fd: int) -> Holder | None:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 4096) or b"null")
        return Holder(data["owner"], int(data["pid"]), data["since"], data.get("control"))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def holder_of(rig: RigConfig) -> Holder | None:
    """Who owns the rig now (the first of its devices that is held), or None."""
    for key in device_keys(rig):
        path = _path(key)
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
            except BlockingIOError:  # held: its content names the holder
                held = _read(fd)
                if held is not None:
                    return held
            else:
                fcntl.flock(fd, fcntl.LOCK_UN)
        finally:
            os.close(fd)
    return None
