"""The node runtime: what every process of the graph is built on.

A node is a thin loop over plain functions, like a dora-rs Python node:

    node = Node("detector", params={"model": None})
    node.subscribe("/camera/image", "Image", mode="latest")
    node.advertise("/hand/keypoints", "HandKeypoints")
    for msg in node:                      # ends on SIGINT/SIGTERM or when all inputs ended
        hands = detect(msg.data["data"])  # plain function, knows nothing of the bus
        node.publish("/hand/keypoints", {"hands": hands, ...}, stamp_ns=msg.stamp_ns)

Parameters come from the launch file (env HANDMOCAP_PARAMS, JSON) or, when a node is run by
hand, from `name:=value` arguments; topic remaps from HANDMOCAP_REMAP. Received messages are
decoded and validated; a malformed or oversized one is dropped, counted in the node's
status and logged once per (topic, cause); it never stops the node.

End of stream: when a node closes, it sends `_eos` on every topic it advertised. A node
whose every input topic has ended (all its known publishers sent `_eos` or died) ends its
loop, closes and so passes the end downstream: that is how a finite replay drains the
graph and `handlaunch` returns.
"""
from __future__ import annotations

import gc
import json
import logging
import math
import os
import secrets
import signal
import sys
import threading
import time
import weakref
from collections import Counter, defaultdict
from dataclasses import dataclass
from pathlib import Path

import zmq

from handmocap.runtime import bus, codec
from handmocap.runtime import keys
from handmocap.runtime.keys import Keys
from handmocap.runtime.params import parse_cli_params

# an executor rewrites its nodes' files (Node.beat) once they are BEAT_EARLY of bus.HEARTBEAT_S
# old, when it has nothing to do; a node's heartbeat thread only once they are BEAT_LATE of it
BEAT_EARLY, BEAT_LATE = 0.7, 0.9
SCAN_S = 0.2          # how often subscribers look for new publishers
RESET_JUDGE_S = 1.0   # an ended connection whose publisher lives on this long after was ended by zmq
POLL_MS = 100         # longest a receive blocks before the loop looks at scans, ticks and stop
READY_TIMEOUT_S = 60  # how long a publisher waits for its graph to start
LOST_LOG_S = 10.0     # at most one line per topic this often about messages a keep-all input lost
STREAMS_KEPT = 4      # seq streams told apart per keep-all topic (publishers, restarts; Node._count_lost)
PUBLISHER_WAIT_S = 10.0   # how long a closing node waits for its subscribers to take in its end of stream
EOS_GRACE_S = 2.0     # an end of stream from the control channel waits this long for data still on its way


_EOS = bus.EOS
IDLE = object()   # Node.steps(): nothing more queued for now
_local = threading.local()   # a container's node thread: its own launch settings (see launch.run_container)


def _setting(key: str, default=None):
    """A launch setting of this node (HANDMOCAP_NODE_NAME, _PARAMS, _REMAP, _CONNECT, _BIND): the
    container's per-thread copy where the node runs in a container, else the environment."""
    own = getattr(_local, "settings", None)
    if own is not None:
        return own.get(key, default)
    return os.environ.get(key, default)


def shared_context() -> "zmq.Context | None":
    """The one zmq Context of a container process (None outside one): its nodes talk over inproc://."""
    return _SHARED["ctx"]


_SHARED = {"ctx": None, "token": None}   # set by launch.run_container
LARGE = bus.LARGE   # payloads above this go without copies (zero-copy send, receive into a zmq frame)


@dataclass
class Message:
    topic: str
    type: str
    data: dict          # decoded message, numpy arrays as read-only views
    payload: bytes | zmq.Frame   # the wire payload as received (large ones stay in zmq's frame)
    recv_ns: int

    @property
    def raw(self) -> bytes:
        """The wire payload, unchanged (the recorder stores this)."""
        return self.payload if isinstance(self.payload, bytes) else self.payload.bytes

    @property
    def stamp_ns(self) -> int:
        return self.data["header"]["stamp_ns"]


def check_file_param(node: str, key: str, value, keywords=(), made_by=None) -> None:
    """A param that names a file, or one of `keywords`, or null (a default): ValueError naming
    the node, the param, the path and (made_by) the command that makes such a file when no such
    file exists (for a node's `check_params`, which the launcher calls before any process starts)."""
    if value is not None and str(value) not in keywords and not Path(str(value)).is_file():
        raise ValueError(f"{node} param {key}: no such file {value}" + (f"; make it with `{made_by}`" if made_by else ""))


def check_number_param(node: str, key: str, value, minimum=None, positive=False, integer=False,
                       null=False) -> None:
    """A param that must be a number (an int with `integer`; at least `minimum`; above 0 with
    `positive`; or null where `null`): ValueError naming the node, the param and the value
    (for a node's `check_params`)."""
    if value is None and null:
        return
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (not integer or float(value).is_integer()) and (minimum is None or value >= minimum)
    if not (ok and (not positive or value > 0)):
        want = ("an integer" if integer else "a number") + (" > 0" if positive else "") + \
            (f" >= {minimum}" if minimum is not None else "") + (" or null" if null else "")
        raise ValueError(f"{node} param {key}: expected {want}, got {value!r}")


def check_jpeg_param(node: str, value) -> None:
    """jpeg_quality: null (raw images) or an integer 1 to 100."""
    check_number_param(node, "jpeg_quality", value, minimum=1, integer=True, null=True)
    if value is not None and value > 100:
        raise ValueError(f"{node} param jpeg_quality: expected 1 to 100 or null, got {value}")


