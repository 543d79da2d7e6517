"""The version is written in one place, pyproject.toml; `lrf_jax.__version__` is the installed
distribution's (importlib.metadata), read on first access."""

from __future__ import annotations

import importlib.metadata
import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from urllib.parse import unquote, urlparse

import pytest

import lrf_jax

ROOT = Path(__file__).resolve().parents[1]
VERSION = "0.9.0"


def test_pyproject_holds_the_version():
  project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
  assert project["version"] == VERSION and "version" not in project.get("dynamic", [])


def test_version_is_the_installed_metadata():
  assert lrf_jax.__version__ == importlib.metadata.version("lrf_jax")
  assert "__version__" in dir(lrf_jax)


def test_an_install_of_this_checkout_is_this_version():
  """Where the installed lrf_jax is this checkout (CI: `pip install -e .`), its metadata says
  pyproject's version; an older one means the install is stale (reinstall)."""
  direct_url = importlib.metadata.distribution("lrf_jax").read_text("direct_url.json")
  url = json.loads(direct_url or "{}").get("url", "")
  if not url.startswith("file:") or Path(unquote(urlparse(url).path)).resolve() != ROOT:
    pytest.skip(f"the installed lrf_jax is not this checkout ({url or 'no direct_url.json'})")
  assert lrf_jax.__version__ == importlib.metadata.version("lrf_jax") == VERSION


def test_no_other_version_literal_in_the_package():
  found = [f"{p.relative_to(ROOT)}:{i}" for p in (ROOT / "lrf_jax").rglob("*.py")
           for i, line in enumerate(p.read_text().splitlines(), 1)
           if re.match(r"\s*__version__\s*(:[^=]*)?=", line)]
  assert found == []


def test_without_metadata_the_version_says_unknown(monkeypatch):
  def missing(name):
    raise importlib.metadata.PackageNotFoundError(name)
  monkeypatch.setattr(importlib.metadata, "version", missing)
  from lrf_jax.records import version
  assert version() == "0+unknown"


def test_reading_the_version_loads_no_jax():
  code = "import sys, lrf_jax; v = lrf_jax.__version__; assert 'jax' not in sys.modules; print(v)"
  out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                       timeout=60)
  assert out.returncode == 0, out.stderr
  assert out.stdout.strip() == importlib.metadata.version("lrf_jax")
