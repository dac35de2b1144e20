"""Client side of the control socket: hostd send | list | select | status | stop | quality."""

from __future__ import annotations

import errno
import json
import os
import socket
from pathlib import Path

from hostd.errors import HostdError


class ClientError(HostdError):
    """The daemon could not be reached or refused the request."""


def socket_path(config: str | None) -> str:
    """$HOSTD_SOCKET, else control.socket of `config` (resolved by config.resolve_path)."""
    if os.environ.get("HOSTD_SOCKET"):
        return os.environ["HOSTD_SOCKET"]
    from hostd.service.config import load

    return load(config).control.socket


def request(path: str, req: dict, payload: bytes = b"", timeout_s: float = 30.0) -> dict:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(timeout_s)
    try:
        s.connect(path)
    except FileNotFoundError:
        raise ClientError(f"no hostd socket at {path}: is `hostd run` running? (systemctl status hostd; "
                          "--config, HOSTD_CONFIG or HOSTD_SOCKET name another socket)") from None
    except ConnectionRefusedError:
        raise ClientError(f"hostd is not running on {path} (stale socket): start it "
                          "(systemctl start hostd)") from None
    except PermissionError:
        raise ClientError(f"permission denied on {path}: add yourself to the socket's group "
                          "(sudo usermod -aG hostd $USER, then log in again)") from None
    except OSError as e:
        if e.errno == errno.EACCES:
            raise ClientError(f"permission denied on {path}") from None
        raise ClientError(f"cannot reach hostd at {path}: {e}") from None
    try:
        with s, s.makefile("rb") as f:
            try:
                s.sendall((json.dumps(req) + "\n").encode() + payload)
            except (BrokenPipeError, ConnectionResetError):
                pass  # hostd answered early (a refusal) and closed: its reply is still readable
            line = f.readline()
    except OSError as e:
        raise ClientError(f"hostd at {path} closed the connection ({e})") from None
    if not line:
        raise ClientError(f"hostd at {path} gave no answer")
    try:
        reply = json.loads(line)
    except ValueError:
        raise ClientError(f"hostd at {path} gave a malformed answer") from None
    if not reply.get("ok"):
        raise ClientError(reply.get("error", "refused"))
    return reply


def send_file(path: str, file: str, name: str | None) -> dict:
    p = Path(file)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise ClientError(f"cannot read {file}: {e.strerror}") from None
    return request(path, {"cmd": "send", "name": name or p.stem, "size": len(data)}, data)
