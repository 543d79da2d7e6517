"""What the Ray processes the project starts or documents expose, and how long they live: the
one-machine cluster recipe of docs/datasets.md, run as written (only its port changed), and the
Ray instance a `RayEngine` starts, listen on loopback only (TCP and UDP, every process of them,
sampled for 30 s); a driver's token-authenticated job on the recipe's cluster runs; the engine's
instance ends with the driver, also a SIGKILLed one; an address where no cluster answers is
refused before any item is computed.

Every Ray process here runs under a temporary HOME (no ~/.ray of the user is read or written)
and RAY_TMPDIR (no session of the user's /tmp/ray), with RAY_ADDRESS unset, and is killed at the
end: the recipe's processes by their session id, the engine's by the pids recorded while they
ran (never `ray stop`, which would stop every Ray instance of the machine)."""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import textwrap
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

pytest.importorskip("ray")
psutil = pytest.importorskip("psutil")

from lrf_jax.batch import engines  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs" / "datasets.md"
WATCH_S = 30.0  # how long the listeners are sampled
GONE_S = 30.0  # how long a dead driver's instance may take to end
pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="process sessions and /proc: Linux")


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("127.0.0.1", 0))
    return s.getsockname()[1]


def _is_loopback(ip: str) -> bool:
  addr = ipaddress.ip_address(ip.split("%")[0])
  if isinstance(addr, ipaddress.IPv6Address) and addr.ipv4_mapped is not None:
    addr = addr.ipv4_mapped  # ::ffff:127.0.0.1: a dual-stack socket bound to 127.0.0.1
  return addr.is_loopback


def _alive(p: psutil.Process) -> bool:
  try:
    return p.is_running() and p.status() != psutil.STATUS_ZOMBIE
  except psutil.Error:
    return False


def _session(sid: int) -> list[psutil.Process]:
  """Every live process of the session `sid` (a process started with start_new_session and
  all it started, daemons included: they keep the session when their parent exits)."""
  out = []
  for p in psutil.process_iter():
    try:
      if os.getsid(p.pid) == sid and _alive(p):
        out.append(p)
    except (OSError, psutil.Error):
      pass
  return out


def _tree(pid: int) -> list[psutil.Process]:
  try:
    root = psutil.Process(pid)
    return [root] + root.children(recursive=True)
  except psutil.Error:
    return []


def _listeners(procs: Iterable[psutil.Process]) -> set[tuple[int, str, str, str, int]]:
  """(pid, name, TCP/UDP, local ip, port) of every listening TCP socket and bound UDP socket."""
  out = set()
  for p in procs:
    try:
      name = p.name()
      for c in p.net_connections(kind="inet"):
        tcp = c.type == socket.SOCK_STREAM
        if (tcp and c.status == psutil.CONN_LISTEN) or (not tcp and c.laddr):
          out.add((p.pid, name, "TCP" if tcp else "UDP", c.laddr.ip, c.laddr.port))
    except psutil.Error:
      pass
  return out


def _watch(groups, seconds: float = WATCH_S, also=None) -> set[tuple[int, str, str, str, int]]:
  """The listeners of the processes `groups()` returns, sampled every 0.5 s for `seconds`;
  `also(elapsed)` is called at each sample."""
  seen: set[tuple[int, str, str, str, int]] = set()
  t0 = time.monotonic()
  while (elapsed := time.monotonic() - t0) < seconds:
    seen |= _listeners(groups())
    if also is not None:
      also(elapsed)
    time.sleep(0.5)
  return seen


def _kill(procs: Iterable[psutil.Process]) -> None:
  procs = [p for p in procs if _alive(p)]
  for p in procs:
    try:
      p.kill()
    except psutil.Error:
      pass
  psutil.wait_procs(procs, timeout=10)


@contextmanager
def _isolated_env() -> Iterator[dict[str, str]]:
  """An environment for Ray processes: a temporary HOME and RAY_TMPDIR (short: Ray's socket
  paths live there), no RAY_ADDRESS, no authentication settings of this process."""
  root = tempfile.mkdtemp(prefix="lrf-ray-", dir="/tmp")
  try:
    env = {k: v for k, v in os.environ.items()
           if k not in ("RAY_ADDRESS", "RAY_AUTH_MODE", "RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH")}
    (Path(root) / "home").mkdir()
    (Path(root) / "t").mkdir()
    env.update(HOME=f"{root}/home", RAY_TMPDIR=f"{root}/t", PYTHONPATH=str(REPO),
               RAY_USAGE_STATS_ENABLED="0")
    yield env
  finally:
    shutil.rmtree(root, ignore_errors=True)


