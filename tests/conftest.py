import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture
def run_dir(monkeypatch):
    """A private graph: its own run dir (short, for unix socket paths), in this process and children."""
    d = tempfile.mkdtemp(prefix="hm")
    monkeypatch.setenv("HANDMOCAP_RUN_DIR", d)
    yield Path(d)
    shutil.rmtree(d, ignore_errors=True)


def graph_env(run_dir: Path, **extra) -> dict:
    """Environment for a handlaunch subprocess: private run dir, test nodes importable."""
    env = {**os.environ, "HANDMOCAP_RUN_DIR": str(run_dir), "HANDMOCAP_VALIDATE_SEND": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])}
    env.update(extra)
    return env


def handlaunch(args, run_dir, timeout=60, **kw):
    return subprocess.run([sys.executable, "-m", "handmocap.launch", *map(str, args)], env=graph_env(run_dir),
                          capture_output=True, text=True, timeout=timeout, **kw)
