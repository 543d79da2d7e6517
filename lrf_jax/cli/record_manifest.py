"""Record the manifest of `lrf_jax.cli.parallel_compile`: the kernels each program's default
call needs, with their argument types, in the order it first calls them.

    python -m lrf_jax.cli.record_manifest    # rewrites lrf_jax/cli/compile_manifest.json

`tests/test_parallel_compile.py` fails when the shipped manifest differs from a new recording.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from lrf_jax.cli.parallel_compile import ENV_VAR, MANIFEST, PACKAGE, PROGRAMS


def demo_files(folder: Path) -> tuple[str, str]:
  """Two scans as PLY files, as a user's files reach a command."""
  from lrf_jax import datasets, io
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  a, b = folder / "a.ply", folder / "b.ply"
  io.write_ply(a, pair.model_points)
  io.write_ply(b, pair.scene_points)
  return str(a), str(b)


def _program_call(program: str, a: str, b: str, folder: Path) -> None:
  import io as std_io
  from contextlib import redirect_stderr, redirect_stdout
  with redirect_stdout(std_io.StringIO()), redirect_stderr(std_io.StringIO()):
    if program == "register":
      from lrf_jax.cli.register import main as register_main
      register_main([a, b])
    else:
      from lrf_jax.cli.frames import main as frames_main
      frames_main([a, "--out", str(folder / "frames.npz")])


def record_one(program: str) -> list[list[Any]]:
  """Run `program`'s default call on a demo pair in this process and list the lrf_jax kernels
  it calls first-hand (not those compiled inside another), with their argument types, in the
  order of the calls. Run it in a fresh process: a kernel this process called already is not
  seen again. Works on a warm cache too (a load is a call)."""
  from numba.core import sigutils
  from numba.core.dispatcher import Dispatcher
  original = Dispatcher.compile
  depth = [0]
  calls: list[list[Any]] = []

  def compile_and_note(self: Any, sig: Any) -> Any:
    func = self.py_func
    if depth[0] == 0 and func.__module__.startswith("lrf_jax"):
      args, _ = sigutils.normalize_signature(sig)
      entry = [func.__module__, func.__qualname__, [repr(t) for t in args]]
      if entry not in calls:
        calls.append(entry)
    depth[0] += 1
    try:
      return original(self, sig)
    finally:
      depth[0] -= 1

  Dispatcher.compile = compile_and_note  # type: ignore[method-assign]
  try:
    with tempfile.TemporaryDirectory() as tmp:
      a, b = demo_files(Path(tmp))
      _program_call(program, a, b, Path(tmp))
  finally:
    Dispatcher.compile = original  # type: ignore[method-assign]
  return calls


def record(programs: tuple[str, ...] = PROGRAMS) -> dict[str, list[list[Any]]]:
  """`record_one` of each program, each in a fresh process (`LRF_JAX_PARALLEL_COMPILE=0`)."""
  env = {**os.environ, ENV_VAR: "0", "PYTHONPATH": os.pathsep.join(
      [str(PACKAGE.parent), *filter(None, [os.environ.get("PYTHONPATH")])])}
  out = {}
  for program in programs:
    text = subprocess.run([sys.executable, "-m", "lrf_jax.cli.record_manifest", "--record-one",
                           program], env=env, capture_output=True, text=True, check=True).stdout
    out[program] = json.loads(text.strip().splitlines()[-1])
  return out


def main(argv: list[str] | None = None) -> int:
  argv = sys.argv[1:] if argv is None else argv
  if argv[:1] == ["--record-one"] and len(argv) == 2:
    print(json.dumps(record_one(argv[1])))
    return 0
  if argv:
    print("usage: python -m lrf_jax.cli.record_manifest", file=sys.stderr)
    return 2
  MANIFEST.write_text(json.dumps(record(), indent=1) + "\n")
  print(f"wrote {MANIFEST}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
