"""The first run of a new user: a fresh clone, a fresh venv, empty caches, fresh processes.

    LRF_DATA=/path/to/data python benchmarks/bench_first_run.py [--venv PATH] [--worktree]

For each program below a fresh clone of this repository (`git clone`; `--worktree` copies the
working tree instead, uncommitted changes included) and an empty HOME and XDG_CACHE_HOME (no JAX
or numba cache, no `*.nbi` in the tree), then the program twice as fresh processes (the second
run loads what the first compiled):

* `python -c "import lrf_jax"` (the import alone);
* `lrf-register bun000.ply bun045.ply` (the Stanford bunny scans under `$LRF_DATA`);
* a script that imports lrf_jax and calls `compute_frames` on bun000 at 1,000 keypoints;
* `python evaluate.py --datasets bunny --max-pairs 1 --methods lrf_net_plus`;
* Open3D's FPFH + RANSAC + ICP script of `bench_cli.py`, as a fresh process, in the same run.

The venv is made with the README's install command (`python3 -m venv .venv && pip install -e .`,
timed: the install is part of the first run), in the first clone; the other clones run with
that venv and `PYTHONPATH` set to themselves. `--venv PATH` reuses an existing venv instead (no
install, nothing downloaded: runnable offline). Open3D runs under `--open3d-python` (default:
this interpreter). Each row gives the wall time, the peak memory of the process and the load
average when it started; the CPU is named from lscpu.
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))
from bench_cli import OPEN3D_SCRIPT  # noqa: E402

NOTICE = "lrf_jax: compiling kernels"
IMPORT_CODE = ("import time; t = time.perf_counter(); import lrf_jax; "
               "print(f'import {time.perf_counter() - t:.3f} s')")
FRAMES_CODE = """
import sys, time
t0 = time.perf_counter()
import numpy as np, lrf_jax
from lrf_jax import io  # noqa: E402
path = sys.argv[1]
n = len(io.read_cloud(path).points)
keypoints = np.random.default_rng(0).choice(n, 1000, replace=False)
t1 = time.perf_counter()
frames, valid = lrf_jax.compute_frames(path, keypoints, radius_mr=15)
frames = np.asarray(frames)
print(f"call {time.perf_counter() - t1:.2f} s, total {time.perf_counter() - t0:.2f} s")
"""
SKIP = {".git", ".venv", "__pycache__", "out", ".pytest_cache"}


def cpu_name() -> str:
  """The CPU's model name (lscpu, else /proc/cpuinfo, else platform) and the core count."""
  name = ""
  try:
    out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    name = next((line.split(":", 1)[1].strip() for line in out.splitlines()
                 if line.startswith("Model name")), "")
  except OSError:
    pass
  if not name and Path("/proc/cpuinfo").exists():
    name = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text()
                 .splitlines() if line.startswith("model name")), "")
  return f"{name or platform.processor() or 'unknown CPU'}, {os.cpu_count()} cores"


def load() -> str:
  """The 1-minute load average, as text."""
  try:
    return f"{os.getloadavg()[0]:.2f}"
  except OSError:
    return "?"


def timed(cmd: list[str], env: dict[str, str], cwd: Path) -> dict:
  """Run `cmd` as a fresh process: wall seconds, its peak RSS (MB), rc, whether the compile
  notice appeared on stderr, the last line of stdout, the load average at the start."""
  start_load = load()
  with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, cwd=cwd, stdout=out, stderr=err, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    out.seek(0)
    err.seek(0)
    stdout, stderr = out.read(), err.read()
  lines = [s for s in stdout.splitlines() if s.strip()]
  return {"seconds": seconds, "rc": proc.returncode, "notice": NOTICE in stderr,
          "load": start_load, "peak_mb": usage.ru_maxrss / 1024, "last": lines[-1] if lines else "",
          "stderr": stderr[-2000:]}


def copy_tree(src: Path, dst: Path, worktree: bool) -> None:
  """A fresh clone of `src` in `dst` (committed code), or with `worktree` a copy of its files
  (uncommitted changes included) without caches, venvs or compiled kernels."""
  if not worktree:
    subprocess.run(["git", "clone", "-q", str(src), str(dst)], check=True)
    return

  def keep(info: tarfile.TarInfo) -> tarfile.TarInfo | None:
    parts = Path(info.name).parts
    if any(p in SKIP for p in parts) or info.name.endswith((".nbi", ".nbc", ".pyc")):
      return None
    if info.issym() and os.path.isabs(info.linkname):  # a local link (a build folder): not code
      return None
    return info

  dst.mkdir(parents=True)
  archive = dst.parent / (dst.name + ".tar")
  with tarfile.open(archive, "w") as tar:
    tar.add(src, arcname=".", filter=keep)
  with tarfile.open(archive) as tar:
    tar.extractall(dst, filter="data")
  archive.unlink()


def make_venv(tree: Path) -> tuple[Path, float]:
  """The README's install command in `tree`; returns the venv's python and the seconds taken."""
  t0 = time.perf_counter()
  subprocess.run(f"{shutil.which('python3') or sys.executable} -m venv .venv && "
                 ". .venv/bin/activate && pip install -q -e .", shell=True, cwd=tree, check=True)
  return tree / ".venv" / "bin" / "python", time.perf_counter() - t0


