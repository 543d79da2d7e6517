"""The README works as written: every ```python block runs, and every project command of its
```bash blocks (train.py, evaluate.py, lrf-frames, lrf-register) parses with that program's own
argument parser (the jobs are not run); train.py's config and overrides also load. It keeps the
two fresh-machine commands verbatim, its links lead to files and headings that exist, and it
stays short; the package's layout (docs/layout.md, linked from it) lists every module."""

from __future__ import annotations

import re
import shlex
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
LAYOUT = REPO / "docs" / "layout.md"
# The two commands a newcomer runs on a fresh machine (.ci/run runs the second): verbatim.
FIRST_COMMANDS = (
    'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[eval]" && python evaluate.py',
    'python3 -m venv .venv && . .venv/bin/activate && pip install -e ".[test]" && python -m pytest -q',
)
# Blocks that take over ~10 s on 2 cores (a whole registration); run by the slow suite.
SLOW_MARKERS = ("lrf_jax.register(",)


def _blocks(language: str) -> list[tuple[int, str]]:
  """(line number, text) of every fenced block of `language` in the README."""
  text = README.read_text()
  out = []
  for m in re.finditer(rf"^```{language}\n(.*?)^```", text, flags=re.S | re.M):
    out.append((text[:m.start()].count("\n") + 1, m.group(1)))
  return out


def _commands(block: str) -> list[list[str]]:
  """The simple commands of a bash block: continuation lines joined, comments dropped, split at
  `&&`, `;`, `&` and `|`, shell keywords and leading VAR=value assignments removed, `$VAR`
  replaced by 1 (the README's placeholders: process counts and indices)."""
  commands = []
  for line in block.replace("\\\n", " ").splitlines():
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    current = []
    for token in lexer:
      if token in (";", "&&", "&", "|", "||", ";;"):
        commands.append(current)
        current = []
      else:
        current.append(token)
    commands.append(current)
  out = []
  for cmd in commands:
    while cmd and (cmd[0] in ("do", "then", "done", "else") or re.match(r"^\w+=", cmd[0])):
      cmd = cmd[1:]
    out.append([re.sub(r"\$\{?\w+\}?", "1", t) for t in cmd])
  return [c for c in out if c]


def _project_command(cmd: list[str]) -> tuple[str, list[str]] | None:
  """(program, its arguments) for a command of this project, else None."""
  if cmd[0] in ("lrf-frames", "lrf-register"):
    return cmd[0], cmd[1:]
  if cmd[0] in ("python", "python3") and len(cmd) > 1:
    if cmd[1] in ("train.py", "evaluate.py"):
      return cmd[1], cmd[2:]
    if cmd[1:3] == ["-m", "lrf_jax.cli.register"]:
      return "lrf-register", cmd[3:]
  return None


def _parse(program: str, args: list[str]) -> None:
  if program == "lrf-frames":
    from lrf_jax.cli.frames import build_parser
    build_parser().parse_args(args)
  elif program == "lrf-register":
    from lrf_jax.cli import multiway as multiway_cli
    from lrf_jax.cli.register import build_parser
    if multiway_cli.wanted(build_parser(), args):  # more than two scans: the multiway command
      multiway_cli.build_parser().parse_args(args)
    else:
      build_parser().parse_args(args)
  elif program == "evaluate.py":
    import evaluate
    evaluate.build_parser().parse_args(args)
  else:
    import train
    from lrf_jax.learning import config as config_lib
    parsed = train.build_parser().parse_args(args)
    config_lib.replace(config_lib.load_config(parsed.config),
                       **config_lib.parse_overrides(parsed.overrides))


BASH = [(line, cmd) for line, block in _blocks("bash") for cmd in _commands(block)
        if _project_command(cmd)]


def test_the_readme_has_project_commands_and_python_blocks():
  programs = {_project_command(cmd)[0] for _, cmd in BASH}
  assert programs == {"train.py", "evaluate.py", "lrf-frames"} | (programs & {"lrf-register"})
  assert len(_blocks("python")) >= 3


@pytest.mark.parametrize("line,cmd", BASH, ids=[f"line{line}" for line, _ in BASH])
def test_bash_command_options_parse(line, cmd):
  program, args = _project_command(cmd)
  try:
    _parse(program, args)
  except SystemExit as e:  # argparse's error exit
    pytest.fail(f"README.md:{line}: `{shlex.join(cmd)}` does not parse ({e})")


def test_the_command_splitter_handles_the_readmes_shell():
  block = ('for I in 0 1; do\n  A=1 B=2 \\\n  python train.py --config smoke --process-id $I '
           'epochs=1 &\ndone; wait\npython evaluate.py --out x   # a comment\n')
  cmds = _commands(block)
  assert ["python", "train.py", "--config", "smoke", "--process-id", "1", "epochs=1"] in cmds
  assert ["python", "evaluate.py", "--out", "x"] in cmds


def test_a_bad_option_would_be_caught():
  with pytest.raises(SystemExit):
    _parse("evaluate.py", ["--no-such-option"])
  with pytest.raises(ValueError):
    _parse("train.py", ["--config", "smoke", "no_such_key=1"])


PYTHON = [pytest.param(block, id=f"line{line}",
                       marks=[pytest.mark.slow] if any(m in block for m in SLOW_MARKERS) else [])
          for line, block in _blocks("python")]


@pytest.mark.parametrize("block", PYTHON)
def test_python_block_runs(block, tmp_path, monkeypatch):
  import lrf_jax
  monkeypatch.chdir(tmp_path)  # whatever a block writes lands here
  before = set(lrf_jax.METHODS)
  try:
    exec(compile(block, str(README), "exec"), {"__name__": "readme"})
  finally:
    for name in set(lrf_jax.METHODS) - before:  # a block that registers a toy method
      del lrf_jax.METHODS[name]


