"""The README works as written: every ```python block runs, and every project command of its
```bash blocks (train.py, evaluate.py, lrf-frames, lrf-register) parses with that program's own
argument parser (the jobs are not run); train.py's config and overrides also load."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
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


def layout_entries() -> set[str]:
  """The paths the README's layout section lists (relative to the repository root): a tree with
  two spaces per level, each line's leading names (`a.py, b.py,` lists allowed) under the last
  folder (`name/`) of the level above; the description after them is not read."""
  section = README.read_text().split("\n## Layout", 1)[1].split("\n## ", 1)[0]
  block = section.split("```", 2)[1]
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
    assert len(folders) == level, f"README layout: {line!r} is indented under no folder"
    for name in names:
      entries.add("/".join([*folders, name.rstrip("/")]))
    if names[-1].endswith("/") and len(names) == 1:
      folders.append(names[-1].rstrip("/"))
  return entries


def test_layout_section_matches_the_tree():
  listed = layout_entries()
  missing = sorted(p for p in listed if not (REPO / p).exists())
  assert missing == [], f"README layout lists what does not exist: {missing}"
  package = REPO / "lrf_jax"
  actual = {str(p.relative_to(REPO)) for p in package.rglob("*.py")}
  actual |= {str(p.parent.relative_to(REPO)) for p in package.rglob("__init__.py")}
  unlisted = sorted(actual - listed)
  assert unlisted == [], f"README layout omits: {unlisted}"


def test_the_readme_stays_short():
  """The overview, the two commands, one example per task and links into docs/: at most
  16,000 characters (the rest belongs on the site)."""
  assert len(README.read_text(encoding="utf-8")) <= 16_000
