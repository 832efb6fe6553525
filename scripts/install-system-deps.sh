#!/usr/bin/env bash
# System libraries for offscreen rendering on the CPU (MuJoCo's EGL backend through Mesa).
# Installs only what is missing, so it is cheap on a machine that already has them.
set -euo pipefail
if ldconfig -p | grep -q 'libEGL.so.1' && ldconfig -p | grep -q 'libOpenGL.so.0\|libGL.so.1'; then
  exit 0
fi
if command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq libegl1 libgl1 libopengl0 libegl-mesa0 libgl1-mesa-dri >/dev/null
else
  echo "install an EGL or OSMesa library for offscreen rendering (see README)" >&2
fi
