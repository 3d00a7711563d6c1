"""Write ``benchmarks/results/MANIFEST.md``: for every generated result (each JSON file and each
report folder under ``benchmarks/results/``), the script and the command that made it.

The command is read from the file itself where it records one (``argv`` / ``command`` keys), else
from the lab notebook (``docs/lab/*.md``, the pages in the order of ``docs/lab/index.md``'s toctree):
the section that quotes the file and the nearest command line above the quote in that section
(``python benchmarks/...``, ``pocoloco ...``, ``bash scripts/...``). A result no section quotes is
listed as unreferenced, so stale files show up.

    python benchmarks/results_manifest.py            # rewrite MANIFEST.md
    python benchmarks/results_manifest.py --check    # exit 1 if MANIFEST.md is out of date
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
LAB = ROOT / "docs" / "lab"
NOT_QUOTED = "**not quoted in the lab notebook**"
COMMAND = re.compile(r"((?:python3? |torchrun [^`]*?)benchmarks/[\w/]+\.py[^`\n]*|pocoloco (?:bench|eval|train|data)[^`\n]*|bash scripts/[\w.]+[^`\n]*)")


def _pages() -> list[Path]:
    """The lab notebook's pages: ``index.md``, then its toctree's entries in order, then any other page."""
    index = LAB / "index.md"
    if not index.is_file():
        return sorted(LAB.glob("*.md"))
    pages = [index]
    block = re.search(r"```\{toctree\}\n(.*?)```", index.read_text(), re.S)
    for entry in block.group(1).splitlines() if block else []:
        entry = entry.strip()
        if entry and not entry.startswith(":"):
            page = LAB / (entry if entry.endswith(".md") else entry + ".md")
            if page.is_file() and page not in pages:
                pages.append(page)
    return pages + [p for p in sorted(LAB.glob("*.md")) if p not in pages]


def _sections(text: str, page: str) -> list[tuple[str, list[str]]]:
    """(``page`` § heading, lines) of every ``#`` / ``##`` / ``###`` section of one page, in order
    (lines inside fenced code blocks are never headings)."""
    out: list[tuple[str, list[str]]] = []
    fence = None
    for line in text.splitlines():
        m = re.match(r"(`{3,}|~{3,})", line)
        if fence is None and m:
            fence = m.group(1)
        elif fence is not None and line.strip() == fence:
            fence = None
        elif fence is None and re.match(r"#{1,3} ", line):
            out.append((f"`{page}` § {line.lstrip('#').strip()}", []))
            continue
        if out:
            out[-1][1].append(line)
    return out


def _recorded(path: Path) -> str | None:
    if path.suffix != ".json":
        return None
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    if isinstance(data, dict):
        for key in ("argv", "command"):
            value = data.get(key)
            if isinstance(value, list) and value:
                return " ".join(str(v) for v in value)
            if isinstance(value, str) and value:
                return value
    return None


def _script_of(command: str) -> str:
    m = re.search(r"benchmarks/[\w/]+\.py|scripts/[\w.]+", command)
    if m:
        return m.group(0)
    m = re.match(r"pocoloco (\w+(?: \w+)?)", command)
    return f"pocoloco {m.group(1)}" if m else "?"


def manifest() -> str:
    sections = [s for p in _pages() for s in _sections(p.read_text(), p.relative_to(ROOT).as_posix())]
    entries = sorted([p for p in RESULTS.iterdir() if p.suffix == ".json" or p.is_dir()], key=lambda p: p.name)
    rows = []
    for path in entries:
        name = path.name
        command = _recorded(path)
        where = ""
        quoted = re.compile(rf"(?<![\w-]){re.escape(name)}(?![\w-])")  # the name itself, not inside another
        for heading, lines in sections:
            hits = [i for i, line in enumerate(lines) if quoted.search(line)]
            if not hits:
                continue
            where = where or heading
            if command is None:
                for i in range(hits[0], -1, -1):  # the nearest command at or above the first quote
                    found = COMMAND.findall(lines[i])
                    if found:
                        command = found[-1].strip().rstrip("\\").strip()
                        break
            if command is not None:
                break
        script = _script_of(command) if command else _script_of(where) if where else "?"
        if script == "?":  # by name: bench_<prefix>.py (or an experiment) whose prefix the file starts with
            stems = sorted(((q.stem.removeprefix("bench_"), q) for q in (ROOT / "benchmarks").rglob("*.py")),
                           key=lambda sq: -len(sq[0]))  # fmt: skip
            match = next((q for stem, q in stems if name.startswith(stem)), None)
            script = match.relative_to(ROOT).as_posix() + " (by name)" if match else "?"
        status = where if where else NOT_QUOTED
        kind = "folder" if path.is_dir() else "json"
        rows.append(f"| `{name}`{'/' if kind == 'folder' else ''} | `{script}` | "
                    f"{'`' + command.replace('|', '/') + '`' if command else '(see the section)'} | {status} |")  # fmt: skip
    return "\n".join([
        "# What made each result",
        "",
        "Written by `python benchmarks/results_manifest.py` (do not edit by hand): each generated result",
        "in this folder, the script and command that made it (recorded in the file, or the nearest command",
        "line above the file's first quote in the lab notebook, `docs/lab/`), and the page and section of",
        "the lab notebook that discuss it. Results no section quotes are marked: they are candidates for",
        "removal.",
        "",
        "| result | script | command | lab notebook page § section |",
        "|---|---|---|---|",
        *rows,
        "",
    ])  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if MANIFEST.md is out of date")
    args = parser.parse_args()
    text = manifest()
    target = RESULTS / "MANIFEST.md"
    if args.check:
        if not target.is_file() or target.read_text() != text:
            print(f"{target}: out of date; run python benchmarks/results_manifest.py", file=sys.stderr)
            return 1
        return 0
    target.write_text(text)
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    unquoted = sum(NOT_QUOTED in line for line in rows)
    print(f"wrote {target} ({len(rows)} results, {unquoted} not quoted in the lab notebook)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
