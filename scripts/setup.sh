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

# ---- Blender as a Python module (tests/blender: the exported asset opened in Blender) ----
# The pinned `bpy` wheel (tools/blender/requirements.txt) in its own environment,
# tools/blender/.venv: bpy bundles its own USD, OpenEXR and glog, and aborted at import inside
# the project's .venv ("You called InitGoogleLogging() twice"). It needs a few X11 client
# libraries even headless. Skipped when the stamp matches the requirements file.
bl_env=tools/blender/.venv
bl_want=$(sha256sum tools/blender/requirements.txt | cut -d' ' -f1)
if [ ! -f "$bl_env/.setup-stamp" ] || [ "$(cat "$bl_env/.setup-stamp")" != "$bl_want" ] || \
   [ ! -x "$bl_env/bin/python" ]; then
  bl_pkgs=()
  for pair in libX11.so.6:libx11-6 libXrender.so.1:libxrender1 libXfixes.so.3:libxfixes3 \
              libXi.so.6:libxi6 libxkbcommon.so.0:libxkbcommon0 libSM.so.6:libsm6 \
              libICE.so.6:libice6 libXext.so.6:libxext6 libXt.so.6:libxt6; do
    ldconfig -p 2>/dev/null | grep -q "${pair%%:*}" || bl_pkgs+=("${pair#*:}")
  done
  if [ ${#bl_pkgs[@]} -gt 0 ]; then
    if [ "$(id -u)" -ne 0 ]; then
      log "missing system packages for bpy: ${bl_pkgs[*]}; run as root or: sudo apt-get install -y ${bl_pkgs[*]}"
      exit 1
    fi
    log "installing system packages for bpy: ${bl_pkgs[*]}"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${bl_pkgs[@]}" >/dev/null || \
      { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${bl_pkgs[@]}" >/dev/null; }
  fi
  log "installing Blender's bpy into $bl_env (first run: a 370 MB wheel)"
  [ -x "$bl_env/bin/python" ] || "$py" -m venv "$bl_env"
  "$bl_env/bin/python" -m pip install -q -r tools/blender/requirements.txt
  "$bl_env/bin/python" -c "import bpy; print('[setup] bpy', bpy.app.version_string)" >&2
  echo "$bl_want" > "$bl_env/.setup-stamp"
fi
# ---- end of the Blender block ----

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
