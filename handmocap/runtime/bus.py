"""The one bus: brokerless ZeroMQ PUB/SUB between node processes, with file-based discovery.

Wire: every message is three frames, `[topic + b"\\0", type name, msgpack payload]`. The
trailing NUL makes ZeroMQ's prefix subscription an exact topic match. A control type
`_eos` (payload: the publishing node's name, NUL, the eos_token of its node file) marks the end
of a publisher's stream; a subscriber honours it only with the token of the publisher it names.

Discovery: each node binds one XPUB socket (by default `ipc://<run dir>/<node>.pub`, so
nothing listens on the network) and writes `<run dir>/<node>.json` saying what it publishes
and subscribes; the file is rewritten every HEARTBEAT_S as the node's heartbeat. Subscribers
scan the run dir and connect straight to each publisher of a topic they want: no broker on
the data path. A node on another host is reached with an explicit `tcp://` endpoint
(`connect` in the launch file); its own socket listens on the network only when the launch
file gives it a `bind: tcp://...` endpoint.

Queues (bounded memory, nothing lost silently): each publisher has two sockets.
- The main one is lossy. Per connection, the publisher queues QUEUE_MESSAGES = 32 messages
  where it publishes images, else QUEUE_MESSAGES_SMALL = 1024, and the subscriber as many
  again (32 where images may come through its socket): at most 64 frames (59 MB of 640x480
  raw ones, about 3 MB of JPEG ones) or 2,048 small messages (a two-hand /hand/pose is
  ~2.7 kB: ~6 MB). A subscriber that falls further behind loses what comes next; a keep-all
  ('all') one counts the loss from the gaps in the header's seq (Node.stats["lost"]). The
  main path never waits for it.
- The lossless one (XPUB_NODROP, same bounds) serves 'lossless' subscribers, the recorder:
  when one of them is that far behind, the publisher waits, so a bag stays complete.
  It is bound on this host only (ipc/inproc); across hosts every subscriber is keep-all.
The sockets bind at the node's first send (zmq fixes a listener's queue when it binds, and by
then the node has said what it publishes); a `tcp://` bind is made at start, with 32.
An end of stream goes out on both, and once more on the lossless socket as a control message
(topic frame prefixed CONTROL) that every latest and keep-all subscriber takes on a socket of
its own: the copy in a full lossy queue may be dropped, that one is not. It carries the last
seq sent, so the subscriber waits for its data to catch up and counts a lost tail.
"""
from __future__ import annotations

import json
import os
import stat
import tempfile
import threading
import time
import weakref
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import zmq


EOS = b"_eos"
CONTROL = b"\0"   # topic-frame prefix of control messages (ends of stream), on the lossless socket
LARGE = 65536   # payloads above this are sent without a copy (zmq holds on to the sender's buffer)
HEARTBEAT_S = 0.5
QUEUE_MESSAGES = int(os.environ.get("HANDMOCAP_QUEUE", "32"))   # see Queues above
QUEUE_MESSAGES_SMALL = 1024   # a queue where no frame comes through it
RECONNECT_MS = 10   # a subscriber retries a publisher not bound yet (it binds at its first send) this often
WAIT_LOG_S = 5.0   # a publisher held by a lossless subscriber says so after this long
# the largest message part a subscriber socket where no image comes takes (ZMQ_MAXMSGSIZE; a
# two-hand /hand/pose is ~2.7 kB); where images may come, the codec's MAX_MESSAGE_BYTES. zmq
# reads the size first and drops the connection before reading a byte of a larger part, so an
# 80 MiB message costs nothing (the node makes that connection again: Subscriber.connect_again)
MAX_SMALL_MESSAGE_BYTES = 4 * 1024 * 1024
STALE_S = 5.0   # a node file whose heartbeat is older than this, or whose pid is gone, is dead


def queue_length(types) -> int:
    """A send or receive queue per connection (messages) for these message types (None: any)."""
    return QUEUE_MESSAGES if any(t in (None, "Image") for t in types) else QUEUE_MESSAGES_SMALL


class RunDirError(PermissionError):
    """A run dir that is not this user's own private folder (nothing may start in it)."""


