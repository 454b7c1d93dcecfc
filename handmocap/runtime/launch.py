"""`handlaunch FILE.yaml [name:=value ...]`: start a graph of nodes, supervise it, stop it.

A launch file:

    graph: default            # optional: name of the run dir (isolates graphs on one host)
    args:                     # settable on the command line as name:=value
      input: {help: video file, image folder or bag}          # no default: required
      bag: {default: out.mcap}
      clip: {default: $(dirname)/clip.mp4}                    # $(dirname): this file's folder
    env: {OMP_NUM_THREADS: "1"}                               # for every node
    keys: {secret: keys/a.key_secret, clients: keys/clients, server: keys/b.key}   # CURVE on tcp:// (handmocap/runtime/keys.py)
    insecure: false           # true: tcp:// endpoints without keys (a warning at every start)
    nodes:
      replay:                 # node name (unique in the graph)
        node: replay          # module handmocap.nodes.replay (or a dotted module path)
        params: {source: $(var input), loop: false}
        required: true        # its failure fails the graph
      recorder:
        node: recorder
        params: {output: $(var bag)}
        remap: {/camera/image: /cam0/image}
        respawn: true         # restart on failure, back-off from respawn_delay (s) doubling to 30 s;
                              # not an expected error (exit 2: a bad param, a missing file, a camera
                              # that can't be opened) within CONFIG_ERROR_S of a start: no retry mends it
        env: {}
        bind: tcp://127.0.0.1:6000    # optional: listen here instead of the default ipc socket
        connect: [tcp://10.0.0.2:6000] # optional: publishers on other hosts
        if: $(var bag)        # optional: the node runs only when this is true (see is_true)
      detector: {node: detector, container: perception}   # optional: see below

Containers (ROS 2 composition): nodes with the same `container: NAME` run in one process,
unchanged: each binds its own socket (so every other process, handtopic and the recorder
still see its topics) and also an inproc:// endpoint of the process's one zmq Context, over
which the container's other nodes receive its messages without a socket hop. Nodes whose
module offers start() -> (node, handler) (detector, shape, ik) are called in turn by one
executor thread (handmocap.runtime.executor, as ROS 2's single-threaded executor): a frame goes
detector -> shape -> ik in one pass, and no two of them fight over the interpreter lock;
the others (sources) run their own loop in a thread each. The container is one supervised
process: it is required when one of
its nodes is, respawns when one of its nodes does (after the shortest respawn_delay), and
its output lines carry each node's own name. A node that fails inside it (exit code or
exception) stops the whole container when that node is required or respawns (the container
exits with its code, and handlaunch fails the graph or respawns the container), else the
others go on without it, as they would with separate processes.

The product launch files put the source (replay, camera or depthai) with detector, shape and
ik in container `perception` (ROS 2's intra-process pattern for camera drivers): a frame
goes to the detector over inproc:// (zmq passes the pooled payload buffer, no socket, no
kernel copy; the detector's decode views the pixels in it), while the recorder, visualizer
and bridge, processes of their own, get /camera/image over ipc as before. zmq's I/O thread
writes the frame to them; the source thread does not wait for it (SNDHWM 0). Sources,
onnxruntime and OpenCV's decoding release the GIL while they work. A source that fails
(a corrupt video, a camera that can't be opened) stops the container as a required node:
its one error line, then handlaunch's verdict on the container; what the recorder received
is in its bag. SIGTERM or a crash takes the source down with perception, and a respawn
restarts them together.

Everything is checked before any process starts; an error names the file, line and problem.
The launcher returns when every node has finished (a finite replay ends, its end-of-stream
drains the graph), with exit 1 if a required node failed; Ctrl-C/SIGTERM stops all nodes.
"""
from __future__ import annotations

import fcntl
import importlib
import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from handmocap.runtime import bus
from handmocap.runtime.keys import ENV as KEYS_ENV, Keys, release as release_keys
from handmocap.runtime.params import parse_cli_params

NODE_KEYS = {"node", "params", "remap", "env", "respawn", "respawn_delay", "required", "bind", "connect", "if",
             "container"}
