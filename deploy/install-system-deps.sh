#!/usr/bin/env bash
# System libraries the Python wheels need: open3d -> libusb-1.0-0 (and libgomp1),
# pymeshlab/opencv -> libGL and GLib, gmsh -> GLU and the X libraries its library links to (it
# opens no window); the tests open the QA report in a real browser: chromium (headless); the FE
# solve runs CalculiX: calculix-ccx. Installs
# only what is missing; needs root for apt-get.
set -euo pipefail
packages=(libusb-1.0-0 libgl1 libglib2.0-0 libgomp1 libglu1-mesa libxcursor1 libxft2 libxinerama1 libxrender1
          libxfixes3 libfontconfig1 chromium calculix-ccx)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
if [ "$(id -u)" -ne 0 ]; then
  echo "missing system packages: ${missing[*]}; run: sudo apt-get install -y ${missing[*]}" >&2
  exit 1
fi
echo "installing system packages: ${missing[*]}" >&2
apt-get update -qq
DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