def private_dir(path: Path) -> Path:
    """`path`, made (mode 0700) if missing, checked to be a folder of this user's that no one
    else may read or write and not a symlink: a predictable /tmp path could have been made
    first by another user, who could then read the graph's node files and feed it messages.
    RunDirError naming the path and what is wrong."""
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    st = os.lstat(path)
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise RunDirError(f"run dir {path} is {'a symlink' if stat.S_ISLNK(st.st_mode) else 'not a folder'}; "
                          f"remove it (or set HANDMOCAP_RUN_DIR to a private folder)")
    if st.st_uid != os.getuid():
        raise RunDirError(f"run dir {path} belongs to uid {st.st_uid}, not to you (uid {os.getuid()}): another "
                          f"user made it; remove it, or set HANDMOCAP_RUN_DIR to a private folder")
    if st.st_mode & 0o077:
        raise RunDirError(f"run dir {path} has mode {stat.S_IMODE(st.st_mode):o}: others may read or write it; "
                          f"chmod 700 {path} (or remove it)")
    return path


def run_dir(graph: str | None = None) -> Path:
    """Directory that holds one graph's sockets and node files, private to this user (0700,
    checked on every call: private_dir).

    $HANDMOCAP_RUN_DIR if set, else <tmp>/handmocap-<uid>/<graph> with graph from the
    argument, $HANDMOCAP_GRAPH or "default". Kept short: unix socket paths max out at 107 bytes.
    """
    if os.environ.get("HANDMOCAP_RUN_DIR"):
        d = Path(os.environ["HANDMOCAP_RUN_DIR"])
        d.parent.mkdir(parents=True, exist_ok=True)
        return private_dir(d)
    graph = graph or os.environ.get("HANDMOCAP_GRAPH", "default")
    base = private_dir(Path(tempfile.gettempdir()) / f"handmocap-{os.getuid()}")
    return private_dir(base / graph)


def topic_frame(topic: str) -> bytes:
    return topic.encode() + b"\0"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@dataclass
class NodeInfo:
    """What a node file says about one running node."""
    name: str
    pid: int
    endpoint: str
    publishes: dict = field(default_factory=dict)    # topic -> message type
    subscribes: dict = field(default_factory=dict)   # topic -> "latest" | "all" | "lossless"
    ready: bool = False
    lossless: str = ""           # the endpoint of its lossless socket (the recorder's; bus docstring)
    inproc: dict | None = None   # {endpoint, lossless, token}: also reachable in-process, from its container
    observer: bool = False   # tools (handtopic) that must not hold a graph's start
    ended: bool = False      # set by the launcher on a node that died for good: its streams are over
    heartbeat_ns: int = 0
    stats: dict = field(default_factory=dict)
    eos_token: str = ""      # this run's secret of the node: its end-of-stream carries it (Node._decode)
    closing: bool = False    # set before its end-of-stream goes out: its streams are ending normally
    heard_eos: list = field(default_factory=list)   # eos_tokens of the publishers whose end of stream it took in

    @property
    def alive(self) -> bool:
        return _pid_alive(self.pid) and time.time_ns() - self.heartbeat_ns < STALE_S * 1e9


def write_node_file(directory: Path, info: NodeInfo) -> None:
    """Atomically (re)write a node's file; its mtime and heartbeat_ns are the heartbeat."""
    info.heartbeat_ns = time.time_ns()
    tmp = directory / f".{info.name}.json.{os.getpid()}"
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)   # pids, endpoints: this user's only
    with os.fdopen(fd, "w") as f:
        f.write(json.dumps(info.__dict__))
    os.replace(tmp, directory / f"{info.name}.json")


def read_node_files(directory: Path, alive_only: bool = True) -> dict[str, NodeInfo]:
    nodes = {}
    for p in directory.glob("*.json"):
        try:
            info = NodeInfo(**json.loads(p.read_text()))
        except (OSError, ValueError, TypeError):
            continue   # being rewritten or foreign: the next scan sees it
        if not alive_only or info.alive:
            nodes[info.name] = info
    return nodes


# how long a closing publisher goes on flushing to a subscriber that is slow to read (one
# still busy finishing its own work on shutdown): within reason, lose nothing
PUBLISHER_LINGER_S = 10


