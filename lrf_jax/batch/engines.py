"""Where a data-set job's items run: in this process (`LocalEngine`) or on a Ray cluster
(`RayEngine`), behind one small interface.

An engine maps a pure, picklable function over payloads and yields an `Outcome` per payload as
it finishes, in completion order (the job layer writes each one as it comes). A value many
payloads share (a scan's features, read by every pair it is in) is handed over once with
`put`: the handle it returns stands for the value as a top-level value of a payload dict (the
local engine returns the value itself; the Ray engine stores it once in the object store and
the worker fetches it). The function
catches the errors of a bad item itself and returns them as data; an engine only reports what
killed the work around it: a worker process or a node that died (`Outcome.error`), after Ray
has retried the task `max_retries` times on the nodes that remain.

Ray is used for what it has: tasks with `max_retries` (a task on a dead worker or node is run
again elsewhere), `num_cpus` resources (a worker uses the CPUs its task was given: the
environment variable `LRF_JAX_NUM_THREADS` is set to them for every worker), `ray.wait` for
completion order and `ray.cancel` on Ctrl-C. Worker processes are reused across tasks, so the
compiled kernels a worker has loaded stay loaded.

Loopback: `address="local"` starts a Ray instance of this machine bound to 127.0.0.1 (every
process of it: GCS, raylet, agents, workers), never joining a cluster found on the machine, and
a driver joining a cluster at a loopback address stays on loopback (Ray 2.5x-2.6x otherwise
resolves "127.0.0.1" to the machine's interface address before connecting; the driver
switches that resolution off with Ray's `RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`, set only in this
process). The instance "local" starts authenticates with a token of its own (Ray's token
authentication; `RAY_AUTH_TOKEN` set while it lives, unless the user chose the token or
`RAY_AUTH_MODE=disabled`), so that no other user of the machine can run tasks on it, and
nothing is written to `~/.ray/auth_token` (`ray.init` would write one there, which a later
`ray start --head` of the user would take as a request for token authentication).

Lifetime: the instance `address="local"` starts ends with `close` or with the driver, also when
the driver is killed. Ray's kernel fate-sharing kills the processes the driver started itself
(GCS, raylet, monitors) when it dies, and the workers follow the raylet; the raylet's agents,
though, wait up to a minute on the dead GCS before they exit. A watchdog process (Linux) holds
the read end of a pipe from the driver and keeps the instance's processes: those started with
this instance's mark in their environment (`LRF_JAX_RAY_INSTANCE`, set while `ray.init` starts
the instance; the raylet passes it on to its workers) and their descendants (the agents). When
the driver closes the pipe or dies, it kills them.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import os
import secrets
import subprocess
import sys
from typing import Any, Protocol
from collections.abc import Callable, Iterator, Sequence

__all__ = ["ENGINES", "LocalEngine", "Outcome", "RayEngine", "address_problem", "make_engine",
           "resolve_address"]

ENGINES = ("local", "ray")
# Ray's retries of a task whose worker or node died (not of an item's own error).
MAX_RETRIES = 3
_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
# Ray's token authentication: the mode, and the token itself (before ~/.ray/auth_token).
_AUTH_ENV = ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN")
# Marks every process of a Ray instance an engine starts (its value: a random token).
_INSTANCE_ENV = "LRF_JAX_RAY_INSTANCE"
# The watchdog of such an instance: argv[1] the mark ("LRF_JAX_RAY_INSTANCE=<token>"), argv[2] the
# driver's pid (never killed). Until its stdin ends (the driver closed it, or died) it keeps, once
# a second, the instance's processes: those whose environment holds the mark (what `ray.init`
# starts, and the workers), and every descendant of one (the raylet's agents, whose title
# overwrites their environment), each with its start time (a reused pid is another process).
# Then it kills them all, scanning again until none is left. Standard library only; Linux.
_WATCHDOG = r"""
import os, select, signal, sys, time
for sig in (signal.SIGINT, signal.SIGHUP, signal.SIGPIPE):
  signal.signal(sig, signal.SIG_IGN)
mark = b"\0" + os.fsencode(sys.argv[1]) + b"\0"
skip = {os.getpid(), int(sys.argv[2])}
known = {}

