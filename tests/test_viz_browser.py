"""`lrf-view` in a real browser: headless Chromium (Debian's chromium-headless-shell or
chromium, driven by playwright; no browser download) loads the page of a running `lrf-view` on
a multiway output folder, finds the scene's canvas and every scan's name in the GUI, and the
screenshot shows each scan in its own colour; unticking a scan hides it.

Skips, saying which piece is missing, without playwright, a Chromium or viser. `LRF_CHROMIUM`
names a browser binary of one's own."""

from __future__ import annotations

import io
import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.test_viz import NAMES, make_model_folder

REPO = Path(__file__).resolve().parents[1]
# The binaries tried, in order, when LRF_CHROMIUM is not set (Debian's packages first).
CHROMIUMS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome",
             "google-chrome-stable")
# WebGL without a GPU: Chromium's software rasteriser (SwiftShader, through ANGLE).
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--ignore-gpu-blocklist"]
# Pixels of its colour a scan must cover in the scene (the legend's swatch is ~150).
MIN_PIXELS = 400

pytestmark = pytest.mark.timeout(120)


def chromium() -> str:
  """The browser binary, or skip saying what to install."""
  given = os.environ.get("LRF_CHROMIUM")
  if given:
    if not (Path(given).is_file() and os.access(given, os.X_OK)):
      pytest.skip(f"LRF_CHROMIUM={given} is not an executable file")
    return given
  for name in CHROMIUMS:
    found = shutil.which(name)
    if found:
      return found
  pytest.skip("no Chromium found (tried " + ", ".join(CHROMIUMS) + "): install Debian's "
              "chromium-headless-shell (apt-get install chromium-headless-shell; .ci/run does) "
              "or set LRF_CHROMIUM to a Chromium binary")


def _pixels(png: bytes, rgb, region: tuple[int, int]) -> int:
  """How many pixels of the screenshot's left `region` (width, height) are within 12 of
  `rgb` in every channel."""
  from PIL import Image
  image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))[:region[1], :region[0]]
  return int((np.abs(image.astype(int) - np.asarray(rgb)).max(axis=-1) <= 12).sum())


def test_the_page_shows_every_scan_in_its_colour(tmp_path):
  sync_api = pytest.importorskip("playwright.sync_api",
                                 reason="playwright is not installed (pip install playwright; "
                                        "the [test] extra)")
  pytest.importorskip("viser", reason="viser is not installed (pip install 'lrf_jax[viz]')")
  pytest.importorskip("PIL", reason="Pillow is not installed (matplotlib's dependency)")
  browser_path = chromium()
  from lrf_jax.multiway.figures import scan_colours
  folder = make_model_folder(tmp_path / "model")
  env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
  proc = subprocess.Popen([sys.executable, "-m", "lrf_jax.cli.view", str(folder), "--no-browser"],
                          stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
  try:
    line = proc.stdout.readline()
    m = re.match(r"lrf-view: (http://127\.0\.0\.1:\d+/) ", line)
    assert m, (line, proc.stderr.read() if proc.poll() is not None else "")
    with sync_api.sync_playwright() as pw:
      try:
        browser = pw.chromium.launch(executable_path=browser_path, args=CHROMIUM_ARGS)
      except sync_api.Error as e:
        pytest.skip(f"{browser_path} did not start under playwright: {str(e).splitlines()[0]}")
      try:
        _check_page(browser.new_page(viewport={"width": 1100, "height": 700}), m.group(1),
                    [tuple(int(v) for v in c) for c in scan_colours(len(NAMES))])
      finally:
        browser.close()
  finally:
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
  assert proc.returncode == 130, err


def _check_page(page, url: str, colours: list[tuple[int, ...]]) -> None:
  """The page at `url`: a canvas, every scan's name, each scan's colour in the scene (left of
  the GUI panel); unticking the second scan removes its colour."""
  page.goto(url)
  page.wait_for_selector("canvas", timeout=30_000)
  for name in NAMES:
    page.get_by_text(name, exact=True).first.wait_for(timeout=30_000)
  # viser's notices ("Software WebGL rendering detected", an orange bar) would count as scans
  page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
  panel = page.get_by_text("Scans", exact=True).first.bounding_box()
  assert panel is not None
  region = (int(panel["x"]) - 20, 700)  # the scene, left of the panel
  counts: list[int] = []
  for _ in range(40):  # the clouds arrive after the GUI; the first frames may be empty
    page.wait_for_timeout(250)
    png = page.screenshot()
    counts = [_pixels(png, c, region) for c in colours]
    if min(counts) >= MIN_PIXELS:
      break
  assert min(counts) >= MIN_PIXELS, dict(zip(NAMES, counts))
  page.get_by_role("checkbox", name=NAMES[1]).uncheck()
  for _ in range(20):
    page.wait_for_timeout(250)
    hidden = _pixels(page.screenshot(), colours[1], region)
    if hidden < MIN_PIXELS // 4:
      break
  assert hidden < MIN_PIXELS // 4, hidden
  assert _pixels(page.screenshot(), colours[0], region) >= MIN_PIXELS
