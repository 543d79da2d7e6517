"""The options of `register` on every command line that registers (lrf-register's two-scan and
multiway forms, lrf-batch register): the flags derived from `RegisterOptions` (its fields, in
kebab case, with their defaults and help), read back as `register`'s keywords, and checked
before any work with the flag named in the message."""

from __future__ import annotations

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


def add_register_flags(ap: Any, *, skip: tuple[str, ...] = ()) -> None:
  """Add to the argparse parser `ap` one flag per field of `RegisterOptions` (the field's name in
  kebab case; its default and help from `lrf_jax.registration.options.DEFAULTS` and the field)
  but the fields in `skip`; `keypoints` and `n_keypoints` share `--keypoints N|DETECTOR`."""
  import argparse
  import dataclasses

  from lrf_jax.registration import options as opts
  defaults = opts.DEFAULTS
  for field in dataclasses.fields(opts.RegisterOptions):
    meta, name = field.metadata, field.name
    if name == "keypoints" and name not in skip:
      ap.add_argument("--keypoints", default=str(defaults.n_keypoints), metavar="N|DETECTOR",
                      help="keypoints per cloud: a count of seeded random points, or a detector "
                           "name: 'iss' (ISS keypoints, at most "
                           f"{defaults.n_keypoints}) or 'random'")
    if name in skip or name in _KEYPOINT_FIELDS or meta["flag"] is None:
      continue
    flag = meta["flag"] or "--" + name.replace("_", "-")
    default = getattr(defaults, name)
    kw: dict[str, Any] = dict(dest=name, default=default, help=meta["help"])
    if isinstance(default, bool):
      kw["action"] = "store_true" if not default else argparse.BooleanOptionalAction
    elif name.endswith("viewpoint"):
      kw.update(type=float, nargs=3, metavar=meta["metavar"])
    else:
      kw.update(type=_flag_type(str(field.type)), choices=meta["choices"])
    ap.add_argument(flag, **{k: v for k, v in kw.items() if v is not None or k == "default"})
    for old, target in _OLD_FLAGS.items():
      if target == name:
        ap.add_argument(old, dest=name, type=kw.get("type"), choices=kw.get("choices"),
                        default=argparse.SUPPRESS, help=argparse.SUPPRESS)


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
  from lrf_jax.registration.options import FIELDS, check_register_options
  seed = getattr(args, "seed", 0)
  if isinstance(seed, int) and not 0 <= seed < 2**32:
    return f"--seed: expected an integer in [0, 2**32), got {seed}"
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