def scan():
  procs = {}
  for name in os.listdir("/proc"):
    if name.isdigit() and int(name) not in skip:
      try:
        with open("/proc/" + name + "/stat", "rb") as f:
          stat = f.read()
      except OSError:
        continue
      fields = stat[stat.rindex(b")") + 2:].split()
      if fields[0] not in (b"Z", b"X"):
        procs[int(name)] = (int(fields[1]), fields[19])
  for pid in [p for p, start in known.items() if procs.get(p, (0, None))[1] != start]:
    del known[pid]
  for pid, (_, start) in procs.items():
    if pid not in known:
      try:
        with open("/proc/%d/environ" % pid, "rb") as f:
          if mark in b"\0" + f.read():
            known[pid] = start
      except OSError:
        pass
  grown = True
  while grown:
    grown = False
    for pid, (ppid, start) in procs.items():
      if pid not in known and ppid in known:
        known[pid] = start
        grown = True

while True:
  if select.select([0], [], [], 1.0)[0] and not os.read(0, 4096):
    break
  scan()
for _ in range(100):
  scan()
  if not known:
    break
  for pid in known:
    try:
      os.kill(pid, signal.SIGKILL)
    except OSError:
      pass
  time.sleep(0.1)
"""


@dataclasses.dataclass(frozen=True)
class Outcome:
  """One finished payload.

  Attributes:
    index: the payload's position in the list given to `run`.
    value: what the function returned (None when `error` is set).
    error: why the work around the item died (a lost worker or node, after Ray's retries), or
      None.
    node: where it ran: "local", or the Ray node id.
    attempt: 1 for a first try; Ray's retries count up.
    version: the lrf_jax version of the process that ran it.
  """
  index: int
  value: Any
  error: str | None
  node: str
  attempt: int
  version: str


class Engine(Protocol):
  name: str

  def run(self, fn: Callable[[Any], Any], payloads: Sequence[Any]) -> Iterator[Outcome]: ...

  def put(self, value: Any) -> Any: ...

  def driver_node(self) -> str: ...

  def close(self) -> None: ...


def _version() -> str:
  from lrf_jax.records import version
  return version()


class LocalEngine:
  """Runs every payload in this process, one after another (the kernels use every core)."""

  name = "local"

  def run(self, fn: Callable[[Any], Any], payloads: Sequence[Any]) -> Iterator[Outcome]:
    version = _version()
    for i, payload in enumerate(payloads):
      yield Outcome(i, fn(payload), None, "local", 1, version)

  def put(self, value: Any) -> Any:
    """`value` itself (payloads of this process share it as it is)."""
    return value

  def driver_node(self) -> str:
    """Where this process runs: "local"."""
    return "local"

  def close(self) -> None:
    pass


def _on_worker(fn: Callable[[Any], Any], payload: Any, driver_version: str
               ) -> tuple[Any, str | None, str, int, str]:
  """The Ray task: (value, refusal, node id, attempt, version). A worker whose lrf_jax differs
  from the driver's refuses the item instead of computing it."""
  import ray
  node = ray.get_runtime_context().get_node_id()
  core = getattr(ray._private.worker.global_worker, "core_worker", None)  # noqa: SLF001
  attempt = 1
  if core is not None and hasattr(core, "get_current_task_attempt_number"):
    attempt = int(core.get_current_task_attempt_number()) + 1
  version = _version()
  if version != driver_version:
    return (None, f"the worker runs lrf_jax {version}, the driver {driver_version}: refused",
            node, attempt, version)
  if isinstance(payload, dict):  # the values `RayEngine.put` stored, fetched once each
    payload = {k: ray.get(v) if isinstance(v, ray.ObjectRef) else v for k, v in payload.items()}
  return fn(payload), None, node, attempt, version


def _set_env(values: dict[str, str | None]) -> None:
  """Set these environment variables of this process (None: unset)."""
  for k, v in values.items():
    if v is None:
      os.environ.pop(k, None)
    else:
      os.environ[k] = v


def is_loopback(address: str) -> bool:
  """Whether a Ray address ("local", "HOST:PORT", "ray://HOST:PORT") is on this machine's
  loopback interface."""
  if address == "local":
    return True
  host = address.split("://")[-1].rsplit(":", 1)[0].strip("[]")
  if host == "localhost":
    return True
  try:
    return ipaddress.ip_address(host).is_loopback
  except ValueError:
    return False


def resolve_address(address: str | None) -> str:
  """The Ray address a job uses: `address` when given, else `RAY_ADDRESS` when set, else
  "local" (a new Ray instance of this machine: never another cluster that happens to run
  here)."""
  if address:
    return address
  return os.environ.get("RAY_ADDRESS") or "local"


def address_problem(address: str | None, flag: str = "address") -> str | None:
  """What is wrong with a Ray cluster address (`resolve_address` of it), or None: "local" and
  "auto" are fine; HOST:PORT (or ray://HOST:PORT) must accept a TCP connection within 3 s
  (Ray itself retries an address where nothing answers for minutes). `flag` names the option
  in the message ("$RAY_ADDRESS" when the address came from there)."""
  import socket
  resolved = resolve_address(address)
  if resolved in ("local", "auto"):
    return None
  flag = flag if address else "$RAY_ADDRESS"
  host, sep, port = resolved.split("://")[-1].rpartition(":")
  if not sep or not host or not port.isdigit():
    return (f"{flag}: expected HOST:PORT of a running Ray cluster, 'local' or 'auto', got "
            f"{resolved!r}")
  try:
    socket.create_connection((host.strip("[]"), int(port)), timeout=3).close()
  except OSError as e:
    return (f"{flag}: no Ray cluster answers at {resolved} ({e.strerror or e}); start one "
            "(`ray start --head`) or use the address 'local'")
  return None


class RayEngine:
  """Runs payloads as Ray tasks of `cpus_per_task` CPUs each.

  Args:
    address: "local" (start a Ray instance of this machine, on 127.0.0.1), "HOST:PORT" of a
      running cluster, or None (`resolve_address`).
    cpus_per_task: CPUs each task reserves (and the threads its kernels use).
    max_in_flight: tasks submitted ahead of the finished ones (None: 4 per CPU of the cluster,
      at least 8), so that Ctrl-C has little to cancel and the driver holds few references.
    max_retries: Ray's retries of a task whose worker or node died.

  The cluster is joined on first use (a job with nothing to do never joins it); an address
  where no cluster answers (nothing listening, a name that does not resolve) is then a
  ValueError (`address_problem`) within seconds, as it is from `check`, which only probes the
  address. The instance "local" starts belongs to this engine: `close`, or the end of the
  driver, stops every process of it.
  """

  name = "ray"

  def __init__(self, address: str | None = None, *, cpus_per_task: int = 1,
               max_in_flight: int | None = None, max_retries: int = MAX_RETRIES):
    self.address = resolve_address(address)
    self._given = address  # for messages: None means the address came from RAY_ADDRESS
    self.cpus_per_task = int(cpus_per_task)
    self.max_in_flight = max_in_flight
    self.max_retries = int(max_retries)
    self._started = False
    self._watchdog: subprocess.Popen[bytes] | None = None
    self._auth_env: dict[str, str | None] | None = None

  def check(self) -> None:
    """Raise ValueError (`address_problem`) when no Ray cluster answers at the address. Nothing
    to check for "local", or when this process is already connected to Ray (the engine then
    uses that connection)."""
    ray = sys.modules.get("ray")
    if ray is not None and getattr(ray, "is_initialized", lambda: False)():
      return
    problem = address_problem(self.address if self._given else None)
    if problem:
      raise ValueError(problem)

  def _ray(self):
    from lrf_jax.extras import require
    require("ray", "the ray engine")
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # Ray reports nothing anywhere
    if is_loopback(self.address):
      os.environ.setdefault(_LOOPBACK_ENV, "0")
    import ray
    if is_loopback(self.address):  # also when Ray was imported before this process set it
      from ray._private import ray_constants
      ray_constants.ENABLE_RAY_CLUSTER = False
    if not ray.is_initialized():
      self.check()  # at once, not after Ray's minutes of retries
      kw: dict[str, Any] = dict(address=self.address, logging_level="warning",
                                log_to_driver=False)
      if is_loopback(self.address):
        kw["_node_ip_address"] = "127.0.0.1"
      if self.address == "local":
        self._start_instance(ray, kw)
      else:
        ray.init(**kw)
      self._started = True
    return ray

  def _start_instance(self, ray, kw: dict[str, Any]) -> None:
    """`ray.init` of a new instance of this machine (address "local": never a cluster found
    through RAY_ADDRESS or Ray's address file), on 127.0.0.1, without dashboard, each of its
    processes started with this instance's mark in its environment, and (Linux) the watchdog
    that kills them when this process closes the engine or dies."""
    kw.update(address="local", include_dashboard=False, dashboard_host="127.0.0.1")
    token = secrets.token_hex(16)
    if sys.platform.startswith("linux"):
      self._watchdog = subprocess.Popen(
          [sys.executable, "-I", "-c", _WATCHDOG, f"{_INSTANCE_ENV}={token}", str(os.getpid())],
          stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
          start_new_session=True)  # so Ctrl-C in a terminal reaches the driver only
    saved = {k: os.environ.get(k) for k in (_INSTANCE_ENV, _LOOPBACK_ENV)}
    self._auth_env = {k: os.environ.get(k) for k in _AUTH_ENV}
    os.environ[_INSTANCE_ENV] = token
    os.environ[_LOOPBACK_ENV] = "0"  # the processes it starts resolve no address elsewhere
    if (os.environ.get("RAY_AUTH_MODE", "token").lower() == "token"
        and not any(os.environ.get(k) for k in ("RAY_AUTH_TOKEN", "RAY_AUTH_TOKEN_PATH"))):
      os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    try:
      ray.init(**kw)
    except BaseException:
      self._end_instance()
      raise
    finally:
      _set_env(saved)

  def _end_instance(self) -> None:
    """Close the watchdog's pipe (it kills what is left of the instance) and wait for it; give
    back the authentication settings this process had before the instance."""
    wd, self._watchdog = self._watchdog, None
    if wd is not None:
      if wd.stdin is not None:
        wd.stdin.close()
      try:
        wd.wait(timeout=30)
      except subprocess.TimeoutExpired:
        wd.kill()
        wd.wait()
    if self._auth_env is not None:
      _set_env(self._auth_env)
      self._auth_env = None
      try:  # Ray's settings read the restored environment again, the next token anew
        from ray import _raylet as raylet
        raylet.Config.initialize("")  # type: ignore[attr-defined]
        raylet.AuthenticationTokenLoader.instance().reset_cache()  # type: ignore[attr-defined]
      except (ImportError, AttributeError):
        pass

  def run(self, fn: Callable[[Any], Any], payloads: Sequence[Any]) -> Iterator[Outcome]:
    ray = self._ray()
    version = _version()
    threads = str(self.cpus_per_task)
    task = ray.remote(_on_worker).options(
        num_cpus=self.cpus_per_task, max_retries=self.max_retries, retry_exceptions=False,
        runtime_env={"env_vars": {"LRF_JAX_NUM_THREADS": threads}})
    window = self.max_in_flight or max(8, 4 * int(ray.cluster_resources().get("CPU", 1)))
    fn_ref = ray.put(fn)
    pending: dict[Any, int] = {}
    nxt = 0
    try:
      while nxt < len(payloads) or pending:
        while nxt < len(payloads) and len(pending) < window:
          pending[task.remote(fn_ref, payloads[nxt], version)] = nxt
          nxt += 1
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
          i = pending.pop(ref)
          yield self._outcome(ray, ref, i)
    except BaseException:
      for ref in pending:
        ray.cancel(ref, force=True)
      raise

  def put(self, value: Any) -> Any:
    """A handle of `value` stored once in the cluster's object store (owned by this driver,
    kept while a payload holds it); a top-level value of a payload dict."""
    return self._ray().put(value)

  def driver_node(self) -> str:
    """The Ray node id of this process (Ray is started or joined first)."""
    return self._ray().get_runtime_context().get_node_id()

  def _outcome(self, ray, ref, i: int) -> Outcome:
    try:
      value, refusal, node, attempt, version = ray.get(ref)
    except ray.exceptions.RayTaskError as e:  # the function raised: a bug, not a lost node
      return Outcome(i, None, f"{type(e.cause).__name__}: {e.cause}", "?", 1, "?")
    except ray.exceptions.RayError as e:  # worker or node lost beyond the retries
      return Outcome(i, None, f"lost after {self.max_retries + 1} attempts: "
                              f"{type(e).__name__}", "?", self.max_retries + 1, "?")
    return Outcome(i, value, refusal, node, attempt, version)

  def close(self) -> None:
    """Leave the cluster; the instance this engine started is stopped, every process of it."""
    if self._started:
      import ray
      ray.shutdown()
      self._started = False
    self._end_instance()


def make_engine(engine: str, address: str | None = None) -> LocalEngine | RayEngine:
  """The engine called `engine` ("local" or "ray"; `address` only for "ray"). A Ray engine
  neither joins nor checks its cluster here (a job with nothing to do needs none): its first use
  does both, refusing an address where no cluster answers within seconds, and `check` does the
  latter alone, for a caller to run before its own work.

  Raises:
    ValueError: an unknown engine, or an address given to the local engine.
  """
  if engine == "local":
    if address:
      raise ValueError(f"address: {address!r} is for engine='ray'; the local engine runs in "
                       "this process")
    return LocalEngine()
  if engine == "ray":
    return RayEngine(address)
  raise ValueError(f"engine: expected one of {ENGINES}, got {engine!r}")
