"""Tables shared by a study's run.py, its README and its test.

A study's run.py collects its printed tables as ``{name: markdown}``, writes them to
``<out>/tables.md`` and ``<out>/tables.json`` (:func:`write_tables`) and, with
``--update-readme``, copies them into the README between the markers::

    <!-- table: NAME -->
    | ... markdown table ... |
    <!-- /table -->

so every figure of a README table is the script's output, not a hand copy.  The tests
compare the keys (header and first column) of each marked README table with the keys of the
same table in the smoke output (:func:`table_keys`) and, given a ``tolerance``, every figure
of every cell (:func:`check_readme_against`): the full run's figures must agree with the
smoke run's within what its smaller trial counts allow.

Output folders: :func:`output_folder` gives a fresh temporary folder for ``--smoke`` runs
without ``--out``, so a smoke run never writes into the repository.
"""
from __future__ import annotations

import json
import re
import sys
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


def print_and_publish(
    tables: dict[str, str], last_line: str, readme: Path, update: bool, smoke: bool
) -> None:
    """The end of a study's run: print every table under a ``## name`` heading, then
    ``last_line`` (where the results are); with ``update`` (``--update-readme``) copy the
    tables into ``readme`` (:func:`update_readme`) and say on stderr which it replaced,
    refused (SystemExit) for a smoke run, whose figures are not the README's."""
    for name, tab in tables.items():
        print(f"\n## {name}\n\n{tab}")
    print(last_line)
    if update:
        if smoke:
            raise SystemExit("--update-readme with --smoke would put smoke figures in the README")
        done = update_readme(readme, tables)
        print(f"{Path(readme).name}: updated {', '.join(done) or 'nothing'}", file=sys.stderr)


def _cells(line: str) -> list[str]:
    # a pipe with a backslash before it (markdown's escape, as in U(|d|)) is part of a cell
    inner = line.strip()
    inner = inner[1:] if inner.startswith("|") else inner
    inner = inner[:-1] if inner.endswith("|") and not inner.endswith("\\|") else inner
    return [c.strip() for c in re.split(r"(?<!\\)\|", inner)]


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


_NUM = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")

#: a tolerance: relative, or (relative, absolute) in the cell's own unit; None: not compared
Tol = float | tuple[float, float] | None


def _figures(cell: str) -> tuple[str, list[str]]:
    """(the cell with every number replaced by '#', the numbers as printed)."""
    return _NUM.sub("#", cell), _NUM.findall(cell)


def _decimals(text: str) -> int:
    mant = text.lower().split("e")[0]
    return len(mant.split(".")[1]) if "." in mant else 0


def compare_cells(a: str, b: str, tol: Tol = 0.0) -> bool:
    """Do two printed cells agree?  Their text apart from the numbers must be equal; each
    number within ``tol`` (relative, or (relative, absolute)) plus half a unit of the last
    printed digit (so 1.2 and 1.25 agree at tol 0: the same value, printed differently)."""
    if tol is None:
        return True
    rtol, atol = (float(tol), 0.0) if not isinstance(tol, tuple) else map(float, tol)
    ta, na = _figures(a)
    tb, nb = _figures(b)
    if ta != tb or len(na) != len(nb):
        return False
    for x, y in zip(na, nb):
        fx, fy = float(x), float(y)
        half = 0.5 * 10.0 ** -min(_decimals(x), _decimals(y))
        if abs(fx - fy) > atol + rtol * max(abs(fx), abs(fy)) + half * (1 + 1e-9):
            return False
    return True


def _rows(md: str) -> tuple[list[str], list[list[str]]]:
    lines = [ln for ln in md.strip().splitlines() if ln.strip().startswith("|")]
    return _cells(lines[0]), [_cells(ln) for ln in lines[2:]]


def check_readme_against(
    readme: Path,
    tables: dict[str, str],
    key_cols: int = 1,
    *,
    tolerance: Tol | dict[str, Tol | dict[str, Tol]] = None,
) -> list[str]:
    """Differences between the marked tables of ``readme`` and ``tables`` (a run's
    tables.json): missing tables, headers or first-column keys that differ, and, with a
    ``tolerance``, figures that differ (:func:`compare_cells`).  Empty when they agree.

    tolerance: None compares keys only (as before); a number or (rtol, atol) every figure
    of every table; a dict {table: tol} per table, where tol may itself be a dict
    {column header: tol} (columns not named compared at 0, i.e. as printed) and None leaves
    a table or a column out; tables not in the dict are compared at 0."""
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
        if tolerance is None or h1 != h2 or k1 != k2:
            continue
        tol = tolerance.get(name, 0.0) if isinstance(tolerance, dict) else tolerance
        if tol is None:
            continue
        head, rows1 = _rows(md)
        _, rows2 = _rows(tables[name])
        for r1, r2 in zip(rows1, rows2):
            for j, (a, b) in enumerate(zip(r1, r2)):
                t = tol.get(head[j], 0.0) if isinstance(tol, dict) else tol
                if not compare_cells(a, b, t):
                    problems.append(
                        f"{name}: row {r1[:key_cols]}, column {head[j]!r}: README {a!r} != "
                        f"run.py {b!r} (tolerance {t})"
                    )
    return problems