class Publisher:
    """The two XPUB sockets of one node (see Queues above): `sock`, lossy, and `lossless`.
    XPUB (not PUB) so that the node sees subscriptions arrive and can hold its first message
    until every subscriber of the graph is connected."""

    def __init__(self, ctx: zmq.Context, endpoint: str, keys=None, lossless_endpoint: str | None = None):
        self._ctx, self._keys = ctx, keys
        self._inproc: list[str] = []
        self.sock = self.lossless = None   # made by open(): zmq fixes a listener's queue when it binds
        self.queue = 0                     # send queue per connection, messages (open)
        self.endpoint, self.lossless_endpoint = endpoint, lossless_endpoint or ""
        self.subscriptions: Counter[bytes] = Counter()
        self.joined: Counter[bytes] = Counter()     # subscriptions ever made, per prefix
        self._frames: dict[tuple, tuple] = {}   # (topic, type) -> their wire frames
        self.in_flight = 0   # large payloads sent and not yet released by zmq and every receiver
        self._landed = threading.Condition()
        self.stop = threading.Event()   # set by the node on SIGINT/SIGTERM: stop waiting for a lossless subscriber
        self.log = None                 # the node's logger (a wait for a lossless subscriber is logged)
        if endpoint.startswith("tcp://"):   # now: a taken port is an error at start (its queue: the short one)
            self.open(QUEUE_MESSAGES)

    def open(self, queue: int) -> None:
        """Make and bind the sockets, with a send queue of `queue` messages per connection
        (queue_length of what the node publishes); the node's first send, subscriber count or
        end of stream does it. Subscribers that connected before it did reconnect by themselves."""
        if self.sock is not None:
            return
        self.queue = queue
        self.sock = self._socket(self._ctx, lossy=True, queue=queue)
        self.lossless = self._socket(self._ctx, lossy=False, queue=queue)
        if self._keys is not None and self.endpoint.startswith("tcp://"):
            from handmocap.runtime import keys as curve
            curve.serve(self.sock, self._ctx, self._keys)
        for sock, where in ((self.sock, self.endpoint), (self.lossless, self.lossless_endpoint)):
            if not where:
                continue
            try:
                sock.bind(where)
            except zmq.ZMQError as e:
                self.sock.close(0)
                self.lossless.close(0)
                taken = e.errno == zmq.EADDRINUSE
                raise OSError(f"cannot listen on {where}: " + ("the address is in use (another graph or program "
                              "listens there, or a node of this graph still does)" if taken else e.strerror)) from None
        for where in self._inproc:
            self.sock.bind(where)
            self.lossless.bind(where + ".lossless")
        self.endpoint = self.sock.getsockopt_string(zmq.LAST_ENDPOINT)
        if self.lossless_endpoint:
            self.lossless_endpoint = self.lossless.getsockopt_string(zmq.LAST_ENDPOINT)

    @staticmethod
    def _socket(ctx: zmq.Context, lossy: bool, queue: int) -> zmq.Socket:
        sock = ctx.socket(zmq.XPUB)
        sock.setsockopt(zmq.SNDHWM, queue)
        sock.setsockopt(zmq.XPUB_VERBOSE, 1)  # count every subscriber, not each prefix once
        sock.setsockopt(zmq.LINGER, int(PUBLISHER_LINGER_S * 1000))   # flush a slow subscriber at close
        if not lossy:
            sock.setsockopt(zmq.XPUB_NODROP, 1)   # full: send says EAGAIN instead of dropping
        return sock

    def bind_inproc(self, endpoint: str, token: str) -> dict:
        """Also bind `inproc://...` (a container: the nodes of one process share one Context and
        reach each other without a socket); returns what the node file says about it."""
        self._inproc.append(endpoint)   # bound by open() (inproc may be connected to first)
        if self.sock is not None:
            self.sock.bind(endpoint)
            self.lossless.bind(endpoint + ".lossless")
        return {"endpoint": endpoint, "lossless": endpoint + ".lossless", "token": token}

    def poll_subscriptions(self) -> None:
        self.open(QUEUE_MESSAGES_SMALL)   # no-op once open; used directly, not by a Node (which opens it first)
        for sock in (self.sock, self.lossless):
            while True:
                try:
                    ev = sock.recv(zmq.NOBLOCK)
                except zmq.Again:
                    break
                if ev[:1] == b"\x01":
                    self.subscriptions[ev[1:]] += 1
                    self.joined[ev[1:]] += 1
                elif ev[:1] == b"\x00" and self.subscriptions[ev[1:]] > 0:
                    self.subscriptions[ev[1:]] -= 1

    def subscriber_count(self, topic: str) -> int:
        self.poll_subscriptions()
        t = topic_frame(topic)
        return sum(n for prefix, n in self.subscriptions.items() if t.startswith(prefix))

    def named_subscribers(self, topic: str) -> tuple[int, int]:
        """(connected now, joined so far) of the subscribers that asked for `topic` by name; a
        catch-all subscription (the recorder's, handtopic's) does not count. For a topic that
        costs work to compute: compute it while somebody asked for it, and send what goes once
        per connection when the joined count grows."""
        self.poll_subscriptions()
        t = topic_frame(topic)
        return self.subscriptions[t], self.joined[t]

    def send(self, topic: str, type_name: str, payload: bytes | memoryview, eos: bool = False) -> None:
        """One message, on both sockets; a payload over LARGE bytes (bytes or a read-only view
        such as `codec.encode_view` gives) goes without a copy: zmq holds on to it until it is
        sent to every outside subscriber and every receiver in this process has let go of it
        (`in_flight` counts those). Waits while a lossless subscriber is QUEUE_MESSAGES behind;
        `eos`: an end of stream, also sent on the control channel."""
        self.open(QUEUE_MESSAGES_SMALL)   # no-op once open (a Node opens it first, sized for what it publishes)
        frames = self._frames.get((topic, type_name))
        if frames is None:
            frames = self._frames[(topic, type_name)] = (topic_frame(topic), type_name.encode())
        if len(payload) > LARGE:   # zero-copy only pays for large frames
            # zmq keeps this array alive while the frame is in use (pyzmq drops it from its gc
            # thread once libzmq frees the message); a memoryview can't carry the finalizer.
            # (numpy imported here: the launcher, which sends nothing, runs without it)
            import numpy as np
            payload = np.frombuffer(payload, np.uint8)
            with self._landed:
                self.in_flight += 1
            weakref.finalize(payload, self._release)
        self.sock.send(frames[0], zmq.SNDMORE)
        self.sock.send(frames[1], zmq.SNDMORE)
        self.sock.send(payload, copy=len(payload) <= LARGE)
        self._send_waiting(self.lossless, frames, payload)   # no lossless subscriber: matches none, costs ~2 us
        if eos:   # the lossy copy is lost if that queue is full: this one is not (see Queues above)
            self._send_waiting(self.lossless, (CONTROL + frames[0], frames[1]), payload)

    def _send_waiting(self, sock: zmq.Socket, frames: tuple, payload) -> None:
        """Send on a XPUB_NODROP socket: while a subscriber's queue is full (EAGAIN on the first
        frame; the others then always fit), wait for it, logging once if it takes WAIT_LOG_S;
        gives up only when the node is told to stop."""
        start, logged = None, False
        while True:
            try:
                sock.send(frames[0], zmq.SNDMORE | zmq.NOBLOCK)
                break
            except zmq.Again:
                now = time.monotonic()
                start = start or now
                if self.stop.is_set() and now - start > 1.0:
                    return   # stopping (Ctrl-C): a stuck subscriber must not hold the node
                time.sleep(0.001 if now - start < 0.05 else 0.01)
                if now - start > WAIT_LOG_S and not logged and self.log is not None:
                    logged = True
                    self.log.warning("waiting for a lossless subscriber (the recorder?) that is %d messages "
                                     "behind on %s: this node goes at its pace", self.queue,
                                     frames[0].rstrip(b"\0").decode(errors="replace"))
        sock.send(frames[1], zmq.SNDMORE)
        sock.send(payload, copy=len(payload) <= LARGE)

    def _release(self) -> None:
        with self._landed:
            self.in_flight -= 1
            self._landed.notify_all()

    def wait_in_flight(self, limit: int, timeout_s: float) -> bool:
        """Block until fewer than `limit` large payloads are in flight (see `send`), at most
        `timeout_s`; returns whether they are."""
        with self._landed:
            return self._landed.wait_for(lambda: self.in_flight < limit, timeout_s)

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.lossless.close()


