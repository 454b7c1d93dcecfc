"""The detector's settings table in docs/reference.md, made from DetectorSettings: each field's
name, default and the comment beside it (above it, or at its end). One place says what a
setting does; this copies it where users read it.

    python scripts/settings_table.py            # rewrite the table in docs/reference.md
    python scripts/settings_table.py --check    # exit 1 when the table is out of date
"""
import argparse
import dataclasses
import inspect
import io
import sys
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from handmocap.perception.detector import DetectorSettings  # noqa: E402

DOC = ROOT / "docs" / "reference.md"
BEGIN = "<!-- detector settings: made by scripts/settings_table.py from DetectorSettings -->"
END = "<!-- end of detector settings -->"


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


def table() -> str:
    defaults, docs = DetectorSettings(), field_docs(DetectorSettings)
    rows = [BEGIN, "| setting | default | what it does |", "|---|---|---|"]
    for f in dataclasses.fields(DetectorSettings):
        value = getattr(defaults, f.name)
        shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else f"{value:g}" \
            if isinstance(value, float) else str(value)
        rows.append(f"| `{f.name}` | {shown} | {docs[f.name].replace('|', '/')} |")
    return "\n".join(rows + [END])


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 when docs/reference.md's table is out of date")
    args = p.parse_args()
    text = DOC.read_text()
    if BEGIN not in text or END not in text:
        sys.exit(f"{DOC}: no detector settings table (the lines {BEGIN!r} ... {END!r})")
    new = text[:text.index(BEGIN)] + table() + text[text.index(END) + len(END):]
    if args.check:
        sys.exit(0 if new == text else f"{DOC}: the detector settings table is out of date: "
                                       f"python scripts/settings_table.py")
    DOC.write_text(new)


if __name__ == "__main__":
    main()
