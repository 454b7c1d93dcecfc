"""CURVE keys for `tcp://` endpoints: a graph on the network talks only to the hosts it names.

ZeroMQ's CURVE (elliptic-curve encryption and authentication, built into libzmq) on every tcp
bind and connect of a graph whose launch file has a `keys:` block:

    keys:
      secret: keys/host_a.key_secret   # this graph's key pair (handkeys made it)
      clients: keys/clients            # public keys (*.key) that may subscribe to our tcp binds
      server: keys/host_b.key          # the public key every tcp publisher we connect to must have

A publisher on a tcp bind is a CURVE server: a subscriber whose public key is not in
`clients` gets nothing (it is refused and the refusal logged). A subscriber connecting to a
tcp endpoint is a CURVE client that insists on `server`'s key: a process that took the port
with another key cannot feed it anything. Messages are encrypted on the wire. ipc and inproc
endpoints (one host, one user: the run dir is private) stay as they were.

    handkeys keys host_a host_b            # key pairs keys/host_a.key(_secret), keys/host_b.key(_secret)

Copy a host's `.key` (public) to the others; its `.key_secret` never leaves it.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import zmq
import zmq.auth

ENV = "HANDMOCAP_KEYS"   # the launcher passes a graph's `keys:` to its nodes as JSON
LOG = logging.getLogger("keys")


@dataclass(frozen=True)
class Keys:
    """Key files of one graph (paths; None: not given)."""
    secret: str | None = None
    clients: str | None = None
    server: str | None = None

    @classmethod
    def from_env(cls) -> "Keys | None":
        raw = os.environ.get(ENV)
        return cls(**json.loads(raw)) if raw else None

    def to_env(self) -> str:
        return json.dumps({"secret": self.secret, "clients": self.clients, "server": self.server})

    def check(self, binds: bool, connects: bool) -> list[str]:
        """What is missing or unreadable for a graph that binds and/or connects over tcp."""
        problems = []
        if binds or connects:
            problems += _readable_pair(self.secret, "secret")
        if binds:
            if not self.clients or not Path(self.clients).is_dir():
                problems.append(f"clients: {self.clients!r} is not a folder of public keys")
            elif not list(Path(self.clients).glob("*.key")):
                problems.append(f"clients: no public key (*.key) in {self.clients}")
        if connects:
            problems += _readable_public(self.server, "server")
        return problems


def _readable_pair(path, what) -> list[str]:
    try:
        public, secret = zmq.auth.load_certificate(str(path))
    except Exception as e:
        return [f"{what}: {path!r} is not a key pair ({e}); make one with `handkeys DIR NAME`"]
    return [] if secret else [f"{what}: {path} holds no secret key (the .key_secret file, not the .key)"]


def _readable_public(path, what) -> list[str]:
    try:
        zmq.auth.load_certificate(str(path))
    except Exception as e:
        return [f"{what}: {path!r} is not a public key file ({e})"]
    return []


class _AllowListed:
    """ZAP credentials check: the client's public key must be one of `clients`; a refusal is
    logged (once per key a minute) with the key, so a wrong key shows in the graph's output."""

    def __init__(self, folder: str):
        self.allowed = {zmq.auth.load_certificate(str(p))[0] for p in Path(folder).glob("*.key")}
        self.refused_at: dict[bytes, float] = {}

    def callback(self, domain, client_key: bytes) -> bool:
        if client_key in self.allowed:
            return True
        now = time.monotonic()
        if now - self.refused_at.get(client_key, -1e9) > 60:
            self.refused_at[client_key] = now
            LOG.warning("refused a subscriber whose public key %s is not among the graph's clients",
                        client_key.decode(errors="replace"))
        return False


_authenticators: dict[int, "zmq.auth.thread.ThreadAuthenticator"] = {}
_auth_lock = threading.Lock()


def _authenticator(ctx: zmq.Context, clients: str) -> None:
    """One ZAP handler per context (a container's nodes share one), allowing `clients`."""
    with _auth_lock:
        if id(ctx) in _authenticators:
            return
        from zmq.auth.thread import ThreadAuthenticator   # (it imports asyncio: ~35 ms of every start without CURVE)
        auth = ThreadAuthenticator(ctx, log=logging.getLogger("keys.zap"))
        auth.start()
        auth.configure_curve_callback("*", _AllowListed(clients))
        _authenticators[id(ctx)] = auth


def release(ctx: zmq.Context) -> None:
    """Stop the context's ZAP handler, if it has one (before ctx.term(): its thread's sockets
    would otherwise hold the termination up and then fail in their event loop)."""
    with _auth_lock:
        auth = _authenticators.pop(id(ctx), None)
    if auth is not None:
        auth.stop()


def serve(sock: zmq.Socket, ctx: zmq.Context, keys: Keys) -> None:
    """Make `sock` (about to bind tcp) a CURVE server that admits only the graph's clients."""
    _authenticator(ctx, keys.clients)
    public, secret = zmq.auth.load_certificate(keys.secret)
    sock.curve_publickey, sock.curve_secretkey = public, secret
    sock.curve_server = True


def client(sock: zmq.Socket, keys: Keys) -> None:
    """Make `sock` (about to connect tcp) a CURVE client that accepts only the server's key."""
    public, secret = zmq.auth.load_certificate(keys.secret)
    sock.curve_publickey, sock.curve_secretkey = public, secret
    sock.curve_serverkey = zmq.auth.load_certificate(keys.server)[0]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="handkeys", description="Make CURVE key pairs for a graph's tcp endpoints "
                                 "(the launch file's keys: block; see handmocap/runtime/keys.py).")
    ap.add_argument("folder", help="where to write NAME.key (public) and NAME.key_secret (secret, 0600)")
    ap.add_argument("names", nargs="+", help="one key pair per host or graph, e.g. robot laptop")
    args = ap.parse_args(argv)
    folder = Path(args.folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name in args.names:
        if (folder / f"{name}.key_secret").exists():
            print(f"handkeys: error: {folder / (name + '.key_secret')} exists; keep it or remove it first",
                  file=sys.stderr)
            return 1
        public, secret = zmq.auth.create_certificates(str(folder), name)
        os.chmod(secret, 0o600)
        print(f"{public}  (public: copy to the hosts that talk to {name})\n{secret}  (secret: stays on {name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
