"""Discovery: which process offers which topic or service at which ZeroMQ address.

Nodes on one machine share a bus directory (``$DTX_BUS_DIR``, default
``/tmp/dtx-<uid>/<$DTX_DOMAIN or default>``). A publisher or service writes one small JSON
file per endpoint there; subscribers and clients look a name up and connect to what they
find, so a node names topics, never ports. Entries of dead processes are ignored and swept.
The directory is private: created 0700, and refused when another user owns it or anyone but
its owner may write it (whoever can write there could answer this user's requests).
Chosen over a master process because there is nothing to start first and nothing to crash;
crossing machines uses endpoints named in the launch file instead (see ``bus.security``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import stat
import tempfile
import time
from pathlib import Path
from urllib.parse import quote, unquote

KINDS = ("topic", "service")
IPC_PATH_LIMIT = 100  # sockaddr_un holds 108 bytes; keep a margin


class BusDirectoryError(ValueError):
    """The bus directory is not private to this user; the message says why and what to do."""


def default_bus_dir() -> Path:
    explicit = os.environ.get("DTX_BUS_DIR")
    if explicit:
        return Path(explicit)
    domain = os.environ.get("DTX_DOMAIN", "default")
    return Path(tempfile.gettempdir()) / f"dtx-{os.getuid()}" / domain


def private_directory(path: Path) -> None:
    """Make ``path`` (mode 0700) unless it exists, then make sure it is this user's own: a
    real directory, owned by this user, writable by no one else. Otherwise BusDirectoryError:
    a directory another user made first (or may write) would let that user serve fake
    endpoints to this user's nodes."""
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    except OSError as exc:
        raise BusDirectoryError(f"cannot create the bus directory {path}: {exc}") from exc
    info = os.lstat(path)
    if not stat.S_ISDIR(info.st_mode):
        raise BusDirectoryError(
            f"bus directory {path} is not a directory (a symbolic link or a file is in its "
            "place); remove it, or choose another with DTX_BUS_DIR"
        )
    if info.st_uid != os.getuid():
        raise BusDirectoryError(
            f"bus directory {path} belongs to uid {info.st_uid}, not to you (uid {os.getuid()}): "
            "another user may be squatting it; remove it, or choose another with DTX_BUS_DIR"
        )
    if info.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise BusDirectoryError(
            f"bus directory {path} is writable by others (mode {stat.S_IMODE(info.st_mode):o}); "
            f"chmod 700 {path}, or choose another with DTX_BUS_DIR"
        )


@dataclasses.dataclass(frozen=True)
class Endpoint:
    kind: str  # "topic" or "service"
    name: str
    address: str
    node: str
    pid: int
    schema: str
    reply_schema: str = ""
    latched: bool = False
    curve_server_key: str = ""  # Z85 public key when the endpoint requires CURVE


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class Registry:
    def __init__(self, root: Path | None = None) -> None:
        self.root = Path(root) if root is not None else default_bus_dir()
        if root is None and not os.environ.get("DTX_BUS_DIR"):
            private_directory(self.root.parent)  # /tmp/dtx-<uid>, whose name anyone may take first
        else:
            self.root.parent.mkdir(parents=True, exist_ok=True)
        private_directory(self.root)
        for sub in (*KINDS, "nodes", "sock"):
            private_directory(self.root / sub)

    def socket_address(self, owner: str) -> str:
        path = self.root / "sock" / owner
        if len(str(path)) > IPC_PATH_LIMIT:
            raise ValueError(
                f"ipc path {path} is longer than {IPC_PATH_LIMIT} bytes; set DTX_BUS_DIR to a shorter directory"
            )
        return f"ipc://{path}"

    def advertise(self, endpoint: Endpoint) -> Path:
        folder = self.root / endpoint.kind / quote(endpoint.name, safe="")
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / f"{quote(endpoint.node, safe='')}-{endpoint.pid}-{time.monotonic_ns()}.json"
        _write_json_atomic(path, dataclasses.asdict(endpoint))
        return path

    def lookup(self, kind: str, name: str) -> list[Endpoint]:
        return self._read_folder(self.root / kind / quote(name, safe=""))

    def names(self, kind: str) -> dict[str, list[Endpoint]]:
        found = {}
        for folder in sorted((self.root / kind).iterdir()):
            endpoints = self._read_folder(folder)
            if endpoints:
                found[unquote(folder.name)] = endpoints
        return found

    def write_node_status(self, node: str, status: dict) -> None:
        _write_json_atomic(self.root / "nodes" / f"{quote(node, safe='')}.json", status)

    def live_node_pid(self, node: str) -> int | None:
        """The pid of the running process that holds the name ``node`` on this bus, if any."""
        status = _read_json(self.root / "nodes" / f"{quote(node, safe='')}.json")
        if status is None or status.get("status") == "stopped":
            return None
        pid = int(status.get("pid", 0))
        return pid if pid > 0 and pid_alive(pid) else None

    def node_statuses(self) -> list[dict]:
        statuses = []
        for path in sorted((self.root / "nodes").glob("*.json")):
            data = _read_json(path)
            if data is not None:
                data["alive"] = pid_alive(int(data.get("pid", 0)))
                statuses.append(data)
        return statuses

    def forget_process(self, pid: int) -> int:
        """Remove every endpoint ``pid`` advertised; how many. The launcher calls it when a
        child ends, so a client reading the directory (any language, docs/wire-protocol.md)
        never picks the entry of a worker killed with -9, even before a look-up sweeps it."""
        removed = 0
        for kind in KINDS:
            for path in (self.root / kind).glob(f"*/*-{pid}-*.json"):
                data = _read_json(path)
                if data is not None and data.get("pid") == pid:
                    path.unlink(missing_ok=True)
                    removed += 1
        return removed

    def _read_folder(self, folder: Path) -> list[Endpoint]:
        if not folder.is_dir():
            return []
        endpoints = []
        for path in sorted(folder.glob("*.json")):
            data = _read_json(path)
            try:
                endpoint = Endpoint(**data)  # type: ignore[arg-type]
            except TypeError:
                continue  # unreadable or from another version of dtx
            if pid_alive(endpoint.pid):
                endpoints.append(endpoint)
            else:
                path.unlink(missing_ok=True)
        return endpoints


def _write_json_atomic(path: Path, data: dict) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data))
    os.replace(tmp, path)


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, TypeError):
        return None  # being replaced or removed right now; the next look-up sees it