def _docs_commands() -> tuple[str, str]:
  """The one-machine recipe of docs/datasets.md: the `ray start --head` line of its fenced
  blocks (one), and the driver's `--address 127.0.0.1:PORT` line of the same block."""
  blocks = re.findall(r"^```bash\n(.*?)^```", DOCS.read_text(), flags=re.S | re.M)
  recipe = [b.splitlines() for b in blocks if "ray start --head" in b]
  assert len(recipe) == 1, recipe
  start = [ln for ln in recipe[0] if "ray start --head" in ln]
  driver = [ln for ln in recipe[0] if re.search(r"--address 127\.0\.0\.1:\d+", ln)]
  assert len(start) == 1 and len(driver) == 1, recipe[0]
  return start[0], driver[0]


def _env_prefix(line: str) -> dict[str, str]:
  """The NAME=VALUE assignments a command line starts with."""
  out = {}
  for word in line.split():
    m = re.fullmatch(r"([A-Z_][A-Z0-9_]*)=(\S*)", word)
    if not m:
      break
    out[m.group(1)] = m.group(2)
  return out


DRIVER = textwrap.dedent("""
  import sys
  from lrf_jax.batch import engines
  eng = engines.make_engine("ray", sys.argv[1])
  try:
    print(sorted(o.value for o in eng.run(abs, [-1, -2, -3])), flush=True)
  finally:
    eng.close()
""")


