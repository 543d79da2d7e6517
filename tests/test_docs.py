"""The documentation site works as written: every page mkdocs.yml lists exists, every name its API
pages document imports, and every example marked runnable (`<!-- run -->` on the line above a
```python block; `<!-- run: data -->` for one that needs the real data under LRF_DATA) runs."""

from __future__ import annotations

import importlib
import os
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
MKDOCS = REPO / "mkdocs.yml"


def nav_pages() -> list[str]:
  """The .md files mkdocs.yml's nav lists (relative to docs/); read as text, no YAML parser."""
  nav = MKDOCS.read_text().split("\nnav:", 1)[1]
  return re.findall(r":\s*([\w./-]+\.md)\s*$", nav, flags=re.M)


def runnable_blocks() -> list[tuple[str, int, str, bool]]:
  """(page, line, code, needs data) of every runnable example of the pages."""
  out = []
  for page in sorted(DOCS.rglob("*.md")):
    text = page.read_text()
    for m in re.finditer(r"^<!-- run(: data)? -->\n```python\n(.*?)^```", text, flags=re.S | re.M):
      line = text[:m.start()].count("\n") + 2
      out.append((str(page.relative_to(REPO)), line, m.group(2), bool(m.group(1))))
  return out


def test_every_page_of_the_nav_exists_and_every_page_is_in_the_nav():
  pages = nav_pages()
  assert len(pages) >= 13
  missing = [p for p in pages if not (DOCS / p).is_file()]
  assert missing == [], f"mkdocs.yml lists pages that do not exist: {missing}"
  unlisted = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md"))
  assert sorted(set(unlisted) - set(pages)) == []


def _api_names() -> list[str]:
  names = []
  for page in sorted((DOCS / "api").glob("*.md")):
    names += re.findall(r"^::: ([\w.]+)\s*$", page.read_text(), flags=re.M)
  return names


@pytest.mark.parametrize("name", _api_names())
def test_every_name_of_the_api_pages_imports(name):
  parts = name.split(".")
  for i in range(len(parts), 0, -1):  # the longest importable module, then attributes
    try:
      obj = importlib.import_module(".".join(parts[:i]))
    except ModuleNotFoundError:
      continue
    for attr in parts[i:]:
      obj = getattr(obj, attr)
    return
  pytest.fail(f"{name} does not import")


def test_the_pages_have_runnable_examples():
  blocks = runnable_blocks()
  assert len(blocks) >= 4
  assert any("register(" in code for _, _, code, _ in blocks)


EXAMPLES = [pytest.param(page, line, code, needs_data, id=f"{page}:{line}",
                         marks=[pytest.mark.data] if needs_data else [])
            for page, line, code, needs_data in runnable_blocks()]


@pytest.mark.parametrize("page,line,code,needs_data", EXAMPLES)
def test_runnable_example(page, line, code, needs_data, tmp_path, monkeypatch):
  if needs_data and not os.environ.get("LRF_DATA"):
    pytest.skip("needs the real data under LRF_DATA")
  import lrf_jax
  monkeypatch.chdir(tmp_path)  # whatever an example writes lands here
  before = set(lrf_jax.METHODS)
  try:
    exec(compile(code, f"{page}:{line}", "exec"), {"__name__": "docs"})
  finally:
    for name in set(lrf_jax.METHODS) - before:  # an example that registers a toy method
      del lrf_jax.METHODS[name]


def test_the_first_commands_last_line_names_places_that_exist():
  """`python evaluate.py` (the README's first command) ends with where to go next: the
  commands it names are console scripts of the package and the page it names is in the site."""
  import tomllib

  import evaluate
  scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
  for command in ("lrf-register", "lrf-batch"):
    assert f"`{command} " in evaluate.NEXT_STEPS and command in scripts
  assert "docs/getting-started.md" in evaluate.NEXT_STEPS
  assert (REPO / "docs" / "getting-started.md").is_file()
