"""The options of `register` on every command line that registers (lrf-register's two-scan and
multiway forms, lrf-batch register): the flags derived from `RegisterOptions` (its fields, in
kebab case, with their defaults and help), read back as `register`'s keywords, and checked
before any work with the flag named in the message.

A flag renamed keeps its old name as an alias for a release (one action, several option
strings: the field metadata's `aliases`, or a hand-written flag's extra names); `AliasedFlag`
records which name was typed, and `as_typed` spells a message's flag that way."""

from __future__ import annotations

import argparse
import re
from typing import Any

KEYPOINT_DETECTORS = ("random", "iss")


def parse_keypoints(value: Any, option: str = "--keypoints") -> dict[str, Any]:
  """`register`'s keywords for a --keypoints value: a count (`n_keypoints`) or a detector name
  (`keypoints`).

  Raises:
    ValueError: neither a positive integer nor a name in `KEYPOINT_DETECTORS`.
  """
  text = str(value).strip()
  if text.lower() in KEYPOINT_DETECTORS:
    return {"keypoints": text.lower()}
  try:
    count = int(text)
  except ValueError:
    count = 0
  if count < 1:
    raise ValueError(f"{option}: expected a positive integer or a detector name "
                     f"({', '.join(KEYPOINT_DETECTORS)}), got {value!r}")
  return {"n_keypoints": count}


def option_message(message: str, keywords: dict[str, str]) -> str:
  """`message` of a library ValueError ("n_keypoints: ...") with its leading keyword replaced by
  the command-line option that sets it (`keywords`: keyword -> argparse dest)."""
  name, sep, rest = message.partition(": ")
  if sep and name in keywords:
    return f"--{keywords[name].replace('_', '-')}: {rest}"
  return message


# The attribute of a parsed namespace that holds {flag: the name it was typed under} for the
# flags with several names that were given (`AliasedFlag`).
TYPED_FLAGS = "typed_flags"


class AliasedFlag(argparse.Action):
  """argparse's "store" for a flag with several names (the first its name, the others old names
  kept as aliases): it also records in the namespace (`TYPED_FLAGS`) which name was typed, so
  that a message can name the flag as the user wrote it (`as_typed`)."""

  def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
               values: Any, option_string: str | None = None) -> None:
    setattr(namespace, self.dest, values)
    typed = dict(getattr(namespace, TYPED_FLAGS, None) or {})
    typed[self.option_strings[0]] = option_string or self.option_strings[0]
    setattr(namespace, TYPED_FLAGS, typed)


def alias_help(text: str, aliases: tuple[str, ...] | list[str]) -> str:
  """`text`, the help of a flag, followed by its old names (`aliases`), as every `--help` shows
  them."""
  if not aliases:
    return text
  return f"{text} (old name{'s' if len(aliases) > 1 else ''}: {', '.join(aliases)})"


def as_typed(message: str, args: Any) -> str:
  """`message` with each flag of several names that `args` (a parsed namespace) holds named as
  it was typed: "--keypoint-voxel-mr: ..." reads "--voxel-mr: ..." after `--voxel-mr 0.01`."""
  for flag, typed in (getattr(args, TYPED_FLAGS, None) or {}).items():
    if typed != flag:
      message = re.sub(r"(?<![\w-])" + re.escape(flag) + r"(?![\w-])", typed, message)
  return message


# Old spellings of flags still accepted (hidden): old flag -> field.
_OLD_FLAGS = {"--correspondences": "n_correspondences", "--icp": "icp_mode"}
# Fields set by one shared flag rather than their own: --keypoints N|DETECTOR.
_KEYPOINT_FIELDS = ("keypoints", "n_keypoints")


def _flag_type(annotation: str) -> Any:
  """argparse's `type` for a `RegisterOptions` field annotation ("float | None" -> float)."""
  for name, kind in (("float", float), ("int", int)):
    if annotation.split(" | ")[0] == name:
      return kind
  return None