@pytest.mark.slow  # 30 s of sampling, a cluster's start and a driver's
def test_the_docs_cluster_recipe_listens_on_loopback_only_and_takes_a_token_driver():
  """docs/datasets.md's `ray start --head` line, run as written but for a free port: every
  process of it (GCS, raylet, agents, dashboard, monitors, the workers of a job) and the
  driver's listen on 127.0.0.1 only; the driver, run with the environment the docs' driver
  line sets, connects to the token-authenticated cluster and gets its results."""
  start, driver_line = _docs_commands()
  port = _free_port()
  line, n = re.subn(r"--port \d+", f"--port {port}", start)
  assert n == 1, start
  address = re.search(r"--address (127\.0\.0\.1:\d+)", driver_line).group(1)
  address = address.rsplit(":", 1)[0] + f":{port}"
  with _isolated_env() as env:
    head = subprocess.Popen(["bash", "-c", line], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    driver: list[subprocess.Popen[str]] = []
    try:
      out, _ = head.communicate(timeout=120)  # `ray start` returns once the cluster is up
      assert head.returncode == 0, out

      def run_driver(elapsed):
        if not driver:
          driver.append(subprocess.Popen(
              [sys.executable, "-c", DRIVER, address], env={**env, **_env_prefix(driver_line)},
              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))

      seen = _watch(lambda: _session(head.pid) + [q for d in driver for q in _tree(d.pid)],
                    also=run_driver)
      result, _ = driver[0].communicate(timeout=120)
    finally:
      _kill([q for d in driver for q in _tree(d.pid)] + _session(head.pid))
    assert _session(head.pid) == []
  outside = sorted(x for x in seen if not _is_loopback(x[3]))
  assert outside == [], f"listening beyond loopback: {outside}"
  assert any(x[1] == "gcs_server" and x[4] == port for x in seen), sorted(seen)
  assert "Local node IP: 127.0.0.1" in out, out
  assert driver[0].returncode == 0 and "[1, 2, 3]" in result, result


ENGINE_DRIVER = textwrap.dedent("""
  import json, sys
  import psutil
  from lrf_jax.batch import engines

  def tree():
    return [p.pid for p in psutil.Process().children(recursive=True)]

  first = engines.RayEngine()
  assert sorted(o.value for o in first.run(abs, [-1, -2])) == [1, 2]
  first_pids = tree()
  first.close()
  print(json.dumps({"closed": first_pids}), flush=True)
  second = engines.RayEngine()
  assert sorted(o.value for o in second.run(abs, [-3, -4])) == [3, 4]
  print(json.dumps({"running": tree()}), flush=True)
  sys.stdin.read()  # until the test kills this process
""")


def _gone(pids: dict[int, float], seconds: float) -> list[tuple[int, str]]:
  """The processes of `pids` (pid: create time) still alive after waiting up to `seconds`."""
  t0 = time.monotonic()
  while True:
    left = []
    for pid, created in pids.items():
      try:
        p = psutil.Process(pid)
        if p.create_time() == created and _alive(p):
          left.append((pid, p.name()))
      except psutil.Error:
        pass
    if not left or time.monotonic() - t0 > seconds:
      return left
    time.sleep(0.25)


def _processes(pids: dict[int, float]) -> list[psutil.Process]:
  """The processes of `pids` (pid: create time) still running."""
  out = []
  for pid, created in pids.items():
    try:
      p = psutil.Process(pid)
      if p.create_time() == created:
        out.append(p)
    except psutil.Error:
      pass
  return out


def _created(pids: Iterable[int]) -> dict[int, float]:
  out = {}
  for pid in pids:
    try:
      out[pid] = psutil.Process(pid).create_time()
    except psutil.Error:
      pass
  return out


@pytest.mark.slow  # two Ray starts, 30 s of sampling, the wait for the killed driver's instance
def test_the_engines_own_instance_is_loopback_only_and_ends_with_its_driver():
  """A driver process makes `RayEngine()` (its own Ray instance) and runs tasks: `close` leaves
  no process of the instance; a second instance's processes (driver, GCS, raylet, agents,
  workers) listen on 127.0.0.1 only for 30 s; then the driver is SIGKILLed and within 30 s no
  process it had started is left."""
  with _isolated_env() as env:
    env["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "1"  # a user's setting the engine must override
    proc = subprocess.Popen([sys.executable, "-c", ENGINE_DRIVER], env=env, text=True,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, start_new_session=True)
    started: dict[int, float] = {}
    try:
      closed = json.loads(proc.stdout.readline())["closed"]
      left = _gone(_created(closed), 10)
      assert closed and left == [], f"left by close(): {left}"
      running = json.loads(proc.stdout.readline())["running"]
      started.update(_created(running))

      def record(_):
        started.update(_created(q.pid for q in _tree(proc.pid)[1:]))

      seen = _watch(lambda: _tree(proc.pid), also=record)
      assert len(started) >= 5, started  # GCS, raylet, agents, workers, the watchdog
      proc.send_signal(signal.SIGKILL)
      proc.wait(timeout=10)
      left = _gone(started, GONE_S)
    finally:
      _kill(_processes(started) + _tree(proc.pid) + _session(proc.pid))
      proc.wait(timeout=10)
    home = os.listdir(Path(env["HOME"]))
  assert left == [], f"alive {GONE_S} s after the driver was killed: {left}"
  outside = sorted(x for x in seen if not _is_loopback(x[3]))
  assert outside == [], f"listening beyond loopback: {outside}"
  assert any(x[1] == "gcs_server" for x in seen), sorted(seen)
  assert home == [], "the instance wrote to HOME (Ray's ~/.ray/auth_token)"


BAD_ADDRESSES = ["127.0.0.1:{port}", "no-such-host.invalid:6379"]  # nothing listens; no such name


@pytest.mark.parametrize("address", BAD_ADDRESSES)
def test_an_address_where_no_cluster_answers_is_refused_within_seconds(address, monkeypatch):
  """Nothing listening, or a name that does not resolve: `RayEngine.check` (the probe alone)
  and the engine's first use refuse the address within seconds, naming it; from RAY_ADDRESS,
  naming that."""
  monkeypatch.delenv("RAY_ADDRESS", raising=False)
  address = address.format(port=_free_port())
  for use in (lambda e: e.check(), lambda e: e.driver_node()):
    t = time.perf_counter()
    with pytest.raises(ValueError, match=f"^address: no Ray cluster answers at "
                                         f"{re.escape(address)} "):
      use(engines.make_engine("ray", address))
    assert time.perf_counter() - t < 10
  monkeypatch.setenv("RAY_ADDRESS", address)
  with pytest.raises(ValueError, match=r"^\$RAY_ADDRESS: no Ray cluster answers"):
    engines.make_engine("ray").check()


@pytest.mark.parametrize("address", BAD_ADDRESSES)
def test_a_job_on_an_address_where_no_cluster_answers_computes_no_item(
    address, tmp_path, monkeypatch):
  """A job with items to do, on an address where no cluster answers, is refused before any item
  is computed."""
  from lrf_jax import batch
  from tests.test_batch import OPTS, make_scans, pairs_tsv
  monkeypatch.delenv("RAY_ADDRESS", raising=False)
  address = address.format(port=_free_port())
  computed = []
  real_run = engines.LocalEngine.run

  def spy(self, fn, payloads):
    computed.extend(payloads)
    return real_run(self, fn, payloads)

  monkeypatch.setattr(engines.LocalEngine, "run", spy)
  tsv = pairs_tsv(tmp_path / "scans", make_scans(tmp_path / "scans", 2))
  with pytest.raises(ValueError, match=re.escape(address)):
    batch.run_register(tsv, tmp_path / "out", engine="ray", address=address, progress=False,
                       **OPTS)
  assert computed == []
