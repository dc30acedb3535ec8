#!/usr/bin/env bash
# Creates .venv and installs mi_shadowgs (editable) with its dev tools.
# Installs Debian's libllvm19 when no usable libLLVM is present and we are root:
# Dr.Jit 1.5's LLVM backend crashes with LLVM 14/15.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}

have_llvm() {
  ls /usr/lib/*-linux-gnu/libLLVM*.so* /usr/lib/llvm-*/lib/libLLVM*.so* 2>/dev/null \
    | grep -vE 'LLVM[-.]?(so\.)?1[45]([.-]|$)' | grep -q .
}
if ! have_llvm; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing libllvm19 (Dr.Jit's LLVM backend needs LLVM >= 16; 14/15 crash)"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "setup: no usable libLLVM found; install it: sudo apt-get install -y libllvm19" >&2
  fi
fi

if [ ! -x .venv/bin/python ]; then
  "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e '.[dev]'
touch .venv/.installed
