#!/usr/bin/env bash
# Installs what the project needs on a fresh Debian/Ubuntu machine: libLLVM >= 16 for Dr.Jit's CPU backend
# (Debian 12 ships 14/15, with which LLVM aborts) and the Python package with its test extras.
set -euo pipefail
cd "$(dirname "$0")/.."

has_llvm16() {
  { ls /usr/lib/*/libLLVM*.so* /usr/lib/libLLVM*.so* 2>/dev/null || true; } | grep -qE 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'
}
if ! has_llvm16; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  echo "setup: installing libllvm19 (Dr.Jit's CPU backend needs LLVM >= 16)"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi
python3 -m pip install -q --disable-pip-version-check -e ".[dev]"
