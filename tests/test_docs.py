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


# The options tables of the pipeline-stage pages: between `<!-- options: CLASS -->` and
# `<!-- /options -->`, rendered by `lrf_jax.cli.options.options_table`
# (`python -m lrf_jax.cli.options --docs docs/` rewrites them).
OPTIONS_TABLE = re.compile(r"<!-- options: ([\w.]+) -->\n(.*?)<!-- /options -->", flags=re.S)


def _options_class(path: str) -> type:
  module, _, name = path.rpartition(".")
  return getattr(importlib.import_module(module), name)


def _options_tables() -> list[tuple[str, str, str]]:
  """(page, class path, the table as the page has it) of every options table of the pages."""
  return [(str(page.relative_to(DOCS)), m.group(1), m.group(2))
          for page in sorted(DOCS.rglob("*.md")) for m in OPTIONS_TABLE.finditer(page.read_text())]


def _options_classes() -> dict[str, type]:
  """Every options class of the package ({dotted path: class}): the dataclasses of the modules
  that build fields with `option_field`, whose fields hold their help in `metadata`."""
  import dataclasses
  import inspect

  classes = {}
  for path in sorted((REPO / "lrf_jax").rglob("*.py")):
    if "option_field(" not in path.read_text():
      continue
    module = importlib.import_module(".".join(path.relative_to(REPO).with_suffix("").parts))
    for name, obj in inspect.getmembers(module, inspect.isclass):
      if (obj.__module__ == module.__name__ and obj.__name__ == name  # not an alias
          and dataclasses.is_dataclass(obj)
          and any("help" in f.metadata for f in dataclasses.fields(obj))):
        classes[f"{module.__name__}.{name}"] = obj
  return classes


def test_every_options_table_is_the_generated_one():
  from lrf_jax.cli.options import options_table
  tables = _options_tables()
  assert len(tables) >= 9
  stale = [f"{page}: {path}" for page, path, table in tables
           if table.strip() != options_table(_options_class(path)).strip()]
  assert stale == [], (f"options tables differ from their fields' help: {stale}; run "
                       "`python -m lrf_jax.cli.options --docs docs/`")
  import subprocess
  import sys
  check = subprocess.run([sys.executable, "-m", "lrf_jax.cli.options", "--docs", str(DOCS),
                          "--check"], cwd=REPO, capture_output=True, text=True)
  assert check.returncode == 0, check.stdout + check.stderr  # it knows every page's class


def test_every_options_class_has_a_table_on_a_page_of_the_nav():
  classes = _options_classes()
  from lrf_jax.registration.options import GROUPS
  assert {c.__name__ for c in GROUPS.values()} | {"GraphOptions", "FrameOptions"} <= {
      c.__name__ for c in classes.values()}
  shown = {path for _, path, _ in _options_tables()}
  assert sorted(set(classes) - shown) == [], "options classes with no table on any page"
  assert sorted(shown - set(classes)) == [], "tables naming no options class"
  pages = set(nav_pages())
  assert sorted({page for page, _, _ in _options_tables()} - pages) == []


def test_the_tables_flags_are_the_command_lines():
  """Every flag a table names is a flag of the command line that takes the options, for the
  same field: lrf-register's (every `RegisterOptions` group), its multiway form's
  (`GraphOptions`) and lrf-frames' (`FrameOptions`)."""
  from lrf_jax.cli import frames, multiway, register
  parsers = {"lrf_jax.multiway.options.GraphOptions": multiway.build_parser(),
             "lrf_jax.batch.scan_frames.FrameOptions": frames.build_parser()}
  checked = 0
  for _, path, table in _options_tables():
    ap = parsers.get(path) or register.build_parser()
    for row in table.strip().splitlines()[2:]:
      field_cell, flags = row.split(" | ")[:2]
      field = field_cell.strip("| `")
      for flag in re.findall(r"`(--[\w-]+)", flags):
        checked += 1
        action = ap._option_string_actions.get(flag)
        assert action is not None, f"{path}: {flag} is no flag of the command line"
        assert action.dest in (field, "keypoints"), (path, flag, action.dest)
  assert checked >= 30


def test_the_regeneration_rewrites_a_stale_table(tmp_path):
  import subprocess
  import sys
  page = tmp_path / "page.md"
  marker = "<!-- options: lrf_jax.registration.options.IcpOptions -->"
  page.write_text(f"# A page\n\n{marker}\n\n| stale |\n\n<!-- /options -->\n\nText.\n")
  run = [sys.executable, "-m", "lrf_jax.cli.options", "--docs", str(tmp_path)]
  assert subprocess.run([*run, "--check"], cwd=REPO, capture_output=True).returncode == 1
  assert subprocess.run(run, cwd=REPO, capture_output=True).returncode == 0
  from lrf_jax.cli.options import options_table
  from lrf_jax.registration.options import IcpOptions
  assert page.read_text() == (f"# A page\n\n{marker}\n\n{options_table(IcpOptions)}\n"
                              "<!-- /options -->\n\nText.\n")
  assert subprocess.run([*run, "--check"], cwd=REPO, capture_output=True).returncode == 0


@pytest.mark.parametrize("function,options", [
    ("lrf_jax.registration.pipeline.register", "lrf_jax.registration.options.RegisterOptions"),
    ("lrf_jax.multiway.pipeline.register_all", "lrf_jax.multiway.options.MultiwayOptions")])
def test_the_keyword_args_of_the_docstrings_name_fields_with_their_types(function, options):
  """`register`'s and `register_all`'s docstrings list options of `**overrides` under "Keyword
  Args:" (Google style, for mkdocstrings) with their types: each is a field, of that type."""
  import inspect
  module, _, name = function.rpartition(".")
  doc = inspect.getdoc(getattr(importlib.import_module(module), name))
  section = doc.split("\nKeyword Args:\n", 1)[1].split("\n\n", 1)[0]
  listed = dict(re.findall(r"^  (\w+) \((.+?)\): ", section, flags=re.M))
  assert len(listed) >= 10
  flat = importlib.import_module(options.rpartition(".")[0])
  fields = {f.name: str(f.type) for f in flat.option_fields()}
  assert {k: fields.get(k) for k in listed} == listed
