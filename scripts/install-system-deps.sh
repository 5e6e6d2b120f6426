#!/usr/bin/env bash
# System libraries plantscan needs on Debian/Ubuntu, installed when missing (as root),
# otherwise a clear message saying what to install.
#   libusb-1.0-0  open3d (and libgphoto2's USB access)
#   libgomp1      open3d / OpenCV threading
#   socat         the serial-stage tests (an emulator on a pseudo-terminal)
#   chromium      the HTML report test (headless browser)
#   postgresql    the results store tests (a throw-away server each test session starts)
set -euo pipefail
PKGS=(libusb-1.0-0 libgomp1 socat chromium postgresql)
missing=()
if ! command -v dpkg-query >/dev/null 2>&1; then
  echo "install-system-deps: not a Debian/Ubuntu system; make sure you have: ${PKGS[*]}"
  exit 0
fi
for p in "${PKGS[@]}"; do
  if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed"; then
    missing+=("$p")
  fi
done
# python3 -m venv needs ensurepip (Debian's python3-venv) unless this Python ships it.
if ! python3 -c "import ensurepip" >/dev/null 2>&1; then
  missing+=(python3-venv)
fi
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" -ne 0 ]; then
  echo "install-system-deps: missing system packages: ${missing[*]}"
  echo "  run: sudo apt-get install -y ${missing[*]}"
  exit 1
fi
echo "install-system-deps: installing ${missing[*]}"
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
