"""Option values shared by lrf-register's two-scan and multiway command lines (kept apart from
both: `cli.register` hands over to `cli.multiway`)."""

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
