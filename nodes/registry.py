"""Discovery: which process offers which topic or service at which ZeroMQ address.

Nodes on one machine share a bus directory (``$DTX_BUS_DIR``, default
``/tmp/dtx-<uid>/<$DTX_DOMAIN or default>``). A publisher or service writes one small JSON
file per endpoint there; subscribers and clients look a name up and connect to what they
find, so a node names topics, never ports. Entries of dead processes are ignored and swept.
Chosen over a master process because there is nothing to start first and nothing to crash;
crossing machines uses endpoints named in the launch file instead (see ``nodes.security``).
"""
from __future__ import annotations

import dataclasses
import json
import os
import tempfile
import time
from pathlib import Path
from urllib.parse import quote, unquote

KINDS = ("topic", "service")
IPC_PATH_LIMIT = 100  # sockaddr_un holds 108 bytes; keep a margin


def default_bus_dir() -> Path:
    explicit = os.environ.get("DTX_BUS_DIR")
    if explicit:
        return Path(explicit)
    domain = os.environ.get("DTX_DOMAIN", "default")
    return Path(tempfile.gettempdir()) / f"dtx-{os.getuid()}" / domain


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
        for sub in (*KINDS, "nodes", "sock"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)

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