FALSE_WORDS = {"", "false", "no", "off", "0", "null", "none"}
TOP_KEYS = {"graph", "args", "env", "nodes", "keys", "insecure"}
VAR = re.compile(r"\$\((var|env) ([A-Za-z_][A-Za-z0-9_]*)(?: ([^)]*))?\)")
STARTUP_TIMEOUT_S = 120
# a stopping process may wait out its publishers' linger (a subscriber in another process
# still finishing its own shutdown, e.g. a visualizer drawing its last frames, has not read
# the last frames yet): it is killed only after that, or it could lose them
STOP_TIMEOUT_S = bus.PUBLISHER_LINGER_S + 5
MAX_BACKOFF_S = 30
# a node that ends this soon after it started failed while starting: with an expected error
# (exit code 2: bad parameter, missing file, a device that can't be opened) it is not
# respawned, as it would fail the same way on every retry (later, a camera unplugged mid-run,
# it is); a crash this soon is a crash loop, whose respawn back-off keeps doubling
CONFIG_ERROR_S = 10.0
# how often the launcher looks at its children: a node that died is seen, and respawned when
# its delay is up, within this (issue 49: poses again within 1 s of a detector's kill); a
# look is a waitpid per child, nothing a core feels at 50 a second
SUPERVISE_S = 0.02
# Where node processes keep this package's compiled modules when PYTHONDONTWRITEBYTECODE is set
# (container images and CI runners often set it): without a cache every start, and every
# respawn, compiles the package's modules again (0.08 s of the perception container's 0.4 s of
# imports on a quiet 2-core AMD EPYC, more under load; issue 49's drill wants poses back within
# 1 s of a kill). The first start fills the cache (every module Python reads from then on comes
# from it: a second or two, once). Python keeps them under this folder (PYTHONPYCACHEPREFIX),
# never beside the sources: $XDG_CACHE_HOME/handmocap/pycache, else ~/.cache/handmocap/pycache
# (the same rule as onnx_models.onnx_cache_dir's, read here from the children's environment).
# A PYTHONPYCACHEPREFIX of the user's own is kept; without PYTHONDONTWRITEBYTECODE nothing changes.
PYCACHE_SUBDIR = ("handmocap", "pycache")


