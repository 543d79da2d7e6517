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

Loopback: `address="local"` starts a Ray instance of this machine bound to 127.0.0.1, and a
driver joining a cluster at a loopback address stays on loopback (Ray 2.5x-2.6x otherwise
resolves "127.0.0.1" to the machine's interface address before connecting; the driver
switches that resolution off with Ray's `RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`, set only in this
process).
"""

from __future__ import annotations

import dataclasses
import ipaddress
import os
from typing import Any, Protocol
from collections.abc import Callable, Iterator, Sequence

__all__ = ["ENGINES", "LocalEngine", "Outcome", "RayEngine", "address_problem", "make_engine",
           "resolve_address"]

ENGINES = ("local", "ray")
# Ray's retries of a task whose worker or node died (not of an item's own error).
MAX_RETRIES = 3
_LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"


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
  import lrf_jax
  return lrf_jax.__version__


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

  import lrf_jax
  node = ray.get_runtime_context().get_node_id()
  core = getattr(ray._private.worker.global_worker, "core_worker", None)  # noqa: SLF001
  attempt = 1
  if core is not None and hasattr(core, "get_current_task_attempt_number"):
    attempt = int(core.get_current_task_attempt_number()) + 1
  if lrf_jax.__version__ != driver_version:
    return (None, f"the worker runs lrf_jax {lrf_jax.__version__}, the driver "
                  f"{driver_version}: refused", node, attempt, lrf_jax.__version__)
  if isinstance(payload, dict):  # the values `RayEngine.put` stored, fetched once each
    payload = {k: ray.get(v) if isinstance(v, ray.ObjectRef) else v for k, v in payload.items()}
  return fn(payload), None, node, attempt, lrf_jax.__version__


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
  where nothing answers is then a ValueError (`address_problem`) within 3 s.
  """

  name = "ray"

  def __init__(self, address: str | None = None, *, cpus_per_task: int = 1,
               max_in_flight: int | None = None, max_retries: int = MAX_RETRIES):
    self.address = resolve_address(address)
    self.cpus_per_task = int(cpus_per_task)
    self.max_in_flight = max_in_flight
    self.max_retries = int(max_retries)
    self._started = False

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
      problem = address_problem(self.address)
      if problem:  # at once, not after Ray's minutes of retries
        raise ValueError(problem)
      kw: dict[str, Any] = dict(address=self.address, logging_level="warning",
                                log_to_driver=False)
      if is_loopback(self.address):
        kw["_node_ip_address"] = "127.0.0.1"
      if self.address == "local":
        kw["include_dashboard"] = False
      ray.init(**kw)
      self._started = True
    return ray

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
    if self._started:
      import ray
      ray.shutdown()
      self._started = False


def make_engine(engine: str, address: str | None = None) -> LocalEngine | RayEngine:
  """The engine called `engine` ("local" or "ray"; `address` only for "ray").

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
