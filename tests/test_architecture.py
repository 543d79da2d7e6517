"""The package's shape: no import cycle between modules nor between the package's parts
(`lrf_jax.X`: a subpackage or a module beside `lrf_jax/__init__.py`), function-level imports
included; no dynamic imports hiding one; no function over 80 code lines."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "lrf_jax"
MAX_FUNCTION_LINES = 80


def _modules() -> dict[str, Path]:
  out = {}
  for path in PACKAGE.rglob("*.py"):
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
      parts = parts[:-1]
    out[".".join(parts)] = path
  return out


def _is_type_checking(node: ast.If) -> bool:
  test = node.test
  return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
      isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, name: str, is_package: bool) -> list[str]:
  """Every module name an import statement anywhere in `tree` loads (not under TYPE_CHECKING)."""
  found = []

  def visit(node):
    for child in ast.iter_child_nodes(node):
      if isinstance(child, ast.If) and _is_type_checking(child):
        for sub in child.orelse:
          visit_one(sub)
        continue
      visit_one(child)

  def visit_one(node):
    if isinstance(node, ast.Import):
      found.extend(a.name for a in node.names)
    elif isinstance(node, ast.ImportFrom):
      if node.level:
        base = name.split(".") if is_package else name.split(".")[:-1]
        base = base[:len(base) - node.level + 1]
        mod = ".".join(base + ([node.module] if node.module else []))
      else:
        mod = node.module
      found.append(mod)
      found.extend(f"{mod}.{a.name}" for a in node.names)  # submodules, if they are ones
    visit(node)

  visit(tree)
  return found


def import_graph() -> dict[str, set[str]]:
  """module -> the lrf_jax modules it makes Python execute (the package `lrf_jax` itself left
  out: it is the public facade that imports everything; a subpackage counts for modules outside
  it, since importing `lrf_jax.frames.spec` runs `lrf_jax/frames/__init__.py` first)."""
  modules = _modules()
  graph = {}
  for name, path in modules.items():
    edges = set()
    is_package = path.name == "__init__.py"
    for target in _imports(ast.parse(path.read_text()), name, is_package):
      if target not in modules:
        continue
      parts = target.split(".")
      for i in range(2, len(parts) + 1):
        mod = ".".join(parts[:i])
        if mod != name and not name.startswith(mod + "."):
          edges.add(mod)
    graph[name] = edges
  return graph


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
  """Strongly connected components with more than one module (Tarjan)."""
  index, low, stack, on, out = {}, {}, [], set(), []

  def strong(v):
    index[v] = low[v] = len(index)
    stack.append(v)
    on.add(v)
    for w in graph.get(v, ()):
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
        out.append(sorted(comp))

  for v in sorted(graph):
    if v not in index:
      strong(v)
  return out


def package_of(module: str) -> str:
  """The part of the package `module` belongs to: `lrf_jax.X` for `lrf_jax.X` and everything
  under it."""
  return ".".join(module.split(".")[:2])


def package_graph(modules: dict[str, set[str]] | None = None) -> dict[str, set[str]]:
  """`lrf_jax.X` -> the other parts of the package its modules import (anywhere in a module,
  inside functions included; the facade `lrf_jax` itself left out, as in `import_graph`), from
  `modules` (default: `import_graph()`)."""
  graph: dict[str, set[str]] = {}
  for module, targets in (import_graph() if modules is None else modules).items():
    if module == "lrf_jax":
      continue
    part = package_of(module)
    graph.setdefault(part, set()).update(
        package_of(t) for t in targets if t != "lrf_jax" and package_of(t) != part)
  return graph


# Package cycles still there, each with what it takes to remove it (none since 0.8); the test
# fails on any cycle not listed here and when a listed one is gone.
KNOWN_PACKAGE_CYCLES: list[list[str]] = []


def test_import_graph_has_no_cycle():
  graph = import_graph()
  assert len(graph) > 40 and graph["lrf_jax.frames.compute"]  # the walk sees the package
  assert find_cycles(graph) == []


def test_package_graph_has_no_cycle():
  graph = package_graph()
  assert {"lrf_jax.frames", "lrf_jax.learning", "lrf_jax.search", "lrf_jax.registration"} <= set(graph)
  assert "lrf_jax.frames" in graph["lrf_jax.learning"]  # the walk sees the edges
  assert find_cycles(graph) == KNOWN_PACKAGE_CYCLES


def test_package_graph_counts_function_level_imports_and_merges_subpackages():
  parts = package_graph({"lrf_jax.a.x": {"lrf_jax.b.y"}, "lrf_jax.b.y": {"lrf_jax.a"},
                         "lrf_jax.a": {"lrf_jax.a.x"}, "lrf_jax": {"lrf_jax.a", "lrf_jax.b"}})
  assert parts == {"lrf_jax.a": {"lrf_jax.b"}, "lrf_jax.b": {"lrf_jax.a"}}
  assert find_cycles(parts) == [["lrf_jax.a", "lrf_jax.b"]]
  src = "def f():\n  import lrf_jax.frames.weights\n"
  assert "lrf_jax.frames.weights" in _imports(ast.parse(src), "lrf_jax.learning.model", False)


def test_cycle_detection_sees_function_level_imports():
  src = "def f():\n  from lrf_jax.b import g\n"
  assert "lrf_jax.b" in _imports(ast.parse(src), "lrf_jax.a", False)
  assert find_cycles({"a": {"b"}, "b": {"a"}, "c": set()}) == [["a", "b"]]


def test_no_dynamic_imports():
  """importlib only loads config files by path; nothing imports a module by a computed name."""
  for path in PACKAGE.rglob("*.py"):
    text = path.read_text()
    assert "__import__(" not in text, path
    assert "import_module(" not in text, path


def _code_lines(node: ast.AST, lines: list[str]) -> int:
  body = getattr(node, "body", [])
  doc = set()
  if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
      and isinstance(body[0].value.value, str):
    doc = set(range(body[0].lineno, body[0].end_lineno + 1))
  count = 0
  for i in range(node.lineno, node.end_lineno + 1):
    text = lines[i - 1].strip()
    if text and not text.startswith("#") and i not in doc:
      count += 1
  return count


def longest_functions(n: int = 5) -> list[tuple[int, str]]:
  """The n longest top-level functions and methods (nested functions count toward theirs)."""
  found = []
  for path in PACKAGE.rglob("*.py"):
    text = path.read_text()
    lines = text.splitlines()

    def walk(node):
      for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
          found.append((_code_lines(child, lines),  # noqa: B023 (called in this iteration)
                        f"{path.relative_to(PACKAGE.parent)}:{child.lineno} {child.name}"))  # noqa: B023 (called in this iteration)
        elif isinstance(child, ast.ClassDef):
          walk(child)

    walk(ast.parse(text))
  return sorted(found, reverse=True)[:n]


def test_no_function_over_80_code_lines():
  longest = longest_functions()
  assert longest[0][0] <= MAX_FUNCTION_LINES, longest


def private_imports_across_packages() -> list[str]:
  """`from lrf_jax.X... import _name` in a module outside `lrf_jax.X` (each part of the package
  reaches another only through public names)."""
  found = []
  for name, path in _modules().items():
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith(
          "lrf_jax."):
        assert node.module is not None
        for alias in node.names:
          if alias.name.startswith("_") and package_of(node.module) != package_of(name):
            found.append(f"{name} <- {node.module}.{alias.name}")
  return found


def test_no_private_name_is_imported_across_packages():
  assert private_imports_across_packages() == []


MAX_MODULE_LINES = 600


def test_no_module_over_600_lines():
  long = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
          if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
  assert long == {}


def test_no_module_imports_the_package_itself():
  """Inside the package, a module imports what it uses from its module, never the facade
  `lrf_jax` (which would load every part lazily, back up the layers)."""
  found = []
  for path in PACKAGE.rglob("*.py"):
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.Import) and any(a.name == "lrf_jax" for a in node.names):
        found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}")
      elif (isinstance(node, ast.ImportFrom) and node.module == "lrf_jax" and node.level == 0
            and any(a.name[:1].islower() and a.name not in _SUBPACKAGES() for a in node.names)):
        found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}")
  assert found == []


def _SUBPACKAGES() -> set[str]:  # noqa: N802 -- a constant, computed
  return {p.stem if p.suffix else p.name for p in PACKAGE.iterdir()
          if (p.is_dir() and (p / "__init__.py").exists()) or p.suffix == ".py"}


def test_the_layout_pages_import_table_is_the_package_graph():
  """docs/layout.md's "Packages and their imports" lists `package_graph()` as it is."""
  text = (PACKAGE.parent / "docs" / "layout.md").read_text()
  block = text.split("## Packages and their imports", 1)[1].split("```text\n", 1)[1]
  listed = {}
  for line in block.split("```", 1)[0].splitlines():
    name, _, targets = line.partition("->")
    listed[f"lrf_jax.{name.strip()}"] = {f"lrf_jax.{t.strip()}" for t in targets.split(",")
                                         if t.strip() not in ("", "-")}
  assert listed == package_graph()


