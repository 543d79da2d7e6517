"""`lrf-compile` (`python -m lrf_jax.cli.compile`): compile every kernel for this machine, in
parallel, into the on-disk caches, so that no later run waits for a compile (a Docker image
layer, a CI cache, a cluster's shared cache before a data-set job).

numba compiles one kernel after another within a process (its compiler lock is per process), so the
kernels are compiled by `--jobs` worker processes at once, each running a group of small calls that
needs its own kernels (a registration with the default options, with each other estimator and
option, the frames of each method, each descriptor, a multiway run, and the kernels of
`lrf-register`'s and `lrf-frames`' default calls by signature, which marks those programs warm:
their first run then starts no compile worker, `parallel_compile`). They write into the same caches
(`lrf_jax.compilation_cache`; each save of a kernel is locked by `lrf_jax.kernel_cache`, so
concurrent writers never mix two entries up). Nothing is compiled that a later run would not load:
the calls are the library's own, on small procedural clouds. Exit code 0, 3 when a group failed (its
error is printed: the others are compiled), 2 a bad command line, 130 interrupted. The workers end
with the command, Ctrl-C and a SIGKILL of the command included (`parallel_compile.spawn_context`).

    lrf-compile               # every group, one worker per core
    lrf-compile --jobs 1 --only register frames:lrf_net_plus
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
from collections.abc import Callable

from lrf_jax.cli.help import DefaultsHelpFormatter
from lrf_jax.cli import parallel_compile
from lrf_jax.cli.parallel_compile import PROGRAMS
from lrf_jax.defaults import RADIUS_MR


def _demo_pair():
  from lrf_jax import datasets
  pair = datasets.make_demo_pair(0, seed=0, noise_mr=0.1, partial=True)
  return pair.model_points, pair.scene_points


def _register(**options) -> Callable[[], None]:
  def run() -> None:
    from lrf_jax.registration import register
    a, b = _demo_pair()
    register(a, b, n_keypoints=500, n_correspondences=200, **options)
  return run


def _frames(method: str) -> Callable[[], None]:
  def run() -> None:
    import numpy as np

    from lrf_jax import datasets
    from lrf_jax.frames import METHODS
    from lrf_jax.frames.compute import compute_frames
    points, faces = datasets.make_demo_mesh("blob", seed=0)
    spec = METHODS[method]
    compute_frames(points, np.arange(0, len(points), 10), radius_mr=RADIUS_MR,
                           method=method, faces=faces if spec.needs_mesh else None)
  return run


def _descriptor(name: str) -> Callable[[], None]:
  def run() -> None:
    import numpy as np

    from lrf_jax import datasets
    from lrf_jax.descriptors import compute_descriptors
    from lrf_jax.frames.compute import compute_frames, mesh_resolution
    points, faces = datasets.make_demo_mesh("blob", seed=0)
    kp = np.arange(0, len(points), 10)
    radius = RADIUS_MR * mesh_resolution(points, faces)
    frames = compute_frames(points, kp, radius)
    compute_descriptors(points, kp, radius, frames[0], frames[1], name, faces=faces)
  return run


def _multiway() -> None:
  from lrf_jax import datasets
  from lrf_jax.multiway import register_all
  scans = [datasets.make_demo_pair(0, seed=s, noise_mr=0.1, partial=True).scene_points
           for s in range(3)]
  register_all(scans, progress=False)


def groups() -> dict[str, Callable[[], None]]:
  """Every group of calls by name: "register", "register:<option>", "frames:<method>",
  "descriptor:<name>", "multiway", and "program:<name>" (the kernels of `lrf-register`'s and
  `lrf-frames`' default calls, by signature: `parallel_compile`)."""
  from lrf_jax.descriptors import DESCRIPTORS
  from lrf_jax.frames import METHODS
  out: dict[str, Callable[[], None]] = {"register": _register()}
  for name, opts in (("lrf", dict(estimator="lrf")), ("3point", dict(estimator="3point")),
                     ("iss", dict(keypoints="iss")), ("mutual", dict(mutual=True, ratio=0.9)),
                     ("point_to_point", dict(icp_mode="point_to_point"))):
    out[f"register:{name}"] = _register(**opts)
  out.update({f"frames:{m}": _frames(m) for m in sorted(METHODS)})
  out.update({f"descriptor:{d}": _descriptor(d) for d in sorted(DESCRIPTORS)})
  out["multiway"] = _multiway
  out.update({f"program:{p}": functools.partial(_program, p) for p in PROGRAMS})
  return out


def _program(program: str) -> None:
  """A program's kernels by the signatures its first run compiles
  (`parallel_compile.compile_program`); marks them warm, so its next first run starts no
  compile worker."""
  parallel_compile.compile_program(program)


def _run_group(name: str) -> tuple[str, float, str | None]:
  """In a worker: run one group; (name, seconds, error or None)."""
  import warnings

  from lrf_jax import compilation_cache
  compilation_cache.enable()  # JAX's persistent cache too, for the calls that use JAX
  t0 = time.perf_counter()
  try:
    with warnings.catch_warnings():
      warnings.simplefilter("ignore")
      groups()[name]()
  except Exception as e:  # noqa: BLE001 -- reported, the other groups go on
    return name, time.perf_counter() - t0, f"{type(e).__name__}: {e}"
  return name, time.perf_counter() - t0, None


def _unwritable_cache() -> str | None:
  """Why the caches cannot take the compiled code (a read-only or missing folder), or None.
  Without this, a compile into a read-only cache "succeeded" (numba only warns, and the groups
  run with warnings off) and the next run compiled everything again."""
  import tempfile

  from lrf_jax import compilation_cache
  for what, folder in (("numba's kernels (NUMBA_CACHE_DIR)", compilation_cache.numba_cache_dir()),
                       ("JAX's programs (LRF_JAX_CACHE_DIR)", compilation_cache.cache_dir())):
    try:
      folder.mkdir(parents=True, exist_ok=True)
      with tempfile.TemporaryFile(dir=folder):
        pass
    except OSError as e:
      return (f"the cache of {what}, {folder}, is not writable ({e.strerror or e}); nothing "
              "compiled would be kept")
  return None


def _stop(pool) -> None:
  """End a pool's workers now: a Ctrl-C sent to this process only (`kill -INT`, a supervisor)
  would otherwise wait for every running group to finish (minutes)."""
  processes = list((getattr(pool, "_processes", None) or {}).values())  # no public handle
  pool.shutdown(wait=False, cancel_futures=True)
  for proc in processes:
    proc.terminate()
  for proc in processes:
    proc.join(timeout=10)


def build_parser() -> argparse.ArgumentParser:
  ap = argparse.ArgumentParser(prog="lrf-compile", description="Compile every lrf_jax kernel for "
                               "this machine into the on-disk caches, in parallel.",
                               formatter_class=DefaultsHelpFormatter)
  ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1,
                  help="worker processes (default: one per core)")
  ap.add_argument("--only", nargs="+", default=None, metavar="GROUP",
                  help="only these groups (--list shows them)")
  ap.add_argument("--list", action="store_true", help="list the groups and exit")
  return ap


