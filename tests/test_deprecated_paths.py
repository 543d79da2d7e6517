"""The pre-0.7 names that still read (warning once); nothing of the project's own uses them."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

from lrf_jax import _deprecated

ROOT = Path(__file__).resolve().parents[1]


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
  aliases = {ROOT / "lrf_jax" / "_deprecated.py", Path(__file__).resolve()}
  return [f for f in files if f not in aliases]


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