def test_help_of_evaluate_and_train_shows_defaults_and_presets():
  import evaluate
  import train
  from lrf_jax.learning import config as config_lib
  text = " ".join(evaluate.build_parser().format_help().split())
  assert "(default: 1000)" in text and "(default: out/eval)" in text
  assert "(default: 15.0)" in text and "(default: None)" not in text
  text = " ".join(train.build_parser().format_help().split())
  assert "(default: default)" in text
  for name in config_lib.preset_names():
    assert name in text
  assert {"default", "smoke", "plus_soft"} <= set(config_lib.preset_names())


_ENTRY = re.compile(r"^[\w-]+(/|\.(py|toml|md|yml)),?$")


def layout_entries(text: str | None = None) -> set[str]:
  """The paths the layout page (docs/layout.md; or `text`) lists, relative to the repository
  root: its first fenced block, a tree with two spaces per level, each line's leading names
  (`a.py, b.py,` lists allowed) under the last folder (`name/`) of the level above; the
  description after them is not read."""
  text = LAYOUT.read_text() if text is None else text
  block = text.split("```", 2)[1]
  entries, folders = set(), []  # folders: the open folder at each level
  for line in block.splitlines()[1:]:
    if not line.strip():
      continue
    level = (len(line) - len(line.lstrip())) // 2
    names = []
    for token in line.split():
      if not _ENTRY.match(token):
        break
      names.append(token.rstrip(","))
    if not names:
      continue
    folders = folders[:level]
    assert len(folders) == level, f"docs/layout.md: {line!r} is indented under no folder"
    for name in names:
      entries.add("/".join([*folders, name.rstrip("/")]))
    if names[-1].endswith("/") and len(names) == 1:
      folders.append(names[-1].rstrip("/"))
  return entries


def test_layout_page_matches_the_tree():
  listed = layout_entries()
  missing = sorted(p for p in listed if not (REPO / p).exists())
  assert missing == [], f"docs/layout.md lists what does not exist: {missing}"
  package = REPO / "lrf_jax"
  actual = {str(p.relative_to(REPO)) for p in package.rglob("*.py")}
  actual |= {str(p.parent.relative_to(REPO)) for p in package.rglob("__init__.py")}
  unlisted = sorted(actual - listed)
  assert unlisted == [], f"docs/layout.md omits: {unlisted}"


def test_the_layout_reader_reads_nesting_and_lists():
  text = ("# Layout\n\n```text\nlrf_jax/\n  a.py          x\n  sub/          y\n"
          "    __init__.py, b.py,\n    c.py\n  d.py\ntrain.py  evaluate.py\n```\n")
  assert layout_entries(text) == {"lrf_jax", "lrf_jax/a.py", "lrf_jax/sub",
                                  "lrf_jax/sub/__init__.py", "lrf_jax/sub/b.py",
                                  "lrf_jax/sub/c.py", "lrf_jax/d.py", "train.py", "evaluate.py"}
  with pytest.raises(AssertionError):
    layout_entries("```\nlrf_jax/\n    deep.py\n```\n")


def test_the_two_commands_are_in_the_readme_verbatim():
  blocks = [block.strip() for _, block in _blocks("bash")]
  for command in FIRST_COMMANDS:
    assert command in blocks, f"README.md lost its fresh-machine command: {command}"
  assert blocks.index(FIRST_COMMANDS[0]) < blocks.index(FIRST_COMMANDS[1])


def _slug(heading: str) -> str:
  """A heading's anchor as Python-Markdown's toc extension makes it (mkdocs.yml uses it)."""
  text = unicodedata.normalize("NFKD", heading).encode("ascii", "ignore").decode()
  text = re.sub(r"[^\w\s-]", "", text).strip().lower()
  return re.sub(r"[-\s]+", "-", text)


def _anchors(page: Path) -> set[str]:
  text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)  # no # in code
  return {_slug(m) for m in re.findall(r"^#+\s+(.*?)\s*#*\s*$", text, flags=re.M)}


def readme_links() -> list[str]:
  """The README's relative Markdown links (`[text](target)`), web addresses left out."""
  text = re.sub(r"^```.*?^```", "", README.read_text(), flags=re.S | re.M)
  return [t for t in re.findall(r"\]\(([^)\s]+)\)", text) if not re.match(r"\w+:", t)]


def test_the_readmes_links_lead_to_files_and_headings_that_exist():
  links = readme_links()
  assert "docs/layout.md" in links and "docs/getting-started.md" in links
  broken = []
  for link in links:
    path, _, anchor = link.partition("#")
    target = REPO / path
    if not target.exists() or (anchor and anchor not in _anchors(target)):
      broken.append(link)
  assert broken == [], f"README.md links to what does not exist: {broken}"


def test_the_slugs_follow_the_site():
  assert _slug("A newcomer's path, timed (2026-12-04)") == "a-newcomers-path-timed-2026-12-04"
  assert _slug("The registry: adding an LRF method") == "the-registry-adding-an-lrf-method"


def test_every_readme_link_into_docs_is_a_page_of_the_site():
  from tests.test_docs import nav_pages
  pages = set(nav_pages())
  outside = [link for link in readme_links() if link.startswith("docs/")
             and link.partition("#")[0].removeprefix("docs/") not in pages]
  assert outside == [], f"README.md links to pages the site's nav does not list: {outside}"


def test_the_readme_stays_short():
  """The overview, the two commands, one example per task and links into docs/: at most
  9,000 characters (the rest belongs on the site)."""
  assert len(README.read_text(encoding="utf-8")) <= 9_000
