"""The library's three wings (handmocap/runtime, perception, training): the runtime and the
perception a user runs never import training (nor torch), and no two modules import each
other."""
import ast
import subprocess
import sys

from conftest import ROOT

RUNTIME_SIDE = [ROOT / "handmocap" / "runtime", ROOT / "handmocap" / "perception", ROOT / "nodes"]


def imports_of(path):
    """Every module a file imports (at any depth), as absolute dotted names."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def test_the_runtime_and_perception_never_import_training():
    offenders = {str(p.relative_to(ROOT)): sorted(m for m in imports_of(p) if m.startswith("handmocap.training"))
                 for folder in RUNTIME_SIDE for p in folder.rglob("*.py")}
    assert {k: v for k, v in offenders.items() if v} == {}
    code = ("import importlib, pkgutil, sys, handmocap.runtime, handmocap.perception, handmocap.nodes\n"
            "for pkg in (handmocap.runtime, handmocap.perception, handmocap.nodes):\n"
            "    for m in pkgutil.iter_modules(pkg.__path__):\n"
            "        importlib.import_module(f'{pkg.__name__}.{m.name}')\n"
            "print(sorted(m for m in sys.modules if m == 'torch' or m.startswith('handmocap.training')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_no_two_modules_import_each_other():
    files = {".".join(p.relative_to(ROOT).with_suffix("").parts): p for p in (ROOT / "handmocap").rglob("*.py")}
    graph = {name: {m for m in imports_of(p) if m in files and m != name} for name, p in files.items()}
    cycles = sorted({tuple(sorted((a, b))) for a, deps in graph.items() for b in deps if a in graph.get(b, ())})
    assert cycles == []


def test_no_file_cites_the_design_file_a_clone_lacks():
    """DESIGN.md was the first contract, outside the repo; its content now lives in messages/
    and docs/reference.md, and a user's clone has no DESIGN.md to follow a citation to."""
    files = [p for pattern in ("*.py", "*.md", "*.yaml") for p in ROOT.rglob(pattern)
             if not any(part in (".venv", "runs", ".git", "node_modules") for part in p.relative_to(ROOT).parts)]
    citing = [str(p.relative_to(ROOT)) for p in files if p.name != "test_layout.py" and "DESIGN.md" in p.read_text()]
    assert citing == []


def test_the_docs_tables_are_made_from_where_each_thing_is_declared():
    """docs/reference.md's detector settings and /hand/pose tables and the README's /hand/pose
    table are DetectorSettings' fields and comments and messages/HandPose.json's descriptions
    as they are (python scripts/doc_tables.py rewrites them); every setting has a comment and
    every /hand/pose field a description and a summary."""
    out = subprocess.run([sys.executable, str(ROOT / "scripts" / "doc_tables.py"), "--check"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    sys.path.insert(0, str(ROOT / "scripts"))
    from doc_tables import field_docs, pose_fields
    assert all(p.get("description") for _, p in pose_fields())
    assert all(p.get("x-summary") for name, p in pose_fields() if name.startswith("hands[i]."))

    from handmocap.perception.detector import DetectorSettings
    assert all(field_docs(DetectorSettings).values())


def test_every_detector_setting_is_a_detector_node_param_and_none_typed_ones_take_null():
    """A setting is declared once, as a DetectorSettings field: the node's params and the
    ones null may set follow from it."""
    import dataclasses

    from handmocap.nodes.detector import NULLABLE, PARAMS, setting
    from handmocap.perception.detector import DetectorSettings
    for f in dataclasses.fields(DetectorSettings):
        assert PARAMS[f.name] == getattr(DetectorSettings(), f.name)
        if f.name in NULLABLE:
            assert setting(f.name, None) is None
    assert {"side_every", "evict_margin", "handedness"} <= NULLABLE and "max_hands" not in NULLABLE


def test_the_wings_import_one_way():
    """perception (the maths, geometry included) and runtime (the bus, codec, bags, launcher)
    import neither each other nor the wings above them; interop (Foxglove, ROS 2, the bag
    command line) may import both; nothing in handmocap/ imports a node."""
    wing = lambda p: p.relative_to(ROOT / "handmocap").parts[0]   # noqa: E731
    forbidden = {"perception": ("handmocap.runtime", "handmocap.interop", "handmocap.training"),
                 "runtime": ("handmocap.perception", "handmocap.interop", "handmocap.training"),
                 "interop": ("handmocap.training",)}
    offenders = {}
    for p in (ROOT / "handmocap").rglob("*.py"):
        bad = [m for m in imports_of(p)
               if m.startswith("handmocap.nodes") or m.startswith(forbidden.get(wing(p), ()))]
        if bad:
            offenders[str(p.relative_to(ROOT))] = sorted(bad)
    assert offenders == {}