class Subscriber:
    """SUB sockets of one node, one per mode: `latest` (drained on every wake-up, freshest
    message per topic kept; ZMQ_CONFLATE is no use here, it breaks multipart messages), `all`
    (keep-all, losses counted) and `lossless` (connected to publishers' lossless sockets);
    with keys, one more per mode for tcp connections (CURVE applies to a socket's every
    connection); one more per mode for inproc:// connections, the nodes of its own container
    (`trusted`: what comes on it was encoded by this process's own code); and `control`, the
    ends of stream of the publishers it takes (Queues)."""

    MODES = ("latest", "all", "lossless")

    def __init__(self, ctx: zmq.Context, keys=None, in_container: bool = False):
        self.ctx = ctx
        self.in_container = in_container   # its mode's inproc socket is made with the others (subscribe)
        self.keys = keys   # handmocap.runtime.keys.Keys: tcp connections go through CURVE sockets of their own
        self.socks: dict[tuple[str, str], zmq.Socket] = {}   # (mode or "control", kind: see socket) -> socket
        self.trusted: set[zmq.Socket] = set()                # its inproc sockets
        self.monitors: dict[zmq.Socket, zmq.Socket] = {}      # socket -> its DISCONNECTED events (reconnect)
        self.prefixes: dict[str, list[bytes]] = {m: [] for m in self.MODES}
        self.connected: dict[str, set[str]] = {m: set() for m in (*self.MODES, "control")}
        self.frames: set[str] = set()   # modes whose socket may carry images (a short receive queue)
        self.made = 0   # sockets made so far: a receive loop armed with fewer polls the new ones too

    def socket(self, mode: str, kind: str = "") -> zmq.Socket:
        """The SUB socket of `mode` for connections of `kind`: "" (ipc, or tcp without keys),
        "tcp" (CURVE) or "inproc" (this process's own nodes)."""
        if (mode, kind) not in self.socks:
            s = self.ctx.socket(zmq.SUB)
            s.setsockopt(zmq.RCVHWM, QUEUE_MESSAGES if mode in self.frames else QUEUE_MESSAGES_SMALL)   # Queues
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.RECONNECT_IVL, RECONNECT_MS)
            s.setsockopt(zmq.MAXMSGSIZE, self.max_message_bytes(mode))
            self.monitors[s] = s.get_monitor_socket(zmq.EVENT_DISCONNECTED)
            if kind == "tcp":
                from handmocap.runtime import keys as curve
                curve.client(s, self.keys)
            elif kind == "inproc":
                self.trusted.add(s)
            for prefix in ([CONTROL] if mode == "control" else self.prefixes[mode]):
                s.subscribe(prefix)
            self.socks[(mode, kind)] = s
            self.made += 1
        return self.socks[(mode, kind)]

    def subscribe(self, topic: str | None, mode: str, frames: bool = True) -> None:
        """topic None: every topic (the recorder's 'record all'); `frames`: images may come
        (the receive queue is then QUEUE_MESSAGES long, else QUEUE_MESSAGES_SMALL)."""
        prefix = b"" if topic is None else topic_frame(topic)
        if frames:   # set before it connects: a connection's queue is fixed when it is made
            self.frames.add(mode)
        self.socket(mode)                  # made with the prefixes so far, then given this one
        if self.in_container:              # made now too (no re-arming of a loop that starts with it)
            self.socket(mode, "inproc")
        self.prefixes[mode].append(prefix)
        if mode != "lossless":   # made now too
            self.socket("control")
        for (m, _), s in self.socks.items():
            if m == mode:
                s.subscribe(prefix)
                if frames:
                    s.setsockopt(zmq.RCVHWM, QUEUE_MESSAGES)
                    s.setsockopt(zmq.MAXMSGSIZE, self.max_message_bytes(mode))

    def max_message_bytes(self, mode: str) -> int:
        """The ZMQ_MAXMSGSIZE of a socket of this mode (set before it connects, as its queue)."""
        from handmocap.runtime.codec import MAX_MESSAGE_BYTES   # (the codec's numpy: not in the launcher)
        return MAX_MESSAGE_BYTES if mode in self.frames else MAX_SMALL_MESSAGE_BYTES

    def ended_connections(self) -> list[tuple[zmq.Socket, str]]:
        """(socket, endpoint) of each connection that ended since the last call. libzmq makes
        one whose publisher exited or was respawned again by itself; one it ended over a
        message part above the socket's MAXMSGSIZE (a protocol error) it never retries, and
        that one alone is for connect_again: a disconnect drops what the connection delivered
        and was not read yet, a publisher's last messages and its end of stream."""
        ended = []
        for s, monitor in self.monitors.items():
            while monitor.poll(0, zmq.POLLIN):
                # imported on the first ended connection, not at every node's start: it imports asyncio (~40 ms)
                from zmq.utils.monitor import recv_monitor_message
                ended.append((s, recv_monitor_message(monitor)["endpoint"].decode()))
        return ended

    @staticmethod
    def connect_again(s: zmq.Socket, endpoint: str) -> None:
        """Make a connection libzmq ended for good (see ended_connections) again."""
        try:
            s.disconnect(endpoint)
        except zmq.ZMQError:
            pass   # libzmq forgot it already
        s.connect(endpoint)

    def connect_control(self, endpoint: str) -> None:
        """Take the control messages (ends of stream) of the publisher whose lossless socket
        this is (see Queues above)."""
        if endpoint not in self.connected["control"]:
            self.socket("control").connect(endpoint)
            self.connected["control"].add(endpoint)

    def connect(self, endpoint: str, mode: str) -> bool:
        if endpoint in self.connected[mode]:
            return False
        kind = "inproc" if endpoint.startswith("inproc://") else \
            "tcp" if self.keys is not None and endpoint.startswith("tcp://") else ""
        self.socket(mode, kind).connect(endpoint)
        self.connected[mode].add(endpoint)
        return True

    def close(self) -> None:
        for s, monitor in self.monitors.items():
            s.disable_monitor()
            monitor.close()
        for s in self.socks.values():
            s.close()
