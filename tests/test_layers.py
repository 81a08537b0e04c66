"""The package layers import only downward (the contract is in pyproject.toml,
[tool.importlinter]): model -> measurement -> problem -> solve -> analysis -> workflow ->
outputs -> cli, with volcal.base below everything; and no module imports itself back
through others, inside a layer either (no import circle)."""
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_layers_import_only_downward():
    exe = shutil.which("lint-imports") or str(Path(sys.executable).parent / "lint-imports")
    if not Path(exe).exists():
        pytest.fail("import-linter is part of the test extras (pip install -e '.[test]')")
    run = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout


def test_no_python_callback_in_the_numerics():
    """No ca.Callback anywhere in src/: every CasADi Function can be expanded, serialised
    and code-generated."""
    hits = [str(p.relative_to(ROOT)) for p in (ROOT / "src").rglob("*.py")
            if "ca.Callback" in p.read_text() or "casadi.Callback" in p.read_text()]
    assert not hits, hits



def _strong_components(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (import circles)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    mods = sorted(set(edges) | {d for ds in edges.values() for d in ds})
    ix = {m: i for i, m in enumerate(mods)}
    pairs = [(ix[m], ix[d]) for m, ds in edges.items() for d in ds]
    rows, cols = (np.array(x, int) for x in zip(*pairs)) if pairs else ([], [])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(mods), len(mods)))
    n, label = connected_components(graph, directed=True, connection="strong")
    comps = [[mods[i] for i in np.flatnonzero(label == c)] for c in range(n)]
    return [c for c in comps if len(c) > 1]


def _import_graph() -> dict[str, set[str]]:
    """{module: the volcal modules it imports}, every import counted (also those inside
    functions, which run later but still tie the two modules together)."""
    import grimp

    g = grimp.build_graph("volcal", cache_dir=None)
    return {m: set(g.find_modules_directly_imported_by(m)) & g.modules for m in g.modules}


def test_strong_components_find_a_circle():
    """The detector itself: a circle through three modules is found, a chain is not."""
    circle = {"a.x": {"a.y"}, "a.y": {"a.z"}, "a.z": {"a.x"}, "a.w": {"a.x"}}
    assert _strong_components(circle) == [["a.x", "a.y", "a.z"]]
    assert _strong_components({"a.x": {"a.y"}, "a.y": {"a.z"}}) == []


def test_no_import_circle():
    """No module imports itself back through other modules, in any layer (the layers
    contract only sees imports between layers)."""
    import grimp

    g = grimp.build_graph("volcal", cache_dir=None)
    circles = _strong_components(_import_graph())
    described = []
    for comp in circles:
        # one concrete cycle to name: a shortest chain from the first member back to it
        a = comp[0]
        back = [
            g.find_shortest_chain(importer=b, imported=a)
            for b in g.find_modules_directly_imported_by(a)
            if b in comp
        ]
        chain = min((c for c in back if c), key=len, default=None)
        cycle = " -> ".join([a, *chain]) if chain else ", ".join(comp)
        described.append(f"{cycle} (circle of {len(comp)} modules: {', '.join(comp)})")
    assert not circles, "import circles:\n" + "\n".join(described)
