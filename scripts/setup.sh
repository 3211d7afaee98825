#!/usr/bin/env bash
# Idempotent set-up on a fresh Debian machine (Python 3.11, root):
#   system libraries (libLLVM >= 17 for drjit's CPU backend, libusb for open3d),
#   a virtual environment at .venv with the pinned dependencies and `recon` installed.
# Re-running is fast: each part is skipped when its inputs did not change.
set -euo pipefail
cd "$(dirname "$0")/.."
root=$(pwd)

log() { printf '[setup] %s\n' "$*" >&2; }

# ---- System libraries ----
py=${PYTHON:-python3.11}
command -v "$py" >/dev/null 2>&1 || py=python3
need_pkgs=()
# Debian's python3.x ships without ensurepip; `python -m venv` needs python3.x-venv
"$py" -c 'import ensurepip' >/dev/null 2>&1 || \
  need_pkgs+=("$("$py" -c 'import sys; print("python%d.%d-venv" % sys.version_info[:2])')")
ls /usr/lib/x86_64-linux-gnu/libLLVM-19.so* >/dev/null 2>&1 || ls /usr/lib/*/libLLVM.so.19* >/dev/null 2>&1 || need_pkgs+=(libllvm19)
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || need_pkgs+=(libusb-1.0-0)
ldconfig -p 2>/dev/null | grep -q 'libgomp.so.1' || need_pkgs+=(libgomp1)
ldconfig -p 2>/dev/null | grep -q 'libGL.so.1' || need_pkgs+=(libgl1)
command -v node >/dev/null 2>&1 || need_pkgs+=(nodejs)
command -v npm >/dev/null 2>&1 || need_pkgs+=(npm)
command -v chromium >/dev/null 2>&1 || need_pkgs+=(chromium)   # headless report tests
[ -f /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ] || need_pkgs+=(fonts-dejavu-core)
if [ ${#need_pkgs[@]} -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then
    log "missing system packages: ${need_pkgs[*]}; run as root or: sudo apt-get install -y ${need_pkgs[*]}"
    exit 1
  fi
  log "installing system packages: ${need_pkgs[*]}"
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${need_pkgs[@]}" >/dev/null
fi

# ---- Node tools (tools/<name>/package-lock.json: the glTF validator, the report's model-viewer) ----
for lock in tools/*/package-lock.json; do
  [ -f "$lock" ] || continue
  tool=$(dirname "$lock")
  lock_sum=$(sha256sum "$lock" | cut -d' ' -f1)
  if [ ! -f "$tool/node_modules/.recon-stamp" ] || \
     [ "$(cat "$tool/node_modules/.recon-stamp")" != "$lock_sum" ]; then
    log "installing $tool (npm ci)"
    npm ci --silent --no-audit --no-fund --prefix "$tool" >/dev/null
    echo "$lock_sum" > "$tool/node_modules/.recon-stamp"
  fi
done

# ---- Python environment ----
stamp=.venv/.setup-stamp
want=$(cat requirements.txt requirements-dev.txt pyproject.toml | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x .venv/bin/python ]; then
  exit 0
fi
if [ ! -x .venv/bin/python ]; then
  log "creating .venv with $($py --version)"
  "$py" -m venv .venv
fi
log "installing pinned dependencies into .venv (first run: several minutes)"
.venv/bin/python -m pip install -q --upgrade pip wheel >/dev/null
# torch first and alone, so that nothing can pull the CUDA build.
.venv/bin/python -m pip install -q "torch==2.13.0"
.venv/bin/python -m pip install -q -r requirements-dev.txt
.venv/bin/python -m pip install -q --no-deps -e .
# Check that drjit finds a usable libLLVM (recon picks libLLVM >= 17 itself).
.venv/bin/python -c "import recon.mi as m; m.load_variant(); print('[setup] mitsuba variant', m.variant())" >&2
echo "$want" > "$stamp"
log "done"