def bytecode_env(environ: dict) -> dict:
    """`environ` as node processes get it: where PYTHONDONTWRITEBYTECODE is set and the user chose
    no PYTHONPYCACHEPREFIX, compiled modules are written to and read from the cache folder
    (PYCACHE_SUBDIR) instead of being compiled again at each start. Unchanged otherwise, and
    where there is no home folder to put the cache in (a bare container)."""
    if not environ.get("PYTHONDONTWRITEBYTECODE") or environ.get("PYTHONPYCACHEPREFIX"):
        return dict(environ)
    cache = environ.get("XDG_CACHE_HOME") or (os.path.join(environ["HOME"], ".cache") if environ.get("HOME") else None)
    if cache is None:
        return dict(environ)
    env = {k: v for k, v in environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPYCACHEPREFIX"] = os.path.join(cache, *PYCACHE_SUBDIR)
    return env


class LaunchError(Exception):
    """A launch file problem, already phrased as `file:line: problem`."""


# -- loading with line numbers ----------------------------------------------------------
def _load_yaml_with_lines(path: Path) -> tuple[object, dict]:
    """Parse YAML; also return {key path tuple: 1-based line} for error messages."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise LaunchError(f"{path}: no such launch file") from None
    except OSError as e:
        raise LaunchError(f"{path}: cannot read: {e.strerror}") from None
    # $(dirname): the launch file's own folder (as in ROS 2 launch files), so a file can name
    # files beside it however the user's shell got there
    text = text.replace("$(dirname)", str(path.resolve().parent))
    try:
        root = yaml.compose(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"{path}:{mark.line + 1}" if mark else str(path)
        raise LaunchError(f"{where}: malformed YAML: {getattr(e, 'problem', None) or e}") from None
    lines: dict[tuple, int] = {}

    def build(node, key_path):
        lines.setdefault(key_path, node.start_mark.line + 1)   # a key's own line wins
        if isinstance(node, yaml.MappingNode):
            out = {}
            for k, v in node.value:
                key = yaml.safe_load(yaml.serialize(k))
                if key in out:   # YAML would keep the last silently: a node or arg defined twice
                    first = lines[key_path + (key,)]
                    raise LaunchError(f"{path}:{k.start_mark.line + 1}: {key!r} is given twice "
                                      f"(lines {first} and {k.start_mark.line + 1})"
                                      + (f" under {'.'.join(map(str, key_path))}" if key_path else ""))
                lines[key_path + (key,)] = k.start_mark.line + 1
                out[key] = build(v, key_path + (key,))
            return out
        if isinstance(node, yaml.SequenceNode):
            return [build(v, key_path + (i,)) for i, v in enumerate(node.value)]
        return yaml.safe_load(yaml.serialize(node))

    return (build(root, ()) if root is not None else None), lines


@dataclass
class NodeSpec:
    name: str
    module: str
    params: dict = field(default_factory=dict)
    remap: dict = field(default_factory=dict)
    env: dict = field(default_factory=dict)
    respawn: bool = False
    respawn_delay: float = 1.0
    required: bool = False
    bind: str | None = None
    connect: list = field(default_factory=list)
    container: str | None = None


@dataclass
class ContainerSpec:
    """Nodes that run as threads of one process (see the module docstring)."""
    name: str
    members: list[NodeSpec]
    env: dict = field(default_factory=dict)
    respawn: bool = False
    respawn_delay: float = 1.0
    required: bool = False


@dataclass
class LaunchFile:
    path: Path
    graph: str | None
    nodes: list[NodeSpec]
    keys: Keys | None = None      # CURVE key files for the graph's tcp endpoints (handmocap.runtime.keys)
    insecure: list[str] = field(default_factory=list)   # tcp endpoints left open on purpose (insecure: true)


def is_true(value) -> bool:
    """An `if:` value: false for null, false, 0, and the strings '', 'false', 'no', 'off', '0',
    'null', 'none' (any case); true otherwise (so `if: $(var bag)` runs a node when a path is given)."""
    if isinstance(value, str):
        return value.strip().lower() not in FALSE_WORDS
    return bool(value)


def resolve_module(name: str) -> str:
    return name if "." in name else f"handmocap.nodes.{name}"


def load_launch_file(path: str | Path, cli_args: dict, import_nodes: bool = True) -> LaunchFile:
    """Parse and check a launch file completely (no process is started here). import_nodes=False:
    every check but those that import a node's module (its PARAMS, its check_params), for a
    file already checked whole (`checked_apart`)."""
    path = Path(path)
    doc, lines = _load_yaml_with_lines(path)

    def err(key_path, problem):
        line = lines.get(tuple(key_path), lines.get(tuple(key_path[:-1]), 1))
        return LaunchError(f"{path}:{line}: {problem}")

    if not isinstance(doc, dict):
        raise err((), "a launch file is a mapping with a 'nodes:' section")
    for k in doc:
        if k not in TOP_KEYS:
            raise err((k,), f"unknown key {k!r} (expected one of {', '.join(sorted(TOP_KEYS))})")
    declared = doc.get("args") or {}
    if not isinstance(declared, dict):
        raise err(("args",), "'args' must map argument names to {default: ..., help: ...}")
    for name in cli_args:
        if name not in declared:
            raise LaunchError(f"{path}:{lines.get(('args',), 1)}: unknown argument {name!r} given on the "
                              f"command line; this file declares: {', '.join(declared) or 'none'}")
    values = {}
    for name, spec in declared.items():
        spec = spec if isinstance(spec, dict) else {"default": spec}
        if name in cli_args:
            values[name] = cli_args[name]
        elif "default" in spec:
            values[name] = spec["default"]
        else:
            raise err(("args", name), f"argument {name!r} is required: add {name}:=VALUE"
                      + (f" ({spec['help']})" if spec.get("help") else ""))

    def substitute(obj, key_path):
        if isinstance(obj, dict):
            return {k: substitute(v, key_path + (k,)) for k, v in obj.items()}
        if isinstance(obj, list):
            return [substitute(v, key_path + (i,)) for i, v in enumerate(obj)]
        if not isinstance(obj, str):
            return obj

        def value(m):
            kind, name, default = m.groups()
            if kind == "env":
                if name in os.environ:
                    return os.environ[name]
                if default is None:
                    raise err(key_path, f"environment variable {name} is not set and has no default")
                return default
            if name not in values:
                raise err(key_path, f"$(var {name}) is not declared under 'args:'")
            return values[name]

        whole = VAR.fullmatch(obj)
        if whole:                      # keep the argument's type (int, bool, null)
            return value(whole)
        return VAR.sub(lambda m: str(value(m)), obj)

    nodes_doc = doc.get("nodes")
    if not isinstance(nodes_doc, dict) or not nodes_doc:
        raise err(("nodes",), "'nodes:' must map node names to node entries")
    common_env = substitute(doc.get("env") or {}, ("env",))
    specs = []
    for name, entry in nodes_doc.items():
        kp = ("nodes", name)
        if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", name):
            raise err(kp, f"bad node name {name!r} (letters, digits, '_' and '-')")
        if not isinstance(entry, dict) or "node" not in entry:
            raise err(kp, f"node {name!r} needs a 'node:' key naming its module")
        for k in entry:
            if k not in NODE_KEYS:
                raise err(kp + (k,), f"node {name!r}: unknown key {k!r} "
                          f"(expected one of {', '.join(sorted(NODE_KEYS))})")
        entry = substitute(entry, kp)
        if "if" in entry:
            if isinstance(entry["if"], (dict, list)):
                raise err(kp + ("if",), f"node {name!r}: 'if' must be a value (e.g. $(var bag)), not a "
                          f"{type(entry['if']).__name__}")
        module = resolve_module(str(entry["node"]))
        try:
            found = importlib.util.find_spec(module)
        except ModuleNotFoundError:
            found = None
        if found is None:
            raise err(kp + ("node",), f"node {name!r}: unknown node type {entry['node']!r} "
                      f"(no module {module}); available: {', '.join(available_nodes())}")
        params = entry.get("params") or {}
        if not isinstance(params, dict):
            raise err(kp + ("params",), f"node {name!r}: 'params' must be a mapping")
        try:
            node_module = importlib.import_module(module) if import_nodes else None
        except Exception as e:   # a node whose module cannot even be imported cannot run
            raise err(kp + ("node",), f"node {name!r}: module {module} fails to import: "
                      f"{type(e).__name__}: {e}") from None
        known = getattr(node_module, "PARAMS", None)
        if known is not None:
            for p in params:
                if p not in known:
                    raise err(kp + ("params", p), f"node {name!r} ({entry['node']}) has no parameter {p!r}; "
                              f"known: {', '.join(sorted(known))}")
        container = entry.get("container")
        if container is not None and (not isinstance(container, str)
                                      or not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", container)):
            raise err(kp + ("container",), f"node {name!r}: bad container name {container!r} "
                      f"(letters, digits, '_' and '-')")
        if container is not None and container in nodes_doc:
            raise err(kp + ("container",), f"node {name!r}: container {container!r} has the name of a node")
        if not is_true(entry.get("if", True)):
            continue   # switched off, after the same checks as a node that runs (a typo fails either way)
        # a node module may check the values of its params too (`check_params(params)`, ValueError):
        # model files and settings of a node that runs (a switched-off one needs no model file)
        check = getattr(node_module, "check_params", None)
        if check is not None:
            try:
                check(params)
            except ValueError as e:
                raise err(kp + ("params",), f"node {name!r}: {e}") from None
        specs.append(NodeSpec(name=name, module=module, params=params, remap=entry.get("remap") or {},
                              env={**common_env, **(entry.get("env") or {})},
                              respawn=bool(entry.get("respawn", False)),
                              respawn_delay=float(entry.get("respawn_delay", 1.0)),
                              required=bool(entry.get("required", False)), bind=entry.get("bind"),
                              connect=list(entry.get("connect") or []), container=container))
        if container is not None:   # one process, one environment: its nodes must agree on it
            for other in specs[:-1]:
                if other.container == container and other.env != specs[-1].env:
                    raise err(kp + ("env",), f"node {name!r}: its environment differs from that of node "
                              f"{other.name!r} in the same container {container!r} (one process, one env)")
    keys, insecure = _network_security(doc, specs, err, substitute)
    return LaunchFile(path=path, graph=doc.get("graph"), nodes=specs, keys=keys, insecure=insecure)


def _network_security(doc: dict, specs: list, err, substitute) -> tuple[Keys | None, list[str]]:
    """The graph's `keys:` (checked: a tcp bind needs a key pair and its clients' public keys, a
    tcp connect a key pair and the server's public key), or, with `insecure: true`, the list of
    tcp endpoints left open. A tcp endpoint with neither is an error: it would let anyone who
    can reach the port read the poses or feed forged ones."""
    binds = [(n.name, n.bind) for n in specs if n.bind and n.bind.startswith("tcp://")]
    connects = [(n.name, e) for n in specs for e in n.connect if str(e).startswith("tcp://")]
    raw = substitute(doc.get("keys"), ("keys",)) if doc.get("keys") is not None else None
    insecure = doc.get("insecure", False)
    if not isinstance(insecure, bool):
        raise err(("insecure",), f"'insecure' must be true or false, got {insecure!r}")
    if raw is None:
        if (binds or connects) and not insecure:
            name, endpoint = (binds or connects)[0]
            raise err(("nodes", name), f"node {name!r}: {endpoint} is a network endpoint without keys: add a "
                      f"'keys:' block (make keys with `handkeys keys NAME ...`; handmocap/runtime/keys.py), or "
                      f"'insecure: true' to leave it open to anyone who can reach it")
        return None, [e for _, e in binds + connects]
    if not isinstance(raw, dict) or set(raw) - {"secret", "clients", "server"}:
        raise err(("keys",), "'keys' maps secret (this graph's .key_secret), clients (a folder of public "
                  ".key files) and server (a publisher's public .key)")
    keys = Keys(**{k: str(Path(str(v)).expanduser()) if v is not None else None for k, v in raw.items()})
    problems = keys.check(bool(binds), bool(connects))
    if problems:
        raise err(("keys",), "; ".join(problems))
    return keys, []


def processes(nodes: list[NodeSpec]) -> list[NodeSpec | ContainerSpec]:
    """The processes of a graph: a node on its own, or a container of the nodes that name it
    (where its first node stands in the file)."""
    out, containers = [], {}
    for spec in nodes:
        if spec.container is None:
            out.append(spec)
        elif spec.container in containers:
            containers[spec.container].members.append(spec)
        else:
            containers[spec.container] = ContainerSpec(spec.container, [spec], env=spec.env)
            out.append(containers[spec.container])
    for c in containers.values():
        c.required = any(m.required for m in c.members)
        c.respawn = any(m.respawn for m in c.members)
        c.respawn_delay = min(m.respawn_delay for m in c.members if m.respawn) if c.respawn else 1.0
    return out


def available_nodes() -> list[str]:
    nodes_dir = Path(importlib.util.find_spec("handmocap.nodes").origin).parent
    return sorted(p.stem for p in nodes_dir.glob("*.py") if not p.stem.startswith("_"))


# -- supervision ------------------------------------------------------------------------
class Child:
    """One supervised process: a node, or a container of nodes."""

    def __init__(self, spec: NodeSpec | ContainerSpec, env: dict, log):
        self.spec, self.base_env, self.log = spec, env, log
        self.members = spec.members if isinstance(spec, ContainerSpec) else None
        self.names = [m.name for m in self.members] if self.members else [spec.name]
        self.proc: subprocess.Popen | None = None
        self.started = 0.0
        self.backoff = spec.respawn_delay
        self.restart_at: float | None = None
        self.restarts = 0
        self.exit_code: int | None = None

    @property
    def what(self) -> str:
        """'node detector' or 'container perception (detector, shape, ik)' for messages."""
        if self.members:
            return f"container {self.spec.name} ({', '.join(self.names)})"
        return f"node {self.spec.name}"

    def start(self) -> None:
        env = {**self.base_env, **{k: str(v) for k, v in self.spec.env.items()}, "PYTHONUNBUFFERED": "1"}
        if self.members:
            env["HANDMOCAP_CONTAINER"] = json.dumps([member_settings(m) for m in self.members])
            cmd = [sys.executable, "-m", "handmocap.runtime.launch", "--container"]
        else:
            env.update(member_settings(self.spec)["settings"])
            cmd = [sys.executable, "-m", self.spec.module]
        self.proc = subprocess.Popen(cmd, env=env,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     stdin=subprocess.DEVNULL, start_new_session=True)
        self.started = time.monotonic()
        self.exit_code = None
        threading.Thread(target=self._pump, args=(self.proc,), daemon=True).start()

    def _pump(self, proc) -> None:
        for line in iter(proc.stdout.readline, b""):
            text, who = line.decode(errors="replace").rstrip("\n"), self.spec.name
            if self.members and text.startswith("["):   # a container's node: "[name] text"
                name, _, rest = text[1:].partition("] ")
                if name in self.names:
                    text, who = rest, name
            self.log(who, text)

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def terminate(self) -> None:
        if self.running:
            self.proc.send_signal(signal.SIGTERM)


def feeds(nodes: dict) -> list[tuple[str, str, str]]:
    """(publisher, topic, subscriber) of every topic that goes from one node of the graph to
    another (NodeInfo by name; tools that only observe are left out). An every-topic
    subscriber ("*", the recorder) takes every topic, as its subscription is named "*"."""
    nodes = {n: i for n, i in nodes.items() if not i.observer}
    return [(n, t, m) for n, i in nodes.items() for t in i.publishes for m, j in nodes.items()
            if t in j.subscribes or "*" in j.subscribes]


def topic_cycle(nodes: dict) -> str | None:
    """'a -[/x]-> b -[/y]-> a' for a cycle of topics among the graph's nodes (NodeInfo by
    name), along `feeds`, or None."""
    edges: dict[str, list[tuple[str, str]]] = {n: [] for n, i in nodes.items() if not i.observer}
    for publisher, topic, subscriber in feeds(nodes):
        edges[publisher].append((topic, subscriber))
    state: dict[str, int] = {}   # 1: on the current path, 2: done
    path: list[tuple[str, str]] = []

    def visit(n):
        state[n] = 1
        for topic, m in edges[n]:
            path.append((n, topic))
            if state.get(m) == 1:
                start = next(i for i, (k, _) in enumerate(path) if k == m)
                return "".join(f"{k} -[{t}]-> " for k, t in path[start:]) + m
            if m not in state:
                found = visit(m)
                if found:
                    return found
            path.pop()
        state[n] = 2
        return None

    for n in sorted(edges):
        if n not in state:
            found = visit(n)
            if found:
                return found
    return None


class Launcher:
    def __init__(self, launch: LaunchFile, out=sys.stdout):
        self.launch = launch
        self.out = out
        self._lock = threading.Lock()
        self.dir = bus.run_dir(launch.graph)
        self.id = f"launch-{uuid.uuid4().hex[:8]}"
        env = {**bytecode_env(os.environ), "HANDMOCAP_RUN_DIR": str(self.dir), "HANDMOCAP_LAUNCH_ID": self.id}
        env.pop(KEYS_ENV, None)
        if launch.keys is not None:
            env[KEYS_ENV] = launch.keys.to_env()
        self.children = [Child(s, env, self.print) for s in processes(launch.nodes)]
        self.stopping = False
        self.fed_by: dict[str, list[tuple[str, str]]] = {}   # node -> (topic, publisher) feeding it, once all are up
        self.ended_early: list[str] = []             # nodes that ended before their inputs' publishers

    def print(self, who: str, text: str) -> None:
        with self._lock:
            print(f"[{who}] {text}", file=self.out, flush=True)

    def check_names_free(self) -> None:
        live = bus.read_node_files(self.dir)
        for name in (n for c in self.children for n in c.names):
            if name in live:
                raise LaunchError(f"{self.launch.path}: node {name!r} is already running in graph "
                                  f"{self.dir} (pid {live[name].pid}); stop it, or run this graph "
                                  f"under another name (graph: in the file, or HANDMOCAP_GRAPH=...)")
            (self.dir / f"{name}.json").unlink(missing_ok=True)   # stale file of a dead node

    def lock_graph(self) -> None:
        """Hold an exclusive lock on <run dir>/graph.lock for the launcher's life: "one graph per
        name" is atomic (two launches 0.3 s apart had both passed check_names_free and shared
        sockets). The lock goes with the process, however it ends."""
        self._lock_file = open(self.dir / "graph.lock", "a+")
        try:
            fcntl.flock(self._lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            self._lock_file.seek(0)
            holder = self._lock_file.read().strip() or "?"
            self._lock_file.close()
            raise LaunchError(f"{self.launch.path}: graph {self.dir} is already running (handlaunch pid {holder}); "
                              f"stop it, or run this graph under another name (graph: in the file, or "
                              f"HANDMOCAP_GRAPH=...)") from None
        self._lock_file.seek(0)
        self._lock_file.truncate()
        self._lock_file.write(str(os.getpid()))
        self._lock_file.flush()

    def run(self) -> int:
        self.lock_graph()
        self.check_names_free()
        if self.launch.insecure:
            self.print("handlaunch", f"warning: insecure: true: {', '.join(self.launch.insecure)} carry the graph "
                       f"unencrypted and unauthenticated: anyone who can reach them can read the poses or send "
                       f"forged ones (a 'keys:' block closes them)")
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: setattr(self, "stopping", True))
        for c in self.children:
            c.start()
        self.print("handlaunch", f"started {sum(len(c.names) for c in self.children)} node(s) in {self.dir}"
                   + (f", in {len(self.children)} processes" if any(c.members for c in self.children) else ""))
        ready_file = self.dir / f"{self.id}.ready"
        t0, failed = time.monotonic(), None
        try:
            while not self.stopping:
                if not ready_file.exists():
                    if self._all_ready():
                        files = bus.read_node_files(self.dir, alive_only=False)
                        cycle = topic_cycle(files)
                        if cycle:   # before the first message: nodes wait for the ready file
                            self.print("handlaunch", f"error: topic cycle {cycle}: its nodes would wait for "
                                       f"each other's end of stream and the graph would never end; "
                                       f"nothing was sent")
                            failed = "cycle"
                            break
                        self._write_ready(ready_file, files)
                    elif time.monotonic() - t0 > STARTUP_TIMEOUT_S:
                        self.print("handlaunch", f"error: nodes not up after {STARTUP_TIMEOUT_S} s: "
                                   f"{', '.join(self._not_ready())}")
                        failed = "startup"
                        break
                failed = self._supervise()
                # ended: every process exited and none waits for a respawn (one that failed and is
                # not required was reported; the graph still ends with the others)
                if failed or all(c.exit_code is not None and c.restart_at is None for c in self.children):
                    break
                due = [c.restart_at - time.monotonic() for c in self.children if c.restart_at is not None]
                time.sleep(max(0.0, min([SUPERVISE_S, *due])))
        finally:
            self._stop_all()
            ready_file.unlink(missing_ok=True)
        if failed:
            return 2 if failed == "cycle" else 1
        if self.stopping:
            self.print("handlaunch", "stopped")
            return 130 if any(c.exit_code not in (0, None) for c in self.children if c.spec.required) else 0
        if self.ended_early:
            self.print("handlaunch", f"error: {', '.join(self.ended_early)} ended before their inputs did")
            return 1
        self.print("handlaunch", "all nodes finished")
        return 0

    def _write_ready(self, ready_file: Path, files: dict) -> None:
        """Say that every node is up, with the graph's publishers and subscribers per topic: a
        node then knows which of its inputs will get data (and from whom to await
        end-of-stream), and a publisher which subscribers to wait for, even if it never caught
        another node's file fresh. files: the node files, read once every node was up."""
        publishers: dict[str, list[str]] = {}
        subscribers: dict[str, list[str]] = {}
        for info in files.values():
            for topic in info.publishes:
                publishers.setdefault(topic, []).append(info.name)
            if not info.observer:
                for topic in info.subscribes:
                    subscribers.setdefault(topic, []).append(info.name)
        tmp = ready_file.with_suffix(".tmp")
        tmp.write_text(json.dumps({"publishers": publishers, "subscribers": subscribers}))
        os.replace(tmp, ready_file)
        self.fed_by = {}
        for publisher, topic, subscriber in feeds(files):
            self.fed_by.setdefault(subscriber, []).append((topic, publisher))

    def _ended_before_its_inputs(self, c) -> bool:
        """A node that ended (exit 0) while a publisher of one of its inputs still runs did not
        end by the end of its streams (a forged or mistaken end of stream): say so, and the
        graph's exit code says so too (a required one stops the graph: _supervise). -> whether it did."""
        files = bus.read_node_files(self.dir)   # alive ones: a publisher still running and not closing
        running = {n for other in self.children if other.exit_code is None for n in other.names
                   if n in files and not files[n].closing and not files[n].ended}
        for name in c.names:
            still = [(topic, publisher) for topic, publisher in self.fed_by.get(name, ()) if publisher in running]
            if still:
                self.print("handlaunch", f"error: {name} ended while {', '.join(sorted({p for _, p in still}))}, "
                           f"which publish its input {still[0][0]}, still run (it did not hear the end of its "
                           f"stream from them)")
                self.ended_early.append(name)
        return any(name in self.ended_early for name in c.names)

    def _all_ready(self) -> bool:
        return not self._not_ready()

    def _not_ready(self) -> list[str]:
        files = bus.read_node_files(self.dir, alive_only=False)
        up = {n for n, i in files.items() if i.ended or (i.ready and i.alive)}   # ended: a container's failed node
        return [name for c in self.children if c.exit_code is None for name in c.names if name not in up]

    def _supervise(self) -> str | None:
        now = time.monotonic()
        for c in self.children:
            if c.restart_at is not None:
                if now >= c.restart_at:
                    c.restart_at = None
                    c.restarts += 1
                    self.print("handlaunch", f"respawning {c.spec.name} (restart {c.restarts})")
                    c.start()
                continue
            if c.proc is None or c.exit_code is not None or c.running:
                continue
            c.exit_code = c.proc.returncode
            if c.exit_code == 0:
                if self._ended_before_its_inputs(c) and c.spec.required:
                    self.print("handlaunch", f"error: required {c.what} ended before its inputs did; stopping "
                               f"the graph")
                    return c.spec.name
                continue
            how = f"killed by signal {-c.exit_code}" if c.exit_code < 0 else f"exit code {c.exit_code}"
            if c.spec.respawn and not (c.exit_code == 2 and now - c.started <= CONFIG_ERROR_S):
                if now - c.started > CONFIG_ERROR_S:
                    c.backoff = c.spec.respawn_delay   # it ran a while: not a crash loop
                self.print("handlaunch", f"{c.what} died ({how}); respawn in {c.backoff:.1f} s")
                c.restart_at = now + c.backoff
                c.backoff = min(c.backoff * 2, MAX_BACKOFF_S)
                continue
            for name in c.names:
                self._mark_ended(name)
            if c.spec.required:
                self.print("handlaunch", f"error: required {c.what} failed ({how}); stopping the graph")
                return c.spec.name
            self.print("handlaunch", f"warning: {c.what} failed ({how})")
        return None

    def _mark_ended(self, name: str) -> None:
        """Tell subscribers that a node which died without end-of-stream is gone for good."""
        info = bus.read_node_files(self.dir, alive_only=False).get(name)
        if info is not None:
            info.ended = True
            bus.write_node_file(self.dir, info)

    def _stop_all(self) -> None:
        for c in self.children:
            c.restart_at = None
            c.terminate()
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for c in self.children:
            if c.proc is None:
                continue
            try:
                c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self.print("handlaunch", f"{c.spec.name} did not stop in {STOP_TIMEOUT_S} s; killing it")
                c.proc.kill()
                c.proc.wait()
            if c.exit_code is None:
                c.exit_code = c.proc.returncode
            for name in c.names:
                (self.dir / f"{name}.json").unlink(missing_ok=True)