def add_option_flags(ap: Any, fields: Any, defaults: dict[str, Any], *,
                     skip: tuple[str, ...] = (), suppress_defaults: bool = False,
                     helps: dict[str, str] | None = None) -> None:
  """Add to the argparse parser `ap` one flag per field of an options class (`fields`: its
  `dataclasses.Field`s, whose metadata holds the help, flag, choices and metavar; `defaults`:
  {field: default}) but those in `skip`: the field's name in kebab case (or the metadata's
  `flag`), its default and its help (`helps` replaces a field's help where a command line means
  more by it). A boolean defaulting to False is a `--flag`; one defaulting to True is
  `--flag/--no-flag`. `keypoints` and `n_keypoints` share `--keypoints N|DETECTOR`. The
  metadata's `aliases` (a renamed flag's old names) are further names of the same flag, shown
  in its help, and recorded when typed (`AliasedFlag`, `as_typed`).

  With `suppress_defaults` a flag not given leaves no attribute in the parsed namespace (the
  help still quotes the default), so that only the options a user gave are read back
  (`register_overrides`): `lrf-batch` takes the defaults of the job that way.
  """
  for field in fields:
    meta, name = field.metadata, field.name
    if name == "keypoints" and "n_keypoints" in defaults and name not in skip:
      count = defaults["n_keypoints"]
      ap.add_argument("--keypoints", default=argparse.SUPPRESS if suppress_defaults else str(count),
                      metavar="N|DETECTOR",
                      help="keypoints per cloud: a count of seeded random points, or a detector "
                           f"name: 'iss' (ISS keypoints, at most {count}) or 'random'")
    shared = name in _KEYPOINT_FIELDS and "n_keypoints" in defaults
    if name in skip or shared or meta["flag"] is None:
      continue
    flag = meta["flag"] or "--" + name.replace("_", "-")
    default = defaults[name]
    kw: dict[str, Any] = dict(dest=name, default=default,
                              help=(helps or {}).get(name, meta["help"]))
    if isinstance(default, bool):
      kw["action"] = "store_true" if not default else argparse.BooleanOptionalAction
    elif name.endswith("viewpoint"):
      kw.update(type=float, nargs=3, metavar=meta["metavar"])
    else:
      kw.update(type=_flag_type(str(field.type)), choices=meta["choices"],
                metavar=meta["metavar"])
    kw = {k: v for k, v in kw.items() if v is not None or k == "default"}
    aliases = tuple(meta.get("aliases", ()))
    if aliases:
      if isinstance(default, bool) or kw.get("nargs") is not None:
        raise TypeError(f"{name}: aliases are for flags of one value, not {flag}'s")
      kw.update(action=AliasedFlag, help=alias_help(kw["help"], aliases))
    if suppress_defaults:
      kw["default"] = argparse.SUPPRESS
      if default is not None:
        kw["help"] += f" (default: {default})"
    ap.add_argument(flag, *aliases, **kw)
    for old, target in _OLD_FLAGS.items():
      if target == name:
        ap.add_argument(old, dest=name, type=kw.get("type"), choices=kw.get("choices"),
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)


def add_register_flags(ap: Any, *, skip: tuple[str, ...] = (),
                       suppress_defaults: bool = False) -> None:
  """Add to the argparse parser `ap` one flag per field of `RegisterOptions` but those in `skip`
  (`add_option_flags`; defaults from `lrf_jax.registration.options.DEFAULTS`, help from the
  fields of its groups, `option_fields`)."""
  from lrf_jax.registration import options as opts
  add_option_flags(ap, opts.option_fields(), opts.DEFAULTS.as_dict(), skip=skip,
                   suppress_defaults=suppress_defaults)


def add_multiway_flags(ap: Any, *, helps: dict[str, str] | None = None) -> None:
  """Add to the argparse parser `ap` one flag per field of `MultiwayOptions`
  (`add_option_flags`; defaults from `lrf_jax.multiway.options.DEFAULTS`): the pair options and
  the graph's."""
  from lrf_jax.multiway import options as opts
  add_option_flags(ap, opts.option_fields(), opts.DEFAULTS.as_dict(), helps=helps)


def add_frame_flags(ap: Any, *, skip: tuple[str, ...] = (),
                    suppress_defaults: bool = False) -> None:
  """Add to the argparse parser `ap` one flag per field of
  `lrf_jax.batch.scan_frames.FrameOptions` but those in `skip` (`add_option_flags`; `cloud`
  has none: a command line takes it as its positional argument)."""
  import dataclasses

  from lrf_jax.batch.scan_frames import FrameOptions
  defaults = FrameOptions()
  add_option_flags(ap, dataclasses.fields(FrameOptions),
                   {f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)},
                   skip=skip, suppress_defaults=suppress_defaults)


def add_bin_layout_flag(ap: Any) -> None:
  """Add `--bin-layout xyzi|xyz` (how `.bin` inputs are read: `lrf_jax.io.read_cloud`'s
  `bin_layout`) to the argparse parser `ap` of a command line that registers; its default is
  the parser's (None; none with `argument_default=SUPPRESS`). `lrf-frames` and `lrf-batch
  frames` take it from `FrameOptions`' field of the same name."""
  import dataclasses

  from lrf_jax.batch.scan_frames import FrameOptions
  field = {f.name: f for f in dataclasses.fields(FrameOptions)}["bin_layout"]
  ap.add_argument("--bin-layout", dest="bin_layout", choices=field.metadata["choices"],
                  help=field.metadata["help"])


def register_overrides(args: Any) -> dict[str, Any]:
  """The `register` keywords (`RegisterOptions` fields) the flags present in `args` set;
  `--keypoints` parsed (`parse_keypoints`).

  Raises:
    ValueError: a bad --keypoints.
  """
  from lrf_jax.registration.options import FIELDS
  out = {name: getattr(args, name) for name in FIELDS
         if name not in _KEYPOINT_FIELDS and hasattr(args, name)}
  for name in ("source_viewpoint", "target_viewpoint"):
    if out.get(name) is not None:
      out[name] = tuple(out[name])
  if getattr(args, "keypoints", None) is not None:
    out.update(parse_keypoints(args.keypoints))
  return out


