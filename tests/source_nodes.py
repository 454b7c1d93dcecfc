"""Test helper: run a camera-source node as a real process and collect what it publishes.

The subscriber is a Node in the test process. The source runs as under handlaunch (a
launch id whose `.ready` file exists), so it holds its first frame until the subscriber is
connected and no frame is lost; its end-of-stream ends the subscriber's loop.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from handmocap.runtime.node import Node

TOPICS = {"/camera/image": "Image", "/camera/info": "CameraInfo"}


@dataclass
class SourceRun:
    returncode: int
    stderr: str
    messages: dict = field(default_factory=lambda: {t: [] for t in TOPICS})   # topic -> [decoded dict]

    @property
    def error_lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.strip()]


def run_source(module: str, params: dict, timeout_s: float = 30.0) -> SourceRun:
    """Start `python -m module` with `params`, receive /camera/image and /camera/info until it
    ends (or `timeout_s`), return its exit code, stderr and the decoded messages in order."""
    run_dir = tempfile.mkdtemp(prefix="hm")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HANDMOCAP_")}
    env.update(HANDMOCAP_RUN_DIR=run_dir, HANDMOCAP_PARAMS=json.dumps(params), HANDMOCAP_LAUNCH_ID="t",
               HANDMOCAP_VALIDATE_SEND="1")   # the source checks every message against its schema
    saved_env = os.environ.get("HANDMOCAP_RUN_DIR")
    saved_signals = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    os.environ["HANDMOCAP_RUN_DIR"] = run_dir
    try:
        sub = Node("test_subscriber", argv=[])
        for topic, type_name in TOPICS.items():
            sub.subscribe(topic, type_name, mode="all")
        sub.ready()
        (Path(run_dir) / "t.ready").touch()
        proc = subprocess.Popen([sys.executable, "-m", module], env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, text=True)
        result = SourceRun(returncode=-1, stderr="")
        deadline = time.monotonic() + timeout_s
        exited_at = None
        try:
            for msg in sub.events(timeout=0.2):
                if msg is not None:
                    result.messages[msg.topic].append(msg.data)
                if proc.poll() is not None:
                    exited_at = exited_at or time.monotonic()
                    if time.monotonic() - exited_at > 3.0:   # died without end-of-stream
                        break
                if time.monotonic() > deadline:
                    break
        finally:
            sub.close()
            try:
                _, result.stderr = proc.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, result.stderr = proc.communicate()
        result.returncode = proc.returncode
        return result
    finally:
        if saved_env is None:
            os.environ.pop("HANDMOCAP_RUN_DIR", None)
        else:
            os.environ["HANDMOCAP_RUN_DIR"] = saved_env
        for s, handler in saved_signals.items():
            signal.signal(s, handler)
        shutil.rmtree(run_dir, ignore_errors=True)


def run_failing(module: str, params: dict, timeout_s: float = 60.0) -> subprocess.CompletedProcess:
    """Run a node that is expected to fail before publishing; stdout+stderr as text."""
    run_dir = tempfile.mkdtemp(prefix="hm")
    env = {k: v for k, v in os.environ.items() if not k.startswith("HANDMOCAP_")}
    env.update(HANDMOCAP_RUN_DIR=run_dir, HANDMOCAP_PARAMS=json.dumps(params))
    try:
        return subprocess.run([sys.executable, "-m", module], env=env, capture_output=True, text=True,
                              timeout=timeout_s)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
