"""Several nodes of a container called in turn by one thread: ROS 2's single-threaded executor.

A node module that offers `start() -> (node, handler)` (detector, shape, ik) can run this
way: `spin` polls the receive sockets of all such nodes of a container and calls each
node's handler for its queued messages, in the launch file's order, so a frame goes
detector -> shape -> ik in one pass. Messages still travel over the bus (inproc://), so
the recorder, the visualizer and handtopic see the same topics as before.

Why not a thread per node: a pipeline always has two nodes with work at once, and as
threads of one process they then hand Python's interpreter lock back and forth at every
call into C (numpy, OpenCV, onnxruntime). On a 2-core VM each hand-over wakes a thread on
the other core (perf: futex wake-ups under pthread_cond_signal, ~5% of all CPU time in the
graph); called in turn, the nodes hand nothing over.
"""
from __future__ import annotations

import importlib
import logging
import threading
from typing import Callable

import zmq

from handmocap.runtime import node as node_mod

POLL_MS = node_mod.POLL_MS
QUIET_MS = 3   # how long the executor waits with nothing to do before it runs due scans and heartbeats


def exit_code(fn: Callable[[], None], name: str) -> int:
    """Run fn (a node's main, or its start) and map how it ended to an exit code, as a node
    process would end: 0; SystemExit's code; 2 with one error line for the expected errors
    (bad parameter, missing file); 1 with the traceback for anything else."""
    try:
        fn()
    except KeyboardInterrupt:
        pass
    except SystemExit as e:
        return e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except node_mod.EXPECTED_ERRORS as e:
        logging.getLogger(name).error("%s", e)
        return 2
    except Exception:
        logging.getLogger(name).exception("failed")
        return 1
    return 0


def start_nodes(members: list[dict], on_exit: Callable[[dict, int], None]) -> list[tuple]:
    """Set up each member ({name, module, settings}) with its module's start(), in order;
    returns [(member, node, handler)] of those that started. One that fails is closed (so its
    downstream hears the end of stream) and reported to on_exit(member, code)."""
    started = []
    for m in members:
        node_mod._local.settings = m["settings"]
        mine = lambda: {n for n in node_mod._OPEN_NODES if n._thread == threading.get_ident()}   # noqa: E731
        before = mine()   # (a container's other threads open nodes meanwhile: not ours to close)
        out = []
        code = exit_code(lambda: out.append(importlib.import_module(m["module"]).start()), m["name"])
        if code or not out:
            for n in mine() - before:
                n.close()
            on_exit(m, code or 1)
            continue
        started.append((m, *out[0]))
    return started


def spin(started: list[tuple], on_exit: Callable[[dict, int], None]) -> None:
    """Call each node's handler for every message queued for it, node after node, until
    every node has ended (its inputs ended, or node.stop_all()). A node ends by closing and
    on_exit(member, 0); a message its handler raises on is dropped and counted (Node.handle)."""
    live = [(m, node, handler, node.steps()) for m, node, handler in started]
    poller = zmq.Poller()
    armed = {}   # node -> its sockets made when registered (a node makes one for a new kind of connection)
    while live:
        for _, node, _, _ in live:
            if armed.get(node) != node.sub.made:
                for s in node.sockets():
                    poller.register(s, zmq.POLLIN)   # again for the old ones: no change
                armed[node] = node.sub.made
        for entry in list(live):
            m, node, handler, steps = entry
            ended = []

            def step() -> None:
                for msg in steps:
                    if msg is node_mod.IDLE:
                        return
                    node.handle(handler, msg)   # a message its handler fails on is dropped, not fatal
                ended.append(True)   # the stream is over for this node
            code = exit_code(step, m["name"])
            if code or ended:
                live.remove(entry)
                for s in node.sockets():
                    poller.unregister(s)
                node.close()
                on_exit(m, code)
        if live:
            # discovery scans (each 0.3-1 ms of node files read) and heartbeats (each 0.3-0.6 ms of a
            # node file written) once nothing came for QUIET_MS: not on the next message's path,
            # nor on the path of what the last handler sent to another process (the recorder's
            # receipt of /hand/pose, on a 2-core machine)
            scans = [node for _, node, _, _ in live if node.scan_due()]
            beats = [node for _, node, _, _ in live if node.beat_due()]
            if (scans or beats) and (not poller.poll(QUIET_MS) or any(node.scan_overdue() for node in scans)):
                for node in scans:
                    node.scan()
                for node in beats:
                    node.beat()
            poller.poll(POLL_MS)


def run_in_turn(members: list[dict], on_exit: Callable[[dict, int], None]) -> None:
    """start_nodes + spin in the calling thread (a container's executor thread)."""
    spin(start_nodes(members, on_exit), on_exit)


def can_run_in_turn(module: str) -> bool:
    """Whether a node module offers start() (else it runs as a thread of its own)."""
    try:
        return callable(getattr(importlib.import_module(module), "start", None))
    except Exception:   # an import error shows, as one error line, when the node starts
        return False