def fresh_env(root: Path, tree: Path, pythonpath: bool) -> dict[str, str]:
  """The environment of a new user: empty HOME and XDG cache, no numba / JAX cache settings."""
  home = root / "home"
  home.mkdir(parents=True, exist_ok=True)
  env = {k: v for k, v in os.environ.items()
         if not k.startswith(("NUMBA_", "LRF_JAX_", "JAX_", "XLA_")) and k != "PYTHONPATH"}
  env.update(HOME=str(home), XDG_CACHE_HOME=str(home / ".cache"))
  if pythonpath:
    env["PYTHONPATH"] = str(tree)
  return env


def scenarios(python: Path, scans: Path, out: Path) -> dict[str, list[str]]:
  """The programs, as command lines run in a clone."""
  bindir = python.parent
  src, tgt = str(scans / "bun000.ply"), str(scans / "bun045.ply")
  return {
      "import lrf_jax": [str(python), "-c", IMPORT_CODE],
      "lrf-register bun000 bun045": [str(bindir / "lrf-register"), src, tgt, "--out",
                                     str(out / "T.txt")],
      "compute_frames, bun000, 1,000 keypoints": [str(python), "-c", FRAMES_CODE, src],
      "evaluate.py bunny, 1 pair, lrf_net_plus": [
          str(python), "evaluate.py", "--datasets", "bunny", "--max-pairs", "1", "--methods",
          "lrf_net_plus", "--out", str(out / "eval")],
  }


def main() -> int:
  ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  ap.add_argument("--data", default=os.environ.get("LRF_DATA"))
  ap.add_argument("--venv", type=Path, help="reuse this venv (no install; offline)")
  ap.add_argument("--worktree", action="store_true",
                  help="copy the working tree (uncommitted changes included) instead of cloning")
  ap.add_argument("--open3d-python", default=sys.executable)
  ap.add_argument("--only", nargs="+", help="run only the programs whose label starts so")
  ap.add_argument("--keep", action="store_true", help="keep the temporary folder")
  args = ap.parse_args()
  if not args.data:
    print("set LRF_DATA (or --data) to the folder holding stanford_bunny_scans/", file=sys.stderr)
    return 2
  scans = Path(args.data) / "stanford_bunny_scans"
  tmp = Path(tempfile.mkdtemp(prefix="lrf_first_run_"))
  rows, install = [], None
  try:
    python = args.venv / "bin" / "python" if args.venv else None
    labels = list(scenarios(Path("python"), scans, tmp))
    if args.only:
      labels = [lb for lb in labels if any(lb.startswith(o) for o in args.only)]
    for i, label in enumerate(labels):
      root = tmp / f"s{i}"
      tree = root / "repo"
      copy_tree(REPO, tree, args.worktree)
      if python is None:
        python, seconds = make_venv(tree)
        install = (seconds, load())
      cmd = scenarios(python, scans, root)[label]
      env = fresh_env(root, tree, pythonpath=args.venv is not None or i > 0)
      rows.append((label, [timed(cmd, env, tree) for _ in range(2)]))
    script = tmp / "o3d_register.py"
    script.write_text(OPEN3D_SCRIPT)
    o3d_env = fresh_env(tmp / "o3d", tmp, pythonpath=False)
    cmd = [args.open3d_python, str(script), str(scans / "bun000.ply"), str(scans / "bun045.ply"),
           str(tmp / "o3d.txt")]
    runs = [timed(cmd, o3d_env, tmp) for _ in range(2)]
    rows.append(("Open3D script (FPFH + RANSAC + ICP)", runs))
  finally:
    if not args.keep:
      shutil.rmtree(tmp, ignore_errors=True)
  print_table(rows, install, args)
  return 0


def print_table(rows: list, install: tuple[float, str] | None, args: argparse.Namespace) -> None:
  """The markdown table of the runs."""
  print(f"# The first run: fresh {'copy of the working tree' if args.worktree else 'clone'}, "
        "empty HOME and XDG cache, fresh processes")
  print(f"\nCPU: {cpu_name()}; Python {platform.python_version()}")
  print("install: " + (f"{install[0]:.1f} s (`pip install -e .` in a fresh venv, load "
                       f"{install[1]})" if install else f"skipped (--venv {args.venv})"))
  print("\n| program | first run s | peak MB | load | compile note | second run s | load | "
        "compile note | output |")
  print("|---|---:|---:|---:|---|---:|---:|---|---|")
  for label, (a, b) in rows:
    bad = "" if a["rc"] in (0, 3) and b["rc"] in (0, 3) else f" (rc {a['rc']}/{b['rc']})"
    print(f"| {label}{bad} | {a['seconds']:.1f} | {a['peak_mb']:.0f} | {a['load']} | "
          f"{'yes' if a['notice'] else 'no'} | {b['seconds']:.1f} | {b['load']} | "
          f"{'yes' if b['notice'] else 'no'} | {b['last'][:60]} |")
  for label, (a, b) in rows:
    for r in (a, b):
      if r["rc"] not in (0, 3):
        print(f"\n{label} rc {r['rc']}: {r['stderr']}", file=sys.stderr)


if __name__ == "__main__":
  sys.exit(main())
