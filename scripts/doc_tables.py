"""The tables the docs take from the one place each thing is declared: the detector's and the
ik node's settings (DetectorSettings' and PoseSettings' fields, defaults and the comments
beside them) and `/hand/pose`'s fields
(messages/HandPose.json and the header of messages/common.json: each property's
`description`, `x-shape`, `x-unit`, `x-summary`). Each table sits between two marker lines.

    python scripts/doc_tables.py            # rewrite the tables in docs/reference.md and README.md
    python scripts/doc_tables.py --check    # exit 1 when a table is out of date
"""
import argparse
import dataclasses
import inspect
import io
import json
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handmocap.perception.detector import DetectorSettings  # noqa: E402
from handmocap.perception.pose import PoseSettings  # noqa: E402

MESSAGES = ROOT / "messages"


def marker(name):
    """The lines a table `name` sits between."""
    return f"<!-- {name}: made by scripts/doc_tables.py -->", f"<!-- end of {name} -->"


def field_docs(cls) -> dict[str, str]:
    """{field name: its comment} of a dataclass, read from its source: the comment lines
    right above the field and the comment at the end of its line, joined."""
    names = {f.name for f in dataclasses.fields(cls)}
    docs, above, current = {}, [], None
    for tok in tokenize.generate_tokens(io.StringIO(inspect.getsource(cls)).readline):
        if tok.type == tokenize.COMMENT:
            text = tok.string.lstrip("#").strip()
            if current is not None:              # at the end of the field's own line
                docs[current] = f"{docs[current]} {text}".strip()
            else:
                above.append(text)
        elif tok.type == tokenize.NAME and tok.start[1] == 4 and tok.string in names and current is None:
            current, docs[tok.string], above = tok.string, " ".join(above), []
        elif tok.type == tokenize.NEWLINE:
            current = None
    return docs


def settings_table(cls) -> str:
    """| setting | default | what it does | of a settings dataclass (DetectorSettings, PoseSettings)."""
    defaults, docs = cls(), field_docs(cls)
    rows = ["| setting | default | what it does |", "|---|---|---|"]
    for f in dataclasses.fields(cls):
        value = getattr(defaults, f.name)
        shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else f"{value:g}" \
            if isinstance(value, float) else str(value)
        rows.append(f"| `{f.name}` | {shown} | {docs[f.name].replace('|', '/')} |")
    return "\n".join(rows)


def pose_fields():
    """[(field, property)] of /hand/pose: the header's, `hands`, then each hand's."""
    header = json.loads((MESSAGES / "common.json").read_text())["$defs"]["header"]["properties"]
    pose = json.loads((MESSAGES / "HandPose.json").read_text())["properties"]["hands"]
    return ([(f"header.{k}", v) for k, v in header.items()] + [("hands", pose)] +
            [(f"hands[i].{k}", v) for k, v in pose["items"]["properties"].items()])


def pose_table(summary=False) -> str:
    """/hand/pose's fields: in full (reference), or with their summaries (README, `x-summary`
    only)."""
    rows = ["| field | shape, dtype | unit, frame | meaning |", "|---|---|---|---|"]
    for name, prop in pose_fields():
        text = prop.get("x-summary") if summary else prop.get("description")
        if text:
            rows.append(f"| `{name}` | {prop.get('x-shape', '')} | {prop.get('x-unit', '')} | {text} |")
    return "\n".join(rows)


TABLES = {"detector settings": (ROOT / "docs" / "reference.md", lambda: settings_table(DetectorSettings)),
          "pose settings": (ROOT / "docs" / "reference.md", lambda: settings_table(PoseSettings)),
          "HandPose fields": (ROOT / "docs" / "reference.md", pose_table),
          "HandPose summary": (ROOT / "README.md", lambda: pose_table(summary=True))}


def rewritten(text: str, name: str, table: str, path: Path) -> str:
    begin, end = marker(name)
    if begin not in text or end not in text:
        sys.exit(f"{path}: no {name} table (the lines {begin!r} ... {end!r})")
    return text[:text.index(begin)] + f"{begin}\n{table}\n{end}" + text[text.index(end) + len(end):]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 when a table is out of date")
    args = p.parse_args()
    stale = []
    for path in sorted({path for path, _ in TABLES.values()}):
        text = path.read_text()
        new = text
        for name, (where, make) in TABLES.items():
            if where == path:
                new = rewritten(new, name, make(), path)
        if new != text:
            stale.append(str(path.relative_to(ROOT)))
            if not args.check:
                path.write_text(new)
    if args.check and stale:
        sys.exit(f"out of date: {', '.join(stale)} (python scripts/doc_tables.py)")


if __name__ == "__main__":
    main()