def main(argv: list[str] | None = None) -> int:
  """Run lrf-compile; returns the exit code (0 all compiled, 3 a group failed, 2 usage, 130
  interrupted)."""
  args = build_parser().parse_args(argv)
  names = list(groups())
  if args.list:
    print("\n".join(names))
    return 0
  if args.only:
    unknown = sorted(set(args.only) - set(names))
    if unknown:
      print(f"error: --only: unknown group(s) {unknown}; lrf-compile --list shows them",
            file=sys.stderr)
      return 2
    names = [n for n in names if n in args.only]
  if args.jobs < 1:
    print(f"error: --jobs: expected a positive integer, got {args.jobs}", file=sys.stderr)
    return 2
  problem = _unwritable_cache()
  if problem:
    print(f"error: {problem}", file=sys.stderr)
    return 2
  from concurrent.futures import ProcessPoolExecutor, as_completed

  from tqdm.auto import tqdm

  from lrf_jax import compilation_cache
  t0 = time.perf_counter()
  failed = 0
  seconds: dict[str, float] = {}
  # fresh interpreters (no inherited threads or JAX state) that die with this process, however
  # it ends: a SIGKILL left them compiling, then hung, orphaned (parallel_compile.spawn_context)
  ctx = parallel_compile.spawn_context()
  # A worker that compiles a JAX program starts the accelerator's runtime, which by default takes
  # 75 % of a GPU's memory: 16 workers on one GPU ran out of it. Each takes what it uses.
  os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
  pool = ProcessPoolExecutor(max_workers=min(args.jobs, len(names)), mp_context=ctx)
  try:
    with tqdm(total=len(names), desc="lrf-compile", unit="group") as bar:
      futures = [pool.submit(_run_group, n) for n in names]
      for fut in as_completed(futures):
        name, secs, error = fut.result()
        seconds[name] = secs
        bar.update(1)
        if error:
          failed += 1
          tqdm.write(f"error: {name}: {error}", file=sys.stderr)
  except KeyboardInterrupt:
    _stop(pool)
    print("interrupted: the kernels compiled so far are kept", file=sys.stderr)
    return 130
  pool.shutdown()
  slowest = sorted(seconds, key=seconds.get, reverse=True)[:5]  # type: ignore[arg-type]
  print("slowest groups: " + ", ".join(f"{n} {seconds[n]:.1f} s" for n in slowest),
        file=sys.stderr)
  print(f"compiled {len(names) - failed} of {len(names)} groups with {args.jobs} worker(s) in "
        f"{time.perf_counter() - t0:.1f} s into {compilation_cache.cache_locations()}",
        file=sys.stderr)
  return 3 if failed else 0


if __name__ == "__main__":
  sys.exit(main())
