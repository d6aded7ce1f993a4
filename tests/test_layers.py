"""The package's layer contract, checked on its source (no exception list).

Packages form tiers; data flows one way, from the lower tiers to the higher ones:

    _runtime  <  color  <  io  <  geometry, lighting  <  rendering  <  fitting, live, validation
              <  bench  <  cli

1. A module imports from its own package or from a lower tier, never from a higher tier or a
   sibling of its own tier.
2. Across packages it imports public names of the package itself (``spectral_fit.lighting``),
   never a private module (``spectral_fit.lighting._environment``) or a private name; the
   private ``_runtime`` package's modules are the shared ground every tier builds on.
3. No import cycles between modules, counting imports inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "spectral_fit"
TIERS = [["_runtime"], ["color"], ["io"], ["geometry", "lighting"], ["rendering"],
         ["fitting", "live", "validation"], ["bench"], ["cli"]]
RANK = {p: i for i, tier in enumerate(TIERS) for p in tier}


def _modules() -> dict[str, Path]:
    out = {}
    for p in PACKAGE.rglob("*.py"):
        parts = list(p.relative_to(PACKAGE.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, imported module, imported names) of every import in the module (any depth)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                parts = base[: len(base) - node.level + 1]
                target = ".".join(parts + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] == "spectral_fit":
                names = [a.name for a in node.names]
                # "from package import module" imports the module
                subs = [f"{target}.{n}" for n in names if f"{target}.{n}" in MODULES]
                if subs:
                    out += [(node.lineno, s, []) for s in subs]
                    names = [n for n in names if f"{target}.{n}" not in MODULES]
                if names or not subs:
                    out.append((node.lineno, target, names))
        elif isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names
                    if a.name.split(".")[0] == "spectral_fit"]
    return out


def _domain(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANK else None


def test_every_package_has_a_tier():
    packages = {p.parent.name for p in PACKAGE.glob("*/__init__.py")}
    assert packages == set(RANK), packages ^ set(RANK)
    loose = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert loose == ["__init__.py", "__main__.py"], loose


def _violations() -> list[str]:
    bad = []
    for name, path in sorted(MODULES.items()):
        mine = _domain(name)
        if mine is None:  # spectral_fit/__init__.py and __main__.py: the public face
            continue
        for line, target, names in _imports(name, path):
            theirs = _domain(target)
            where = f"{path.relative_to(PACKAGE.parent)}:{line}"
            if theirs is None:
                if target == "spectral_fit":
                    bad.append(f"{where}: imports the top-level package ({names})")
                continue
            if theirs == mine:
                continue
            if RANK[theirs] >= RANK[mine]:
                bad.append(f"{where}: {mine} (tier {RANK[mine]}) imports {target} "
                           f"(tier {RANK[theirs]})")
            if theirs != "_runtime":
                rest = target.split(".")[2:]
                if any(p.startswith("_") for p in rest):
                    bad.append(f"{where}: imports the private module {target}")
                private = [n for n in names if n.startswith("_")]
                if private:
                    bad.append(f"{where}: imports private names {private} from {target}")
    return bad


def test_layers_and_public_boundaries():
    bad = _violations()
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    graph = {name: {t for _, t, _ in _imports(name, path) if t in MODULES and t != name}
             for name, path in MODULES.items()}
    # a package's __init__ that lazily names its modules imports none of them: the edges
    # here are real imports only
    index, low, stack, on, cycles = {}, {}, [], set(), []

    def strong(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    assert not cycles, cycles


@pytest.mark.parametrize("package", sorted(RANK))
def test_package_exports_resolve(package):
    """Every name a package's ``__init__`` lists is defined by the module it names."""
    import importlib

    mod = importlib.import_module(f"spectral_fit.{package}")
    for name in getattr(mod, "__all__", []):
        assert getattr(mod, name) is not None, (package, name)
