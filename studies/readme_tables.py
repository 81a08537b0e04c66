"""Tables shared by a study's run.py, its README and its test.

A study's run.py collects its printed tables as ``{name: markdown}``, writes them to
``<out>/tables.md`` and ``<out>/tables.json`` (:func:`write_tables`) and, with
``--update-readme``, copies them into the README between the markers::

    <!-- table: NAME -->
    | ... markdown table ... |
    <!-- /table -->

so every figure of a README table is the script's output, not a hand copy.  The tests
compare the keys (header and first column) of each marked README table with the keys of the
same table in the smoke output (:func:`table_keys`).

Output folders: :func:`output_folder` gives a fresh temporary folder for ``--smoke`` runs
without ``--out``, so a smoke run never writes into the repository.
"""
from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path

_MARK = re.compile(r"<!-- table: *([\w.-]+) *-->\n(.*?)<!-- /table -->", re.S)


def output_folder(out: Path | None, smoke: bool, default: Path, study: str) -> Path:
    """``out`` if given; for a smoke run a new temporary folder; else ``default``."""
    if out is not None:
        return Path(out)
    if smoke:
        return Path(tempfile.mkdtemp(prefix=f"volcal-{study}-smoke-"))
    return Path(default)


def markdown(rows: list[dict], cols: list[str] | None = None, heads: list[str] | None = None,
             fmt=None) -> str:
    """A markdown table of ``rows`` (dicts); ``fmt(value) -> str`` formats the cells."""
    cols = cols or list(rows[0]) if rows else (cols or [])
    heads = heads or cols
    fmt = fmt or _fmt
    out = ["| " + " | ".join(heads) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        out.append("| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(out)


def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    try:
        v = float(v)
    except (TypeError, ValueError):
        return str(v)
    if v != v:
        return "-"
    if v == 0:
        return "0"
    if abs(v) >= 1e4 or abs(v) < 1e-2:
        return f"{v:.3g}"
    return f"{v:.3g}" if abs(v) < 100 else f"{v:.1f}"


def write_tables(out: Path, tables: dict[str, str]) -> None:
    """``tables.md`` (all tables, with their names) and ``tables.json`` ({name: markdown})."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tables.json").write_text(json.dumps(tables, indent=1) + "\n", encoding="utf-8")
    md = [f"<!-- table: {k} -->\n{v.strip()}\n<!-- /table -->\n" for k, v in tables.items()]
    (out / "tables.md").write_text("\n".join(md), encoding="utf-8")


def readme_tables(text: str) -> dict[str, str]:
    """The marked tables of a README: {name: markdown}."""
    return {m.group(1): m.group(2).strip() for m in _MARK.finditer(text)}


def update_readme(readme: Path, tables: dict[str, str]) -> list[str]:
    """Replace every marked table of ``readme`` that ``tables`` holds; returns the names
    replaced (tables without a marker are left out of the README)."""
    readme = Path(readme)
    text = readme.read_text(encoding="utf-8")
    done = []

    def sub(m):
        name = m.group(1)
        if name not in tables:
            return m.group(0)
        done.append(name)
        return f"<!-- table: {name} -->\n{tables[name].strip()}\n<!-- /table -->"

    new = _MARK.sub(sub, text)
    if new != text:
        readme.write_text(new, encoding="utf-8")
    return done


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def table_keys(md: str, key_cols: int = 1) -> tuple[tuple[str, ...], list[tuple[str, ...]]]:
    """(header, [first ``key_cols`` cells of every row]) of a markdown table."""
    lines = [ln for ln in md.strip().splitlines() if ln.strip().startswith("|")]
    if len(lines) < 2:
        raise ValueError("not a markdown table")
    head = tuple(_cells(lines[0]))
    rows = [tuple(_cells(ln)[:key_cols]) for ln in lines[2:]]
    return head, rows


def folder_state(folder: Path, ignore: tuple[str, ...] = ()) -> dict[str, tuple[int, int]]:
    """{relative path: (size, mtime_ns)} of every file under ``folder`` (byte-code caches
    and paths starting with one of ``ignore`` left out): what a test compares before and
    after a smoke run."""
    folder = Path(folder)
    out = {}
    for p in folder.rglob("*"):
        rel = p.relative_to(folder).as_posix()
        if p.is_file() and "__pycache__" not in p.parts and not rel.startswith(ignore):
            out[rel] = (p.stat().st_size, p.stat().st_mtime_ns)
    return out


def check_readme_against(readme: Path, tables: dict[str, str], key_cols: int = 1) -> list[str]:
    """Differences between the marked tables of ``readme`` and ``tables`` (a run's
    tables.json): missing tables, headers or first-column keys that differ.  Empty when
    they agree."""
    marked = readme_tables(Path(readme).read_text(encoding="utf-8"))
    problems = []
    if not marked:
        problems.append(f"{readme}: no marked tables")
    for name, md in marked.items():
        if name not in tables:
            problems.append(f"README table {name!r} is not printed by run.py")
            continue
        h1, k1 = table_keys(md, key_cols)
        h2, k2 = table_keys(tables[name], key_cols)
        if h1 != h2:
            problems.append(f"{name}: README header {h1} != run.py header {h2}")
        if k1 != k2:
            problems.append(f"{name}: README keys {k1} != run.py keys {k2}")
    return problems


if __name__ == "__main__":   # python studies/readme_tables.py README.md results/tables.json
    import sys

    readme, tables_json = sys.argv[1:3]
    names = update_readme(Path(readme), json.loads(Path(tables_json).read_text("utf-8")))
    print(f"{readme}: updated {', '.join(names) or 'nothing'}")