def check_bool_param(node: str, key: str, value) -> None:
    """A param that must be true or false (a word such as `maybe` is no bool: YAML reads it as a
    string, which Python would take as true)."""
    if not isinstance(value, bool):
        raise ValueError(f"{node} param {key}: expected true or false, got {value!r}")


class Node:
    def __init__(self, name: str | None = None, params: dict | None = None, observer: bool = False,
                 argv: list[str] | None = None):
        self.name = _setting("HANDMOCAP_NODE_NAME") or name or Path(sys.argv[0]).stem
        self.log = logging.getLogger(self.name)
        if not logging.getLogger().handlers:
            logging.basicConfig(level=logging.INFO, stream=sys.stderr,
                                format="%(levelname)s %(message)s" if "HANDMOCAP_LAUNCH_ID" in os.environ
                                else f"[{self.name}] %(levelname)s %(message)s")
        given = json.loads(_setting("HANDMOCAP_PARAMS", "{}"))
        in_container = getattr(_local, "settings", None) is not None
        given.update(parse_cli_params(([] if in_container else sys.argv[1:]) if argv is None else argv))
        defaults = params or {}
        unknown = sorted(set(given) - set(defaults))
        if params is not None and unknown:
            raise ValueError(f"node {self.name!r} has no parameter(s) {', '.join(unknown)}; "
                             f"known: {', '.join(sorted(defaults)) or 'none'}")
        self.params = {**defaults, **given}
        self.remap = json.loads(_setting("HANDMOCAP_REMAP", "{}"))
        self.dir = bus.run_dir()
        # in a container, the process's one Context: its nodes reach each other over inproc://
        # (no socket, no copy through the kernel); elsewhere its own, which close() terms
        # without waiting on other nodes' sockets
        self._own_ctx = _SHARED["ctx"] is None
        self.ctx = zmq.Context() if self._own_ctx else _SHARED["ctx"]
        bind = _setting("HANDMOCAP_BIND") or f"ipc://{self.dir}/{self.name}.pub"
        curve_keys = Keys.from_env()   # CURVE on tcp endpoints (handmocap.runtime.keys), as the launch file says
        self.pub = bus.Publisher(self.ctx, bind, curve_keys, lossless_endpoint=f"ipc://{self.dir}/{self.name}.lossless")
        self.pub.log = self.log
        self.sub = bus.Subscriber(self.ctx, curve_keys, in_container=not self._own_ctx)
        self.extra_endpoints = json.loads(_setting("HANDMOCAP_CONNECT", "[]"))
        self.info = bus.NodeInfo(self.name, os.getpid(), self.pub.endpoint, observer=observer,
                                 eos_token=secrets.token_hex(8), lossless=self.pub.lossless_endpoint)
        self._eos_tokens: dict[str, str] = {}   # publisher name -> the token its end of stream must carry
        if not self._own_ctx:   # also bound in-process, for the container's other nodes
            self.info.inproc = self.pub.bind_inproc(f"inproc://{self.name}", _SHARED["token"])
        self._thread = threading.get_ident()   # the thread that runs this node (a container has several)
        self.types: dict[str, str] = {}            # subscribed topic -> expected type (None: any)
        self.seq: Counter[str] = Counter()
        self._last_sent: dict[str, int] = {}   # topic -> header seq of the last publish() (its end of stream says it)
        self.stats = {"received": Counter(), "published": Counter(), "dropped": Counter(),
                      "superseded": Counter(), "lost": Counter()}
        self._last_seq: dict[str, list] = {}    # topic -> last header seq of each stream on it (keep-all inputs)
        self._seen: dict[str, tuple] = {}        # topic -> (highest seq received, monotonic time of the last)
        self._last_input: Message | None = None  # the last message received
        self._eos_pending: dict[tuple, tuple] = {}   # (topic, sender) -> (last seq, heard at): control ends
        self._lost_logged: dict[str, tuple] = {}   # topic -> (time of its last loss line, lost then)
        self._received = self.stats["received"]
        self._logged_drops: set = set()
        self._names: dict[tuple, tuple] = {}   # (topic, type) frames -> their names
        self._large: set[str] = set()           # topics whose last payload was large
        self._zero_copy: dict = {}              # socket -> receive without copy (its last payload was large)
        self._publishers: dict[str, set[str]] = defaultdict(set)   # topic -> node names seen
        self._pub_pids: dict[str, int] = {}
        self._resets: dict[tuple, tuple] = {}   # (socket, endpoint) -> (when it ended, {publisher: pid then})
        self._ended: dict[str, set[str]] = defaultdict(set)        # topic -> names that sent EOS
        self._file_lock = threading.Lock()
        self._announced = 0.0   # when the node file was last written (monotonic s)
        self._next_scan = 0.0
        self._looked = False   # a scan ran since the receive loop last checked (an executor's, see scan)
        self._eos_seen = False
        self._graph_complete = False   # launched, and every node of the graph has announced itself
        self._graph_ready = "HANDMOCAP_LAUNCH_ID" not in os.environ
        self._stop = self.pub.stop   # SIGINT/SIGTERM: also ends a wait for a lossless subscriber
        _OPEN_NODES.add(self)
        self._validate_send = bool(os.environ.get("HANDMOCAP_VALIDATE_SEND"))
        self._trace = [] if os.environ.get("HANDMOCAP_TRACE") else None   # timing of every message (diagnostics)
        self._closed = False
        self._at_close = []
        self._old_handlers = {}
        if threading.current_thread() is threading.main_thread():   # signals reach the main thread only
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old_handlers[sig] = signal.signal(sig, lambda *_: self._stop.set())
        self._announce()
        threading.Thread(target=self._heartbeat, daemon=True).start()

    # -- declaring topics ---------------------------------------------------------------
    def resolve(self, topic: str) -> str:
        return self.remap.get(topic, topic)

    def subscribe(self, topic: str | None, type_name: str | None = None, mode: str = "latest") -> str:
        """Receive `topic` (None: every topic) in mode 'latest' (freshest only), 'all' (every
        message, unless this node falls a full queue behind (bus: Queues): then what it lost is
        counted in stats["lost"] and logged) or 'lossless' (every message: the publisher waits
        for this node; for the recorder, not for what must never slow the main path)."""
        if mode not in bus.Subscriber.MODES:
            raise ValueError(f"mode must be one of {', '.join(bus.Subscriber.MODES)}, not {mode!r}")
        topic = "*" if topic is None else self.resolve(topic)
        self.types[topic] = type_name
        self.info.subscribes[topic] = mode
        self.sub.subscribe(None if topic == "*" else topic, mode, frames=type_name in (None, "Image"))
        for ep in self.extra_endpoints:
            self.sub.connect(ep, mode)
        self._announce()
        return topic

    def advertise(self, topic: str, type_name: str) -> str:
        codec.schema(type_name)   # fail now on a type that does not exist
        topic = self.resolve(topic)
        self.info.publishes[topic] = type_name
        self._announce()
        return topic

    # -- publishing ---------------------------------------------------------------------
    def publish(self, topic: str, body: dict, stamp_ns: int | None = None, frame_id: str = "camera") -> None:
        """Send `body` (a message without header) on `topic`; the header is filled here:
        stamp_ns is the capture time of the frame this message derives from (default now)."""
        topic = self.remap.get(topic, topic)
        type_name = self.info.publishes.get(topic)
        if type_name is None:
            raise KeyError(f"{self.name}: publish on {topic!r} without advertise()")
        where = codec.non_finite(body, type_name)
        if where is not None:       # checked at the source: no subscriber ever gets it, no seq is spent
            last = self._last_input
            cause = f"from {last.topic} seq {last.data['header']['seq']} stamp {last.stamp_ns}" if last else "no input"
            self.drop(topic, "not-finite-out", f"{where} has NaN or inf ({cause})", what="a result not published")
            return
        seq = self.seq[topic]
        self.seq[topic] = seq + 1
        self._last_sent[topic] = seq
        msg = {"header": codec.header(seq, frame_id, stamp_ns), **body}
        if self._trace is not None:
            self._trace.append(("pub0", topic, msg["header"]["stamp_ns"], time.time_ns()))
        validate = type_name if self._validate_send else None
        if topic in self._large:   # like the last one, a frame: pack into a pooled buffer, send it as is
            payload = codec.encode_view(msg, validate)
        else:
            payload = codec.encode(msg, validate)
        if (len(payload) > LARGE) != (topic in self._large):
            self._large ^= {topic}
        self.publish_raw(topic, type_name, payload)

    def _open_publisher(self) -> None:
        """Bind our sockets (once), with a send queue sized for what we publish (bus: Queues)."""
        if self.pub.sock is None:
            self.pub.open(bus.queue_length(self.info.publishes.values()))

    def publish_raw(self, topic: str, type_name: str, payload: bytes) -> None:
        """Send an already-encoded payload unchanged (bag playback)."""
        if topic not in self.info.publishes:
            self.info.publishes[topic] = type_name
            self._announce()
        self._open_publisher()
        if not self._graph_ready:
            self.wait_for_graph()
        self.pub.send(topic, type_name, payload)
        self.stats["published"][topic] += 1
        if self._trace is not None:
            self._trace.append(("pub1", topic, None, time.time_ns()))

    def named_subscribers(self, topic: str) -> tuple[int, int]:
        """(connected now, joined so far) of the subscribers that asked for `topic` (after this
        node's remaps) by name, catch-all ones not counted: for a topic that costs work to
        compute only while someone wants it (bus.Publisher.named_subscribers)."""
        self._open_publisher()
        return self.pub.named_subscribers(self.resolve(topic))

    def wait_in_flight(self, limit: int, timeout_s: float = 1.0) -> bool:
        """Block until fewer than `limit` of this node's large messages (frames, sent without a
        copy) are still on their way: queued for or held by a subscriber. A source that sends
        as fast as the graph takes its frames (replay at rate 0) waits here before each one,
        so frames do not pile up in keep-all queues: bounded memory, and its pooled send
        buffers stay warm (a fresh 1 MB buffer per frame costs ~0.6 ms of page faults, with
        the interpreter lock held). Returns False after `timeout_s` (a stuck subscriber
        slows such a source down, never stops it)."""
        return self.pub.wait_in_flight(limit, timeout_s)

    def wait_for_graph(self) -> None:
        """Hold the first message until the launcher says every node is up and every node
        that subscribes to our topics is connected, so a finite source loses no frame."""
        self.ready()
        launch_id = os.environ.get("HANDMOCAP_LAUNCH_ID")
        deadline = time.monotonic() + READY_TIMEOUT_S
        while launch_id and not (self.dir / f"{launch_id}.ready").exists():
            if self._stop.is_set() or time.monotonic() > deadline:
                break
            time.sleep(0.01)
        missing = self.wait_for_subscribers(10.0)
        if missing:
            self.log.warning("starting without all subscribers connected: %s", missing)
        self._graph_ready = True

    def wait_for_subscribers(self, timeout_s: float) -> dict:
        """Block until every node of the graph that subscribes to one of our topics (or to
        every topic) is connected to us, at most `timeout_s`; returns {topic: "have/want"}
        still missing. Observers (handtopic) are not waited for."""
        self._open_publisher()
        deadline = time.monotonic() + timeout_s
        launched = self._launched_subscribers()
        while True:
            files = bus.read_node_files(self.dir, alive_only=launched is None)
            nodes = {n: i for n, i in files.items() if not i.ended and not i.observer and n != self.name}
            missing = {}
            for topic in self.info.publishes:
                if launched is not None:   # the graph's own list: a busy node's stale heartbeat can't hide it
                    want = sum(1 for t in (topic, "*") for n in launched.get(t, ()) if n in nodes)
                else:
                    want = sum(1 for n in nodes.values() for t in n.subscribes if t in (topic, "*"))
                have = self.pub.subscriber_count(topic)
                if have < want:
                    missing[topic] = f"{have}/{want}"
            if not missing or time.monotonic() > deadline or self._stop.is_set():
                return missing
            time.sleep(0.005)

    # -- receiving ----------------------------------------------------------------------
    def ok(self) -> bool:
        return not self._stop.is_set()

    def ready(self) -> None:
        """Mark this node as set up (the launcher starts sources once every node is)."""
        if not self.info.ready:
            # everything allocated while setting up (modules, models) lives as long as the node:
            # out of the collector's sight, its collections stay short on the data path
            gc.freeze()
            self.info.ready = True
            self._scan(force=True)
            self._announce()

    def __iter__(self):
        return self.events()

    def events(self, timeout: float | None = None):
        """Yield received Messages; with `timeout` (s), yield None when nothing came in that
        long (a tick for periodic work). Ends on shutdown or when every input has ended.

        Latency: a message is decoded and yielded as soon as the blocking receive returns it;
        the bookkeeping (discovery scans, end-of-stream checks, ticks) runs after the consumer
        comes back for the next one. With one subscription socket (the usual case) the loop
        blocks in recv itself (RCVTIMEO), with two it polls both."""
        return self._events(timeout, block=True)

    def steps(self):
        """events() that never blocks, for an executor that runs several nodes in one thread
        (handmocap.runtime.executor): yields the Messages queued now, then IDLE, and again on the
        next call; ends as events() does. Its discovery scans are the executor's to run, with
        `scan`, when no node has work: a scan costs 0.3-1 ms (the node files read), and run
        on a step it would land on the frame that woke the executor."""
        return self._events(None, block=False)

    def scan(self) -> None:
        """Look for new publishers now if a scan is due (every SCAN_S): what a steps() loop
        leaves to its executor, which calls it when it is about to wait."""
        self._scan()

    def scan_due(self) -> bool:
        return time.monotonic() >= self._next_scan

    def scan_overdue(self) -> bool:
        """A scan is due for SCAN_S already (an executor that never waits runs it anyway)."""
        return time.monotonic() >= self._next_scan + SCAN_S

    def sockets(self) -> list:
        """The zmq sockets this node receives on (an executor polls them)."""
        return list(self.sub.socks.values())

    def at_close(self, fn) -> None:
        """Call fn() when the node closes, before its end of stream goes out (final stats)."""
        self._at_close.append(fn)

    def _arm(self, block):
        """What a receive loop reads: {socket: "latest" or "all"} (keep-all, lossless and
        control sockets are read alike, tcp and inproc ones as their mode's); a Poller over
        them, or with one socket None (the loop then blocks in recv: RCVTIMEO); that one
        socket and its mode (None, None without sockets); the sockets made so far."""
        socks = {s: "latest" if mode == "latest" else "all" for (mode, _), s in self.sub.socks.items()}
        poller = None
        if len(socks) == 1:
            next(iter(socks)).setsockopt(zmq.RCVTIMEO, POLL_MS if block else 0)
        elif socks:
            poller = zmq.Poller()
            for s in socks:
                poller.register(s, zmq.POLLIN)
        return (socks, poller, *next(iter(socks.items()), (None, None)), self.sub.made)

    def _events(self, timeout, block):
        self.ready()
        socks, poller, only, only_mode, armed = self._arm(block)
        trusted = self.sub.trusted   # inproc: this container's nodes (decoded without the checks, _decode)
        last = time.monotonic()
        idle_since = None
        while not self._stop.is_set():
            if self._eos_pending:
                self._settle_eos(idle_since)
            if block:   # after the consumer's work on the last message: off the message's path
                self._scan()
            if self._looked or self._eos_seen:
                self._looked = self._eos_seen = False
                if not self.info.observer and self._inputs_ended():
                    break
                if self.sub.made != armed:   # a publisher found on a new kind of connection (tcp with keys)
                    socks, poller, only, only_mode, armed = self._arm(block)
            got = False
            if poller is None:
                try:
                    frames = self._recv(only, 0) if socks else None
                except zmq.Again:   # RCVTIMEO: nothing for POLL_MS (or now, when not blocking)
                    frames = None
                if frames is None:
                    if not socks and block:
                        self._stop.wait(POLL_MS / 1000)
                    batches = ()
                elif only_mode == "all":   # keep-all: straight from the receive to the consumer
                    # not blocking (an executor's turn): what is queued now, no more, so a
                    # busy input can't keep the nodes after this one waiting
                    queued = () if block else list(self._pending(only))
                    msg = self._decode(frames, only in trusted)
                    if msg is not None:
                        got = True
                        yield msg
                    # then whatever queued meanwhile
                    batches = ((self._pending(only) if block else queued, only in trusted),)
                else:
                    batches = ((self._drain_latest(only, frames), only in trusted),)
            else:
                batches = [(self._drain_latest(s) if socks[s] == "latest" else
                            (self._pending(s) if block else list(self._pending(s))), s in trusted)
                           for s, _ in poller.poll(POLL_MS if block else 0)]
            for batch, from_here in batches:
                for frames in batch:
                    msg = self._decode(frames, from_here)
                    if msg is not None:
                        got = True
                        yield msg
            if got:
                last = time.monotonic()
                idle_since = None
            else:
                idle_since = idle_since or time.monotonic()
            if not got and timeout is not None and time.monotonic() - last >= timeout:
                last = time.monotonic()
                yield None
            if not block:
                yield IDLE

    def _recv(self, s: zmq.Socket, flags: int = zmq.NOBLOCK) -> list:
        """One multipart message. Where the last payload on this socket was large (frames), the
        payload stays in zmq's frame (no copy; decode reads it in place); else all bytes."""
        if not self._zero_copy.get(s):
            frames = s.recv_multipart(flags)
            if len(frames[-1]) > LARGE:
                self._zero_copy[s] = True
            return frames
        frames = s.recv_multipart(flags, copy=False)
        payload = frames[-1]
        if len(payload) <= LARGE:
            self._zero_copy[s] = False
            payload = payload.bytes
        return [f.bytes for f in frames[:-1]] + [payload]

    def _pending(self, s: zmq.Socket, limit: int = 256):
        """Queued messages one by one (keep-all), at most `limit` before polling again."""
        for _ in range(limit):
            if not s.getsockopt(zmq.EVENTS) & zmq.POLLIN:
                return
            yield self._recv(s)

    def _drain_latest(self, s: zmq.Socket, first: list | None = None) -> list:
        """Read everything queued, keep the freshest message per topic (end-of-stream marks are
        kept, after the data they follow); `first`: one already received."""
        latest, eos = {}, []
        frames = first
        while frames is not None or s.getsockopt(zmq.EVENTS) & zmq.POLLIN:
            if frames is None:
                frames = self._recv(s)
            if len(frames) == 3 and frames[1] == bus.EOS:
                eos.append(frames)
            else:
                if frames[0] in latest:
                    self.stats["superseded"][frames[0].rstrip(b"\0").decode(errors="replace")] += 1
                latest[frames[0]] = frames
            frames = None
        return list(latest.values()) + eos

    def _decode(self, frames: list, trusted: bool = False) -> Message | None:
        """The Message of one received multipart message, or None (an end of stream, or a
        message dropped and counted). `trusted`: it came over inproc:// from a node of this
        container, whose payload this process encoded itself: codec.decode_trusted, without
        the schema, NaN and stamp checks every message from another process gets."""
        if len(frames) != 3:
            return self.drop("?", "frames", f"{len(frames)} frames, expected 3")
        topic_b, type_b, payload = frames
        names = self._names.get((topic_b, type_b))
        if names is None:
            names = self._names[(topic_b, type_b)] = (topic_b.rstrip(b"\0").decode(errors="replace"),
                                                      type_b.decode(errors="replace"))
            if len(self._names) > 4096:   # topic and type names of garbage: don't grow without end
                self._names.clear()
        topic, type_name = names
        if type_b == _EOS:
            control = topic.startswith("\0")   # its copy on the control channel (bus: Queues)
            topic = topic.lstrip("\0")
            sender, _, rest = bytes(payload).decode(errors="replace").partition("\0")
            token, _, last_seq = rest.partition("\0")
            if sender not in self._eos_tokens and self.extra_endpoints:
                return None   # a publisher on another host (connect:): its end does not end this node
            if not token or self._eos_tokens.get(sender) != token:   # not from the publisher it names
                return self.drop(topic, "forged-eos", f"an end of stream that says it is from {sender!r} "
                                  f"but lacks that node's token", "an end of stream")
            if sender in self._ended[topic]:
                return None   # heard already, on the other path
            last = int(last_seq) if last_seq.isdigit() else None
            if control and self._mode(topic) != "lossless":   # may overtake its data: wait for it
                self._eos_pending[(topic, sender)] = (last, time.monotonic())
            else:
                self._end_input(topic, sender, last)
            return None
        want = self.types[topic] if topic in self.types else self.types.get("*")
        if want is not None and want != type_name:
            return self.drop(topic, "type", f"got {type_name}, expected {want}")
        try:
            data = (codec.decode_trusted if trusted else codec.decode)(
                payload if isinstance(payload, bytes) else payload.buffer, type_name)
        except codec.MalformedMessage as e:
            return self.drop(topic, e.reason, str(e))
        self._received[topic] += 1
        if "header" in data:
            seq = data["header"]["seq"]
            self._seen[topic] = (max(seq, self._seen.get(topic, (seq, 0))[0]), time.monotonic())
            if self._mode(topic) == "all":
                self._count_lost(topic, data["header"])
        msg = Message(topic, type_name, data, payload, time.time_ns())
        if "header" in data:
            self._last_input = msg          # what a non-finite result is blamed on (publish)
        if self._trace is not None:
            self._trace.append(("recv", topic, msg.stamp_ns, msg.recv_ns))
        return msg

    def _mode(self, topic: str) -> str | None:
        return self.info.subscribes.get(topic) or self.info.subscribes.get("*")

    def _end_input(self, topic: str, sender: str, last: int | None) -> None:
        """`sender`'s stream on `topic` is over; `last`: the seq of its last message, if known
        (a keep-all input counts what it lost after the last one that came)."""
        self._eos_pending.pop((topic, sender), None)
        self._ended[topic].add(sender)
        self._eos_seen = True
        token = self._eos_tokens.get(sender)   # this run of it: a respawned publisher has a new one
        if token and token not in self.info.heard_eos:   # its publisher waits for this before it closes its sockets
            self.info.heard_eos.append(token)
            self._announce()
        if "*" in self.info.subscribes:   # an every-topic subscription hears the end per topic
            self._ended["*"].add(sender)
        if last is not None and self._mode(topic) == "all":
            self._count_lost(topic, {"seq": last + 1}, last=self._seen.get(topic, (-1, 0))[0])

    def _settle_eos(self, idle_since: float | None) -> None:
        """Ends of stream heard on the control channel take effect once the data caught up
        (its last seq came) or, with nothing queued, after EOS_GRACE_S (the rest was lost)."""
        now = time.monotonic()
        for (topic, sender), (last, heard) in list(self._eos_pending.items()):
            caught_up = last is not None and self._seen.get(topic, (-1, 0))[0] >= last
            if caught_up or (idle_since is not None and now - max(idle_since, heard) >= EOS_GRACE_S):
                self._end_input(topic, sender, last)

    def _count_lost(self, topic: str, header: dict, last: int | None = None) -> None:
        """A keep-all input's gap in the header's seq is what the bus dropped for this node
        (it fell a full queue behind, bus: Queues): counted in stats["lost"], logged at most every
        LOST_LOG_S per topic, with the jump seen. `last`: the seq before this one (an end of
        stream's last seq against the last one received).

        A publisher numbers each topic's messages 0, 1, 2, ... whatever their frame_id, and a
        topic may have several publishers (or one that restarted, or a stray message): a seq
        continues the stream whose last seq is the closest below it, and a seq at or below
        every stream's starts another one (STREAMS_KEPT kept). So a stray seq 0 or a restart is
        no loss, and neither is the old stream going on after it."""
        seq = header["seq"]
        if last is None:
            streams = self._last_seq.setdefault(topic, [])
            below = [s for s in streams if s < seq]
            last = max(below) if below else None
            if last is not None:
                streams.remove(last)
            streams.append(seq)
            del streams[:-STREAMS_KEPT]
        if last is None or seq <= last + 1:
            return
        lost = self.stats["lost"]
        lost[topic] += seq - last - 1
        now = time.monotonic()
        logged_at, logged_count = self._lost_logged.get(topic, (-math.inf, 0))
        if now - logged_at >= LOST_LOG_S:
            self._lost_logged[topic] = (now, lost[topic])
            self.log.warning("lost %d messages of %s (%d in all; the last gap: seq %d after %d): this node is slower "
                             "than its input and fell a full queue behind (bus: Queues); subscribe 'latest' to "
                             "take the freshest only", lost[topic] - logged_count, topic, lost[topic], seq, last)

    def drop(self, topic: str, reason: str, detail: str, what: str = "a malformed message") -> None:
        """Count one message of `topic` not taken (stats["dropped"], "topic:reason", shown in the
        node status) and log the first of each (topic, reason) with `detail`; None."""
        self.stats["dropped"][f"{topic}:{reason}"] += 1
        if (topic, reason) not in self._logged_drops:
            self._logged_drops.add((topic, reason))
            self.log.warning("dropped %s on %s (%s); further drops of this kind are only counted "
                             "in the node status", what, topic, detail[:300])
        return None

    def handle(self, handler, msg: Message) -> None:
        """handler(msg), where an exception drops that message only: counted per topic and
        cause ("handler-<Exception>") in the node status, logged once with its traceback, and
        the node goes on with the next message (one bad input must not stop a graph)."""
        try:
            handler(msg)
        except Exception as e:
            reason = f"handler-{type(e).__name__}"
            if (msg.topic, reason) not in self._logged_drops:
                self.log.warning("its handler failed on a message of %s", msg.topic, exc_info=True)
            self.drop(msg.topic, reason, f"{type(e).__name__}: {e}", "a message its handler failed on")

    # -- discovery and end of stream --------------------------------------------------------
    def _scan(self, force: bool = False) -> bool:
        """Connect to new publishers (every SCAN_S); returns whether it looked."""
        now = time.monotonic()
        if not force and now < self._next_scan:
            return False
        self._next_scan = now + SCAN_S
        self._looked = True
        if not self.info.subscribes:
            return True
        # checked before reading the node files: once the launcher wrote it, every node of the
        # graph had announced itself, so this scan sees every publisher there will be
        launch_id = os.environ.get("HANDMOCAP_LAUNCH_ID")
        ready_file = self.dir / f"{launch_id}.ready" if launch_id else None
        graph_complete = ready_file is not None and ready_file.exists()
        if graph_complete and not self._graph_complete:
            self._add_graph_publishers(ready_file)
        files = bus.read_node_files(self.dir, alive_only=False)
        self._judge_resets(files, now)
        for info in files.values():
            if info.name == self.name or not info.publishes:
                continue
            if info.ended:   # died for good (the launcher says so): as if it had sent end-of-stream
                for topic in self.info.subscribes:
                    if topic == "*" or topic in info.publishes:
                        self._ended[topic].add(info.name)
                continue
            if not info.alive:   # crashed, maybe to be respawned: its stream is not over
                continue
            endpoints = {"latest": info.endpoint, "all": info.endpoint, "lossless": info.lossless or info.endpoint}
            if info.inproc and info.inproc.get("token") == _SHARED["token"] and not self._own_ctx:
                # same container: in-process, not through a socket
                endpoints = {"latest": info.inproc["endpoint"], "all": info.inproc["endpoint"],
                             "lossless": info.inproc.get("lossless", info.inproc["endpoint"])}
            self._eos_tokens[info.name] = info.eos_token
            if self._pub_pids.get(info.name) != info.pid:   # new, or respawned: its stream reopens
                self._pub_pids[info.name] = info.pid
                for ended in self._ended.values():
                    ended.discard(info.name)
                for key in [k for k in self._eos_pending if k[1] == info.name]:
                    del self._eos_pending[key]
            for topic, mode in self.info.subscribes.items():
                if topic == "*" or topic in info.publishes:
                    self.sub.connect(endpoints[mode], mode)
                    if mode != "lossless" and endpoints["lossless"] != endpoints[mode]:
                        self.sub.connect_control(endpoints["lossless"])   # its ends of stream, never dropped
                    self._publishers[topic].add(info.name)
        self._graph_complete = self._graph_complete or graph_complete
        return True

    def _judge_resets(self, files: dict, now: float) -> None:
        """A connection that ended (bus.Subscriber.ended_connections) whose publisher, the very
        process it was then (pid), still lives RESET_JUDGE_S later, before its end of stream,
        was ended by zmq over a message part above the socket's size bound: dropped unread,
        counted and logged as such, and the connection made again (libzmq will not). A
        publisher that exits, or is killed and respawned (a new pid), ends its connections
        too: no fault, and libzmq makes them again itself."""
        for s, endpoint in self.sub.ended_connections():
            at_reset = {i.name: i.pid for i in files.values() if endpoint in (i.endpoint, i.lossless)}
            self._resets.setdefault((s, endpoint), (now, at_reset))
        for (s, endpoint), (since, at_reset) in list(self._resets.items()):
            if now - since < RESET_JUDGE_S:
                continue
            del self._resets[(s, endpoint)]
            for name, pid in at_reset.items():
                info = files.get(name)
                if info is not None and info.pid == pid and info.alive and not info.ended \
                        and not any(name in names for names in self._ended.values()):
                    self.sub.connect_again(s, endpoint)
                    self.drop("?", "oversized-unread", f"{name} sent a message part over this socket's bound "
                              f"of {codec.MAX_MESSAGE_BYTES} bytes (images) or {bus.MAX_SMALL_MESSAGE_BYTES} "
                              f"(others); zmq refused it before reading it and the connection was made again",
                              "an oversized message")

    def _launched_subscribers(self) -> dict | None:
        """{topic: [node names]} of the launched graph's subscribers (from the launcher's ready
        file), or None outside a launched graph or before it is up."""
        launch_id = os.environ.get("HANDMOCAP_LAUNCH_ID")
        try:
            return json.loads((self.dir / f"{launch_id}.ready").read_text())["subscribers"] if launch_id else None
        except (OSError, ValueError, KeyError):
            return None

    def _add_graph_publishers(self, ready_file: Path) -> None:
        """The launcher's list of the graph's publishers per topic (written once every node was
        up): inputs that will get data, and whose end-of-stream to wait for."""
        try:
            publishers = json.loads(ready_file.read_text())["publishers"]
        except (OSError, ValueError, KeyError):
            return
        for topic, names in publishers.items():
            for sub_topic in self.info.subscribes:
                if sub_topic in ("*", topic):
                    self._publishers[sub_topic].update(n for n in names if n != self.name)

    def _inputs_ended(self) -> bool:
        """Every input that has publishers has heard end-of-stream from all of them (or the
        launcher marked the publisher as dead for good). In a launched graph, an input that no
        node of the graph publishes will never get data and counts as ended; outside one, a
        publisher may still come, so such a node waits."""
        if "HANDMOCAP_LAUNCH_ID" in os.environ and not self._graph_complete:
            return False   # until the launcher's list of publishers is in, some may be unknown yet
        topics = [t for t in self.info.subscribes if self._publishers.get(t)]
        if not topics and (not self._graph_complete or self.extra_endpoints):
            return False   # a publisher may still come (or lives on another host: connect:)
        return all(self._publishers[t] <= self._ended[t] for t in topics)

    # -- status -------------------------------------------------------------------------
    def _announce(self) -> None:
        with self._file_lock:
            if self._closed:
                return
            self._announced = time.monotonic()
            try:
                self.info.stats = {k: dict(v) for k, v in self.stats.items()}
                bus.write_node_file(self.dir, self.info)
            except (OSError, RuntimeError):   # RuntimeError: a counter grew while being copied
                pass

    def _heartbeat(self) -> None:
        """The node file rewritten every HEARTBEAT_S, unless it was rewritten since (an executor
        beats for its nodes when it has nothing to do: beat)."""
        while not self._stop.wait(bus.HEARTBEAT_S) and not self._closed:
            if self.beat_due(BEAT_LATE):
                self._announce()

    def beat(self) -> None:
        """Rewrite the node file (the heartbeat) if the last one is BEAT_EARLY of HEARTBEAT_S old:
        what an executor calls when it has nothing to do. Its nodes' heartbeat threads (one a
        node, each file write 0.3-0.6 ms with the interpreter lock held part of it) then find
        the file fresh and leave it, and beat only while a handler keeps the executor busy."""
        if self.beat_due():
            self._announce()

    def beat_due(self, share: float = BEAT_EARLY) -> bool:
        """The node file is `share` of HEARTBEAT_S old (or older)."""
        return time.monotonic() - self._announced >= share * bus.HEARTBEAT_S

    # -- shutdown -----------------------------------------------------------------------
    def close(self) -> None:
        """Send end-of-stream on every advertised topic, remove the node file, close sockets."""
        if self._closed:
            return
        _OPEN_NODES.discard(self)
        for fn in self._at_close:
            try:
                fn()
            except Exception:   # closing goes on: downstream must still hear the end of stream
                self.log.exception("at close")
        self._at_close = []
        if self._trace:
            if threading.get_ident() == self._thread:   # the CPU time of this node's own thread
                thread = threading.current_thread()     # (an executor's: shared, named after its nodes)
                label = self.name if thread is threading.main_thread() else thread.name
                self._trace.append(("cpu", label, None, time.thread_time_ns()))
            Path(os.environ["HANDMOCAP_TRACE"], f"{self.name}.trace.json").write_text(json.dumps(self._trace))
        if self.info.publishes and not self._graph_ready and not self._stop.is_set():
            self.wait_for_subscribers(2.0)   # they must be connected to hear the end-of-stream
        self.info.closing = True   # in the node file before the end of stream goes out (the launcher reads it)
        self._announce()
        if self.info.publishes:
            self._open_publisher()
        for topic in self.info.publishes:
            last = self._last_sent.get(topic)   # lets a keep-all subscriber count a lost tail
            self.pub.send(topic, bus.EOS.decode(), f"{self.name}\0{self.info.eos_token}\0"
                          f"{'' if last is None else last}".encode(), eos=True)
        self._wait_until_heard(PUBLISHER_WAIT_S)
        self._stop.set()
        with self._file_lock:
            self._closed = True
            try:
                (self.dir / f"{self.name}.json").unlink()
            except FileNotFoundError:
                pass
        self.sub.close()
        self.pub.close()
        # Without term() the process may exit with its last messages still queued (a container
        # terms its shared Context once every node of it has closed).
        if self._own_ctx:
            keys.release(self.ctx)   # a tcp bind's ZAP handler first: it holds sockets of the context
            self.ctx.term()
        for sig, handler in self._old_handlers.items():
            signal.signal(sig, handler)
        for endpoint in (self.pub.endpoint, self.pub.lossless_endpoint):
            if endpoint.startswith("ipc://"):
                Path(endpoint[len("ipc://"):]).unlink(missing_ok=True)

    def _wait_until_heard(self, timeout_s: float) -> None:
        """After the end of stream went out: wait until every live subscriber of our topics has
        taken it in (its node file lists our eos_token in heard_eos), at most `timeout_s`. Closing the
        sockets earlier would lose what a subscriber that is behind still has to take from them
        (zmq drops it, LINGER notwithstanding, when that subscriber's receive queue is full)."""
        if not self.info.publishes or self._stop.is_set():
            return   # stopped (Ctrl-C): nobody is held
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            waiting = [n.name for n in bus.read_node_files(self.dir).values()
                       if n.pid != os.getpid()   # in this process: inproc, whose queue outlives the socket
                       and not n.observer and not n.closing and self.info.eos_token not in n.heard_eos
                       and any(t == "*" or t in self.info.publishes for t in n.subscribes)]
            if not waiting or self._stop.is_set():
                return
            time.sleep(0.02)
        self.log.warning("closing while %s had not yet taken in its end of stream (%.0f s): what they had not "
                         "received is lost", ", ".join(waiting), timeout_s)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_OPEN_NODES: "weakref.WeakSet[Node]" = weakref.WeakSet()


