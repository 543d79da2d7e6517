#!/usr/bin/env bash
# The peers of the benchmarks, never runtime dependencies of lrf_jax: PCL 1.13 (Debian's
# libpcl-dev, driver built from tools/pcl_driver) and Open3D (PyPI). Run from the repository
# root inside the project's venv:  bash benchmarks/setup.sh
set -euo pipefail
cd "$(dirname "$0")/.."
if ! dpkg -s libpcl-dev >/dev/null 2>&1; then
  sudo_cmd=""; [ "$(id -u)" -ne 0 ] && sudo_cmd="sudo"
  $sudo_cmd apt-get update -qq
  # libusb-1.0-0: a shared library the Open3D wheel links (missing on a bare machine)
  DEBIAN_FRONTEND=noninteractive $sudo_cmd apt-get install -y -qq libpcl-dev cmake g++ libusb-1.0-0
fi
cmake -S tools/pcl_driver -B tools/pcl_driver/build -DCMAKE_BUILD_TYPE=Release
cmake --build tools/pcl_driver/build -j
pip install -r benchmarks/requirements-bench.txt
