"""The pre-0.7 module paths: each still imports (warning once) and gives its new home's names;
nothing of the project's own (package, tests, benchmarks, scripts, README) uses them."""

from __future__ import annotations

import ast
import importlib
import re
import sys
import warnings
from pathlib import Path

import pytest

from lrf_jax import _deprecated

ROOT = Path(__file__).resolve().parents[1]
OLD_PATHS = sorted(_deprecated.MOVED)


def _fresh_import(name: str):
  """Imports the alias module `name` anew; returns (module, the DeprecationWarnings it raised)."""
  sys.modules.pop(name, None)
  parent, _, leaf = name.rpartition(".")
  if parent in sys.modules:
    vars(sys.modules[parent]).pop(leaf, None)
  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    module = importlib.import_module(name)
  return module, [w for w in caught if issubclass(w.category, DeprecationWarning)]


@pytest.mark.parametrize("old", OLD_PATHS)
def test_old_path_warns_and_forwards(old):
  new = importlib.import_module(_deprecated.MOVED[old])
  module, caught = _fresh_import(old)
  if old == "lrf_jax.console":  # the console scripts' target: forwards without a warning
    assert caught == []
  else:
    assert len(caught) == 1 and _deprecated.MOVED[old] in str(caught[0].message), caught
    assert "next release" in str(caught[0].message)
  public = getattr(new, "__all__", [n for n in vars(new) if not n.startswith("_")])
  for name in public:
    if not isinstance(getattr(new, name), type(sys)):
      assert getattr(module, name) is getattr(new, name), (old, name)


def test_old_package_names_forward_with_a_warning():
  from lrf_jax import geometry, registration
  from lrf_jax.geometry import ops
  from lrf_jax.registration import evidence, pipeline
  geometry._warned = registration._warned = False
  with pytest.warns(DeprecationWarning, match="lrf_jax.geometry.ops"):
    assert geometry.kabsch is ops.kabsch
  with pytest.warns(DeprecationWarning, match="lrf_jax.registration.evidence"):
    assert registration.verdict is evidence.verdict
  assert registration.register is pipeline.register  # the package's own interface: no warning
  with pytest.raises(AttributeError):
    geometry.no_such_name  # noqa: B018


def _sources() -> list[Path]:
  files = [*(ROOT / "lrf_jax").rglob("*.py"), *(ROOT / "tests").rglob("*.py"),
           *(ROOT / "benchmarks").glob("*.py"), ROOT / "train.py", ROOT / "evaluate.py"]
  aliases = {ROOT / "lrf_jax" / (p.removeprefix("lrf_jax.").replace(".", "/") + ".py")
             for p in OLD_PATHS} | {ROOT / "lrf_jax" / "configs" / "__init__.py"}
  aliases |= {ROOT / "lrf_jax" / "_deprecated.py", Path(__file__).resolve()}
  return [f for f in files if f not in aliases]


# `lrf_jax.engine` stays an attribute of the package for one release (it was in `__all__`).
ALLOWED = {"lrf_jax/__init__.py lrf_jax.engine"}


def _old(name: str) -> bool:
  return any(name == o or name.startswith(o + ".") for o in OLD_PATHS)


def test_nothing_of_ours_uses_an_old_path():
  found = []
  for path in _sources():
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
      if isinstance(node, ast.Import):
        found += [f"{path}:{node.lineno} {a.name}" for a in node.names if _old(a.name)]
      elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        names = [f"{node.module}.{a.name}" for a in node.names]
        found += [f"{path}:{node.lineno} {n}" for n in [node.module, *names] if _old(n)]
        if node.module == "lrf_jax.geometry":
          found += [f"{path}:{node.lineno} geometry.{a.name}" for a in node.names
                    if a.name in geometry_helpers()]
      elif isinstance(node, ast.Constant) and isinstance(node.value, str):
        found += [f"{path}:{node.lineno} {m}" for m in re.findall(r"lrf_jax\.[\w.]+", node.value)
                  if _old(m)]
  readme = (ROOT / "README.md").read_text()
  found += [f"README.md {m}" for m in re.findall(r"lrf_jax\.[\w.]+", readme) if _old(m)]
  found = [f for f in found if re.sub(r":\d+", "", f).removeprefix(str(ROOT) + "/")
           not in ALLOWED]
  assert found == []


def geometry_helpers() -> frozenset[str]:
  from lrf_jax import geometry
  return geometry._OPS_NAMES


@pytest.mark.parametrize("old", sorted(_deprecated.RENAMED))
def test_old_name_warns_and_forwards(old):
  """0.7's renamed constants ("neighbour" -> "neighbor", one name per radius fraction): the old
  name still gives the new one's value, warning once per access with the new name."""
  module_name, _, name = old.rpartition(".")
  module = importlib.import_module(module_name)
  new = _deprecated.RENAMED[old]
  with pytest.warns(DeprecationWarning, match=rf"{re.escape(module_name)}\.{new}\b") as caught:
    value = getattr(module, name)
  assert value == getattr(module, new) and len(caught) == 1
  assert name not in vars(module)  # only the alias: the module defines the new name alone
  with pytest.raises(AttributeError):
    getattr(module, name + "_NO_SUCH")


def test_descriptor_spec_host_fn_is_host_descriptors():
  from lrf_jax.descriptors import DESCRIPTORS
  spec = DESCRIPTORS["toldi"]
  with pytest.warns(DeprecationWarning, match="DescriptorSpec.host_descriptors"):
    assert spec.host_fn is spec.host_descriptors is not None


def test_nothing_of_ours_imports_an_old_name():
  found = []
  for path in _sources():
    for node in ast.walk(ast.parse(path.read_text())):
      if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
        found += [f"{path}:{node.lineno} {node.module}.{a.name}" for a in node.names
                  if f"{node.module}.{a.name}" in _deprecated.RENAMED]
      elif isinstance(node, ast.Attribute) and node.attr == "host_fn":
        found.append(f"{path}:{node.lineno} .host_fn")
  assert found == []
