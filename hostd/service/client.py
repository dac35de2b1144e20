"""Client side of the control socket: hostd send | list | select | status | stop | quality."""

from __future__ import annotations

import errno
import json
import os
import pwd
import socket
import stat
from pathlib import Path

from hostd.errors import HostdError
from hostd.service.control import peer_uid


class ClientError(HostdError):
    """The daemon could not be reached or refused the request (then `reply` is its answer)."""

    reply: dict | None = None


def socket_path(config: str | None) -> str:
    """$HOSTD_SOCKET, else control.socket of `config` (resolved by config.resolve_path)."""
    if os.environ.get("HOSTD_SOCKET"):
        return os.environ["HOSTD_SOCKET"]
    from hostd.service.config import load

    return load(config).control.socket


SERVICE_USER = "hostd"  # the unit's User=


def trusted_uids(path: str) -> set[int]:
    """Who may hold hostd's socket: root, ourselves, the service user, and the owner of the
    socket's directory when nobody else can write into it (where hostd refuses to bind otherwise)."""
    uids = {0, os.geteuid()}
    try:
        uids.add(pwd.getpwnam(SERVICE_USER).pw_uid)
    except KeyError:
        pass
    try:
        st = os.stat(Path(path).parent)
        if not st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
            uids.add(st.st_uid)
    except OSError:
        pass
    return uids


def check_peer(s: socket.socket, path: str) -> None:
    """SO_PEERCRED: refuse, before sending a byte, a socket held by a process of another user."""
    uid = peer_uid(s)
    if uid not in trusted_uids(path):
        try:
            who = pwd.getpwuid(uid).pw_name
        except KeyError:
            who = "unknown user"
        raise ClientError(f"refusing to talk to {path}: it is held by uid {uid} ({who}), not by hostd's "
                          f"user: nothing sent; stop that process and put control.socket in a directory "
                          f"only hostd's user owns (/run/hostd)")


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
        check_peer(s, path)
    except ClientError:
        s.close()
        raise
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
        err = ClientError(reply.get("error", "refused"))
        err.reply = reply  # (its "retry": true says the same request may succeed later)
        raise err
    return reply


def send_file(path: str, file: str, name: str | None) -> dict:
    p = Path(file)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise ClientError(f"cannot read {file}: {e.strerror}") from None
    return request(path, {"cmd": "send", "name": name or p.stem, "size": len(data)}, data)
