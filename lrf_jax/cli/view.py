"""`lrf-view`: registrations and models in the browser (viser; the `viz` extra).

    lrf-view model/                       # lrf-register a.ply b.ply c.ply --out-dir model/
    lrf-view reg/                         # lrf-batch register pairs.tsv --out reg/
    lrf-view a.ply b.ply --transform T.txt

A multiway output folder shows every scan at its pose in its colour (a legend, a toggle per
scan) and the pose graph's edges between the scans' centroids (accepted, accepted but "not
sure", rejected); an lrf-batch register folder shows a picker of its pairs; two clouds show the
target with the source before and after the transform (`--transform`, as `lrf-register --out`
writes it). The page is served on 127.0.0.1 (this machine only) at `--port` (default: a free
one), printed on stdout, and opened in the default browser unless `--no-browser`. `--host`
names another address to listen on (e.g. 0.0.0.0: every interface; one warning line on stderr:
the page has no password). A cloud over `--max-points` points is shown as a seeded sample (one
line on stderr says so). Ctrl-C ends it: exit code 130. A bad command line, an input that is
none of the above or an address that cannot be listened on: one `error:` line, exit code 2
(`lrf_jax.cli.exits`). This file is thin: the viewer is `lrf_jax.viz`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NoReturn

from lrf_jax.cli.exits import refuse
from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.cli.interrupt import exit_with, interruptible
from lrf_jax.viz.scenes import MAX_POINTS
from lrf_jax.viz.server import DEFAULT_HOST

__all__ = ["build_parser", "console", "main"]


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(
      prog="lrf-view", allow_abbrev=False, formatter_class=DefaultsHelpFormatter,
      description="Show a multiway model (lrf-register --out-dir), the pairs of an lrf-batch "
                  "register folder, or two clouds and their transform in the browser.",
      epilog="examples: lrf-view model/ | lrf-view reg/ | lrf-view a.ply b.ply --transform "
             "T.txt")
  ap.add_argument("inputs", nargs="+", metavar="PATH",
                  help="FOLDER: an output folder of lrf-register --out-dir or of lrf-batch "
                       "register; or SOURCE TARGET: two clouds (any format lrf-register reads)")
  ap.add_argument("--transform", default=None, metavar="T.txt",
                  help="with two clouds: the 4x4 source->target (as lrf-register --out writes "
                       "it); the source is shown before and after it")
  ap.add_argument("--port", default=None, metavar="N",
                  help="the port to serve on (default: a free one, printed)")
  ap.add_argument("--host", default=DEFAULT_HOST,
                  help="the address to listen on; another than 127.0.0.1 serves other machines "
                       "too, without a password")
  ap.add_argument("--no-browser", action="store_true",
                  help="do not open the page in the default browser")
  ap.add_argument("--max-points", default=str(MAX_POINTS), metavar="N",
                  help="show at most N points per cloud (a seeded sample)")
  ap.add_argument("--seed", type=int, default=0, help="seed of that sample")
  return ap


def _positive_int(text: str, flag: str, what: str) -> int | str:
  """`text` as an int >= 1, else the problem's message."""
  try:
    value = int(text)
  except ValueError:
    return f"{flag}: expected {what}, got {text!r}"
  return value if value >= 1 else f"{flag}: expected {what}, got {value}"


def _check(args: argparse.Namespace) -> str | None:
  """What is wrong with the command line, before any file is read (None: fine); sets
  `args.port` and `args.max_points` to ints."""
  from lrf_jax.io.validation import file_problem
  if len(args.inputs) > 2:
    return (f"expected an output folder or two clouds (SOURCE TARGET), got {len(args.inputs)} "
            "paths")
  if args.port is not None:
    port = _positive_int(args.port, "--port", "a port number from 1 to 65535")
    if isinstance(port, str) or port > 65535:
      return port if isinstance(port, str) else \
          f"--port: expected a port number from 1 to 65535, got {port}"
    args.port = port
  max_points = _positive_int(args.max_points, "--max-points", "a positive number of points")
  if isinstance(max_points, str):
    return max_points
  args.max_points = max_points
  if len(args.inputs) == 1:
    if args.transform is not None:
      return ("--transform: only with two clouds (SOURCE TARGET); a folder holds its own "
              "transforms")
    from lrf_jax.viz.folders import folder_kind
    try:
      folder_kind(args.inputs[0])
    except ValueError as e:
      return str(e)
    return None
  for role, path in zip(("SOURCE", "TARGET"), args.inputs):
    problem = file_problem(path)
    if problem:
      return f"{role} {path}: {problem}"
  if args.transform is not None:
    problem = file_problem(args.transform)
    if problem:
      return f"--transform {args.transform}: {problem}"
  return None


@interruptible("the viewer stopped")
def main(argv: list[str] | None = None) -> int:
  args = build_parser().parse_args(argv)
  problem = _check(args)
  if problem:
    return refuse(problem)
  from lrf_jax.extras import MissingExtraError
  from lrf_jax.viz.api import content_of, folder_content, serve
  from lrf_jax.viz.server import address_problem, import_viser, print_address
  try:
    import_viser("lrf-view")
  except MissingExtraError as e:
    return refuse(str(e))
  problem = address_problem(args.host, args.port)  # before reading the clouds
  if problem:
    return refuse(problem)
  kw = dict(max_points=args.max_points, seed=args.seed)
  try:
    if len(args.inputs) == 1:
      content = folder_content(args.inputs[0], **kw)
    else:
      content = content_of(args.inputs[0], (args.inputs[1],), _transform(args), **kw)
  except (ValueError, OSError) as e:
    return refuse(str(e))
  try:
    viewer = serve(content, host=args.host, port=args.port, **kw)
  except ValueError as e:
    return refuse(str(e))
  print_address(viewer)
  if not args.no_browser and not viewer.open_browser():
    print("note: no web browser found here; open the address above in one", file=sys.stderr,
          flush=True)
  viewer.wait()  # until Ctrl-C; `interruptible` makes it exit code 130
  return 0


def _transform(args: argparse.Namespace):
  """--transform read (`lrf_jax.io.read_xf`: a rigid 4x4), None without it."""
  if args.transform is None:
    return None
  from lrf_jax.io.poses import read_xf
  try:
    return read_xf(Path(args.transform))
  except ValueError as e:
    raise ValueError(f"--transform: {e}") from None


def console() -> NoReturn:
  """`lrf-view`: `main`, then the process ends (`lrf_jax.cli.console.run`)."""
  from lrf_jax.cli.console import run
  run(main)


if __name__ == "__main__":
  exit_with(main(sys.argv[1:]))
