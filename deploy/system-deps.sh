#!/usr/bin/env bash
# System packages the cell needs on Debian 12 / Ubuntu: Open3D's shared libraries (libusb, OpenMP, GL),
# Python's venv module, a C compiler with Python's headers for the compiled perception kernels,
# PostgreSQL's server (the job store's tests run a real one), and Chromium with a font (the operator
# page's tests drive it headless with Playwright; no browser is downloaded).
# Installs only what is missing; uses sudo when not root.
set -euo pipefail

missing=()
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
have_lib 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
have_lib 'libgomp.so.1' || missing+=(libgomp1)
have_lib 'libGL.so.1' || missing+=(libgl1)
python3 -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
command -v gcc >/dev/null 2>&1 || missing+=(gcc)
command -v g++ >/dev/null 2>&1 || missing+=(g++)  # the bridge firmware's host build (tests/test_firmware_host.py)
python3 -c 'import sysconfig, os, sys; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' \
  || missing+=(python3-dev)
compgen -G '/usr/lib/postgresql/*/bin/initdb' >/dev/null || missing+=(postgresql)
command -v chromium >/dev/null 2>&1 || missing+=(chromium)
[ -e /usr/share/fonts/truetype/dejavu/DejaVuSans.ttf ] || missing+=(fonts-dejavu-core)

if [ ${#missing[@]} -eq 0 ]; then
  exit 0
fi
echo "installing system packages: ${missing[*]}"
SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
