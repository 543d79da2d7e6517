"""The `--help` of every command line program: each option's default shown after its help.

`DefaultsHelpFormatter` is argparse's `ArgumentDefaultsHelpFormatter` without the noise:
"(default: X)" is appended only where there is a default to show (not None, not a False
switch, not already in the text), so `--radius-mr` reads "support radius in mesh resolutions
(default: 15.0)" and `--out` (no default) reads as written.
"""

from __future__ import annotations

import argparse

__all__ = ["DefaultsHelpFormatter"]


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
  """Help with "(default: X)" after every option whose default is a value (see module)."""

  def _get_help_string(self, action: argparse.Action) -> str | None:
    text = action.help or ""
    default = action.default
    if (default is None or default is False or default == [] or default is argparse.SUPPRESS
        or "%(default)" in text or "(default" in text.lower()):
      return action.help
    return super()._get_help_string(action)