def register_problem(args: Any, flags: dict[str, str] | None = None) -> str | None:
  """What `RegisterOptions` refuses among the options present in `args`, named by the flag that
  sets it (`flags`: field -> flag where it is not the field's own, e.g. a shared --viewpoint);
  None: fine."""
  from lrf_jax.checks import validate_seed
  from lrf_jax.registration.options import FIELDS, check_register_options
  try:
    validate_seed(getattr(args, "seed", 0), "--seed")
  except ValueError as e:
    return str(e)
  try:
    overrides = register_overrides(args)
  except ValueError as e:  # a bad --keypoints, named already
    return str(e)
  try:
    check_register_options(**overrides)
  except ValueError as e:
    names = {**{f: f for f in FIELDS}, "n_keypoints": "keypoints", **(flags or {})}
    return option_message(str(e), names)
  return None


def options_table(cls: type) -> str:
  """The Markdown table of the options class `cls` (a dataclass whose fields hold their help in
  `metadata`: `RegisterOptions`' groups, `GraphOptions`, `FrameOptions`), as the docs' stage
  pages show it: one row per field, in the class's order, with its Python keyword, its flag (read
  from the parser `add_option_flags` builds for the class: hidden old spellings left out, "-"
  for none), its default and its help (and the flag's choices). `|` is escaped; a value holding
  one is left out of backticks, since Markdown dialects disagree on a pipe in a code span.

  `python -m lrf_jax.cli.options --docs docs/` rewrites every table of the pages in place: a
  table sits between `<!-- options: lrf_jax.registration.options.MatchOptions -->` (its class)
  and `<!-- /options -->`; `--check` writes nothing and exits 1 where one differs
  (`tests/test_docs.py` checks the same).

  Args:
    cls: the options class.

  Returns:
    The table, one line per row, ending with a newline.
  """
  import dataclasses

  def cell(text: Any, code: bool = False) -> str:
    text = " ".join(str(text).split())
    if code and "|" not in text and "`" not in text:
      return f"`{text}`"
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("<", "&lt;")

  fields = dataclasses.fields(cls)
  instance = cls()  # every field at its default
  defaults = {f.name: getattr(instance, f.name) for f in fields}
  ap = argparse.ArgumentParser(add_help=False)
  add_option_flags(ap, fields, defaults)
  flags: dict[str, list[str]] = {}
  for action in ap._actions:
    if action.help != argparse.SUPPRESS and action.option_strings:
      values = " " + " ".join(action.metavar) if isinstance(action.metavar, tuple) else ""
      flags.setdefault(action.dest, []).extend(f + values for f in action.option_strings)
  if "n_keypoints" in defaults and "keypoints" in flags:  # one flag: --keypoints N|DETECTOR
    flag = flags.pop("keypoints")[0]
    flags["keypoints"], flags["n_keypoints"] = [f"{flag} DETECTOR"], [f"{flag} N"]
  rows = ["| field | flag | default | help |", "|---|---|---|---|"]
  for f in fields:
    old_names = f.metadata.get("aliases", ())
    flag_cell = ", ".join(cell(n, code=True) + (" (old name)" if n in old_names else "")
                          for n in flags.get(f.name, [])) or "-"
    text = cell(f.metadata.get("help", ""))
    if f.metadata.get("choices"):
      text += "; one of " + ", ".join(cell(c, code=True) for c in f.metadata["choices"])
    rows.append(f"| {cell(f.name, code=True)} | {flag_cell} | "
                f"{cell(repr(defaults[f.name]), code=True)} | {text} |")
  return "\n".join(rows) + "\n"


if __name__ == "__main__":  # python -m lrf_jax.cli.options --docs docs/ [--check]
  import sys
  from pathlib import Path

  from lrf_jax.batch.scan_frames import FrameOptions
  from lrf_jax.multiway.options import GraphOptions
  from lrf_jax.registration.options import GROUPS

  _classes = {f"{c.__module__}.{c.__name__}": c
              for c in (*GROUPS.values(), GraphOptions, FrameOptions)}

  _ap = argparse.ArgumentParser(prog="python -m lrf_jax.cli.options",
                                description="Rewrite the options tables of the docs' pages "
                                "(`options_table`) in place.")
  _ap.add_argument("--docs", default="docs", metavar="DIR", help="the docs folder (default: docs)")
  _ap.add_argument("--check", action="store_true",
                   help="write nothing; exit 1 when a page's table differs from the generated one")
  _args = _ap.parse_args()

  def _table(m: re.Match) -> str:
    if m.group(1) not in _classes:
      sys.exit(f"error: no options class {m.group(1)}; expected one of {sorted(_classes)}")
    return (f"<!-- options: {m.group(1)} -->\n\n{options_table(_classes[m.group(1)])}\n"
            "<!-- /options -->")

  _stale = []
  for _page in sorted(Path(_args.docs).rglob("*.md")):
    _text = _page.read_text()
    _new = re.sub(r"<!-- options: ([\w.]+) -->\n.*?<!-- /options -->", _table, _text, flags=re.S)
    if _new != _text:
      _stale.append(_page)
      if not _args.check:
        _page.write_text(_new)
      print(f"{'stale' if _args.check else 'rewritten'}: {_page}")
  sys.exit(1 if _args.check and _stale else 0)
