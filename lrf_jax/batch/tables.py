"""The job's tables: the PAIRS.tsv a registration job reads (`read_pairs`) and the results.tsv
every job writes (`tsv`), and the rule for the names that name its output files
(`check_name`)."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path
from typing import Any
from collections.abc import Iterable, Sequence

__all__ = ["PairRow", "absolute", "check_name", "check_unique", "read_pair_rows", "read_pairs", "tsv"]

_MAX_NAME_BYTES = 200  # leaves room for a suffix and the temporary file's decorations


def check_name(name: str, where: str) -> str:
  """`name` if it can name an output file in the job's folder, else ValueError naming `where`:
  empty, "." or "..", starting with ".", a path separator, a control character (a tab or a
  newline would also break results.tsv) or over `_MAX_NAME_BYTES` bytes."""
  bad = (not name or name in (".", "..") or name.startswith(".") or "/" in name or "\\" in name
         or any(ord(ch) < 32 or ord(ch) == 127 for ch in name)
         or len(name.encode("utf-8", "surrogateescape")) > _MAX_NAME_BYTES)
  if bad:
    raise ValueError(f"{where}: expected a file name without a folder or control characters, "
                     f"not starting with '.', at most {_MAX_NAME_BYTES} bytes, got {name!r}")
  return name


def _tsv_text(p: Path) -> str:
  """The text of a PAIRS.tsv: UTF-8 (a byte-order mark dropped), or UTF-16 with its mark (a
  spreadsheet's "Unicode text"); ValueError naming the file and the line of a bad byte."""
  try:
    data = p.read_bytes()
  except OSError as e:
    raise ValueError(f"{p}: could not read it ({e.strerror or e})") from None
  encoding = "utf-16" if data[:2] in (b"\xff\xfe", b"\xfe\xff") else "utf-8-sig"
  try:
    text = data.decode(encoding)
  except UnicodeDecodeError as e:
    line = data[:e.start].count(b"\n") + 1
    raise ValueError(f"{p}: line {line}: expected UTF-8 text, found the byte "
                     f"0x{data[e.start]:02x}") from None
  if "\0" in text:
    line = text[:text.index("\0")].count("\n") + 1
    raise ValueError(f"{p}: line {line}: expected text, found a NUL byte")
  return text


def _tsv_lines(p: Path) -> list[tuple[int, list[str]]]:
  """(line number, fields) of each non-blank line of a PAIRS.tsv. Fields are split at tabs
  only and stripped; a field wholly in double quotes (as spreadsheets quote) is unquoted, ""
  standing for one quote; any other quote is part of the field (no field spans lines)."""
  out = []
  for lineno, line in enumerate(re.split(r"\r\n|\r|\n", _tsv_text(p)), start=1):
    fields = []
    for field in line.split("\t"):
      field = field.strip()
      if len(field) >= 2 and field[0] == field[-1] == '"':
        field = field[1:-1].replace('""', '"')
      fields.append(field)
    if any(fields):
      out.append((lineno, fields))
  return out


def _tsv_header(p: Path, lines: list[tuple[int, list[str]]]) -> list[str]:
  if not lines:
    raise ValueError(f"{p}: expected a header line naming the columns source and target, "
                     "found an empty file")
  lineno, header = lines[0]
  for col in ("source", "target"):
    if col not in header:
      raise ValueError(f"{p}: line {lineno}: expected a header with the columns source and "
                       f"target (tab-separated), found {header}")
  named = [c for c in header if c]
  twice = sorted({c for c in named if named.count(c) > 1})
  if twice:
    raise ValueError(f"{p}: line {lineno}: column {twice[0]!r} appears twice in the header")
  return header


def read_pairs(path: str | os.PathLike) -> list[tuple[str, str, str]]:
  """The pairs of a PAIRS.tsv (`read_pair_rows`) as [(name, source, target)], paths absolute;
  the `gt` column, if any, left out."""
  return [(r.name, r.source, r.target) for r in read_pair_rows(path)]


@dataclasses.dataclass(frozen=True)
class PairRow:
  """One row of a PAIRS.tsv: its name, the source and target paths, the ground truth's path and
  the init's (None: no `gt` / `init` column, or an empty cell), all absolute."""
  name: str
  source: str
  target: str
  gt: str | None = None
  init: str | None = None


def read_pair_rows(path: str | os.PathLike) -> list[PairRow]:
  """The rows of a PAIRS.tsv: a tab-separated file (UTF-8; blank lines skipped) with a header
  naming the columns `source` and `target` (paths; relative ones are relative to the TSV's
  folder), optionally `name` (default: the data row's number, 1-based, zero-padded to 4
  digits: 0001, ..., 9999, 10000; a name that does not change when pairs are appended) and
  optionally `gt` (a 4 x 4 source->target transform file, as `lrf-register --out` writes it,
  relative to the TSV's folder; may be empty in a row) and optionally `init` (the same kind of
  file: the pair is registered from it, `register(..., init=T)`; may be empty in a row). Other
  columns are ignored.

  Returns:
    The rows in the file's order.

  Raises:
    FileNotFoundError: no such file.
    ValueError: not text, a missing or repeated column, a row with more fields than the
      header, an empty source or target, a name that cannot name a file or a repeated name
      (also ignoring case: one file on a case-insensitive file system); the message names the
      file, the line and the field.
  """
  p = Path(path).expanduser()
  if not p.is_file():
    what = "not a regular file" if p.exists() else "no such file"
    raise FileNotFoundError(f"{path}: {what} (expected a PAIRS.tsv)")
  lines = _tsv_lines(p)
  header = _tsv_header(p, lines)
  out: list[PairRow] = []
  seen: dict[str, int] = {}
  for row, (lineno, fields) in enumerate(lines[1:], start=1):
    where = f"{p}: line {lineno}"
    if any(fields[len(header):]):
      raise ValueError(f"{where}: {len(fields)} tab-separated fields, but the header names "
                       f"{len(header)} columns")
    rec = dict(zip(header, fields))
    for col in ("source", "target"):
      if not rec.get(col):
        raise ValueError(f"{where}: column {col}: expected a path, found nothing")
    # Zero-padded to 4 digits whatever the number of rows: appending the 10000th pair must not
    # rename (and so redo) the 9999 before it.
    name = check_name(rec.get("name") or f"{row:04d}", f"{where}: column name")
    if name.casefold() in seen:
      raise ValueError(f"{where}: column name: {name!r} is also the name of line "
                       f"{seen[name.casefold()]} (ignoring case); names must be unique")
    seen[name.casefold()] = lineno
    src, tgt = (absolute(p.parent / Path(rec[c]).expanduser()) for c in ("source", "target"))
    gt, init = (absolute(p.parent / Path(rec[c]).expanduser()) if rec.get(c) else None
                for c in ("gt", "init"))
    out.append(PairRow(name, src, tgt, gt, init))
  return out


def absolute(path: str | os.PathLike) -> str:
  """`path` absolute with its links resolved as far as they resolve: a symlink loop or a missing
  file stays as it is (the item that reads it says what is wrong), never an exception here."""
  return os.path.realpath(os.path.expanduser(path))


def check_unique(names: Sequence[str]) -> None:
  """ValueError when two items share a name, also ignoring case (their outputs would be one
  file on a case-insensitive file system)."""
  seen: dict[str, str] = {}
  for name in names:
    if name.casefold() in seen:
      raise ValueError(f"names: {seen[name.casefold()]!r} and {name!r} would name the same "
                       "output file; names must be unique (also ignoring case)")
    seen[name.casefold()] = name


def _cell(value: Any) -> str:
  """`value` as one results.tsv cell: a tab, line break or other control character (a scan's
  path may hold one) written as its backslash escape (\\t, \\n, \\r, \\xNN), so that a row is
  one line and a cell one field."""
  text = str(value)
  if not any(ord(ch) < 32 or ord(ch) == 127 for ch in text):
    return text
  named = {"\t": "\\t", "\n": "\\n", "\r": "\\r"}
  return "".join(named.get(ch, f"\\x{ord(ch):02x}") if ord(ch) < 32 or ord(ch) == 127 else ch
                 for ch in text)


def tsv(columns: Sequence[str], rows: Iterable[dict[str, Any]]) -> str:
  cell = _cell
  lines = ["\t".join(columns)]
  lines += ["\t".join(cell(r.get(c, "")) for c in columns) for r in rows]
  return "\n".join(lines) + "\n"