EXPECTED_ERRORS = (FileNotFoundError, ValueError, RuntimeError, OSError)


def spin(start) -> None:
    """A node module's main() where it offers start() -> (node, handler) (see
    handmocap.runtime.executor): set up, call the handler for every received message, close."""
    node, handler = start()
    for msg in node:
        node.handle(handler, msg)
    node.close()


def run(main) -> None:
    """Entry point wrapper for node modules: one clear error line instead of a traceback wall
    for the expected failures (bad parameter, missing file, device that can't be opened)."""
    try:
        main()
    except KeyboardInterrupt:
        pass
    except EXPECTED_ERRORS as e:
        logging.getLogger().error("%s", e)
        _close_open_nodes()
        sys.exit(2)
    finally:
        _close_open_nodes()


def stop_all() -> None:
    """Ask every open node of this process to end its loop (a container's signal handler)."""
    for node in list(_OPEN_NODES):
        node._stop.set()


def _close_open_nodes(thread: int | None = None) -> None:
    """Close the nodes a failed main() left open (with `thread`: those that thread runs):
    downstream nodes hear the end of stream, and the process does not exit with live ZeroMQ
    sockets (libzmq can abort then)."""
    for node in list(_OPEN_NODES):
        if thread is not None and node._thread != thread:
            continue
        try:
            node.close()
        except Exception:   # already failing: the error line above is the one that matters
            pass