def member_settings(spec: NodeSpec) -> dict:
    """What a node process (or a container's node thread) is told about itself."""
    settings = {"HANDMOCAP_NODE_NAME": spec.name, "HANDMOCAP_PARAMS": json.dumps(spec.params),
                "HANDMOCAP_REMAP": json.dumps(spec.remap), "HANDMOCAP_CONNECT": json.dumps(spec.connect)}
    if spec.bind:
        settings["HANDMOCAP_BIND"] = spec.bind
    return {"name": spec.name, "module": spec.module, "settings": settings,
            "fatal": spec.required or spec.respawn}


# -- a container process ------------------------------------------------------------------
def _name_thread(name: str) -> None:
    """Give the calling OS thread the node's name (Linux, 15 bytes), so top -H, ps -L and perf
    show which node of a container a thread runs; elsewhere a no-op."""
    try:
        import ctypes
        ctypes.CDLL(None).prctl(15, name.encode()[:15] + b"\0", 0, 0, 0)   # PR_SET_NAME
    except (OSError, AttributeError):
        pass


def run_container(members: list[dict]) -> int:
    """Run the nodes `members` (member_settings) in this process, sharing one zmq Context:
    those whose module offers start() (detector, shape, ik) called in turn by one executor
    thread (handmocap.runtime.executor), the others (sources) as threads of their own. Returns the
    exit code: 0, or that of the first required (or respawning) node that failed, which
    stops the others. A failed node that is neither only ends on its own."""
    import logging

    import zmq

    from handmocap.runtime import executor
    from handmocap.runtime import node as node_mod
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="[%(name)s] %(levelname)s %(message)s")
    log = logging.getLogger("container")
    ctx = zmq.Context()
    node_mod._SHARED.update(ctx=ctx, token=uuid.uuid4().hex)
    stopping = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stopping.set())
    failed: list[tuple[str, int]] = []

    def on_exit(m: dict, code: int) -> None:
        if not code:
            return
        failed.append((m["name"], code))
        if m["fatal"]:
            stopping.set()
        else:
            log.warning("node %s failed (exit code %d); the container goes on without it", m["name"], code)
            # as the launcher marks a node process that died for good: its streams are over,
            # and the graph does not wait for it to come up
            bus.write_node_file(bus.run_dir(), bus.NodeInfo(m["name"], os.getpid(), "", ended=True))

    def member(m: dict) -> None:
        node_mod._local.settings = m["settings"]
        _name_thread(m["name"])
        try:
            code = executor.exit_code(importlib.import_module(m["module"]).main, m["name"])
        finally:
            node_mod._close_open_nodes(threading.get_ident())   # end of stream downstream
        on_exit(m, code)

    def in_turn(group: list[dict]) -> None:
        _name_thread(threading.current_thread().name)
        try:
            executor.run_in_turn(group, on_exit)
        finally:
            node_mod._close_open_nodes(threading.get_ident())

    group = [m for m in members if executor.can_run_in_turn(m["module"])]
    threads = [threading.Thread(target=member, args=(m,), name=m["name"], daemon=True)
               for m in members if m not in group]
    if group:
        threads.append(threading.Thread(target=in_turn, args=(group,), name="+".join(m["name"] for m in group),
                                        daemon=True))
    for t in threads:
        t.start()
    while any(t.is_alive() for t in threads):
        if stopping.is_set():
            node_mod.stop_all()   # again and again: a node still starting up may open after a call
        for t in threads:
            t.join(0.05)
    release_keys(ctx)   # a tcp bind's ZAP handler holds sockets of the context
    ctx.term()   # every node closed its sockets: flush what is queued, then end
    fatal = [(n, c) for n, c in failed if next(m for m in members if m["name"] == n)["fatal"]]
    return fatal[0][1] if fatal else 0