# Private names read by another module: none since 0.9 (a name shared by sibling modules is
# public within its package, e.g. `search.grid.cell_reach`, or lives where it is used). The set
# stays empty: a new private use across modules fails the test.
KNOWN_PRIVATE_USES: set[tuple[str, str, str]] = set()


def private_uses() -> set[tuple[str, str, str]]:
  """(module file, other module, name) for every `_name` of another lrf_jax module a module
  imports (`from m import _name`) or reads (`m._name`)."""
  out = set()
  for path in PACKAGE.rglob("*.py"):
    tree = ast.parse(path.read_text())
    rel = str(path.relative_to(PACKAGE.parent))
    aliases = {}
    for node in ast.walk(tree):
      if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lrf_jax"):
        for a in node.names:
          if a.name.startswith("_") and not a.name.startswith("__"):
            out.add((rel, node.module, a.name))
          aliases[a.asname or a.name] = f"{node.module}.{a.name}"
      elif isinstance(node, ast.Import):
        aliases.update({a.asname: a.name for a in node.names
                        if a.asname and a.name.startswith("lrf_jax")})
    for node in ast.walk(tree):
      if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
          and not node.attr.startswith("__") and isinstance(node.value, ast.Name)
          and node.value.id in aliases):
        out.add((rel, aliases[node.value.id], node.attr))
  return out


def test_private_names_stay_in_their_module():
  assert private_uses() == KNOWN_PRIVATE_USES