def checked_apart(path: str, cli_args: dict) -> int:
    """load_launch_file, every node module imported and its params checked, in a forked child
    that then exits: the launcher itself never imports the nodes' modules (numpy, OpenCV,
    onnxruntime), so the process that supervises a graph stays small (benchmarks/bench_memory.py:
    ~20 MB less). 0 when the file is good, else the exit code; the child printed the error."""
    pid = os.fork()
    if pid == 0:   # the child: no thread runs yet in the launcher, so a fork is safe here
        code = 1
        try:
            load_launch_file(path, cli_args)
            code = 0
        except (LaunchError, ValueError, bus.RunDirError) as e:
            print(f"handlaunch: error: {e}", file=sys.stderr)
            code = 2
        except BaseException:
            import traceback
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--container"]:   # started by a launcher: HANDMOCAP_CONTAINER names its nodes
        return run_container(json.loads(os.environ["HANDMOCAP_CONTAINER"]))
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if argv else 2
    try:
        cli_args = parse_cli_params(argv[1:])
        code = checked_apart(argv[0], cli_args)
        if code:
            return code
        return Launcher(load_launch_file(argv[0], cli_args, import_nodes=False)).run()
    except (LaunchError, ValueError, bus.RunDirError) as e:
        print(f"handlaunch: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
