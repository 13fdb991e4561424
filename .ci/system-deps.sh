#!/usr/bin/env bash
# Debian packages BoneUSRecon needs beyond Python and pip:
#   libegl1 libgl1-mesa-dri  off-screen (EGL) rendering for the VTK wheel; without them
#                            VTK dies with SIGSEGV instead of raising an error.
#   chromium                 only for the test that renders the HTML report in a real
#                            headless browser (skip it with BONEUSRECON_NO_CHROMIUM=1).
# Installs only what is missing; uses sudo when not root.
set -euo pipefail
pkgs=(libegl1 libgl1-mesa-dri)
[ "${BONEUSRECON_NO_CHROMIUM:-0}" = 1 ] || pkgs+=(chromium)
missing=()
for p in "${pkgs[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0
SUDO=""
[ "$(id -u)" -eq 0 ] || SUDO="sudo"
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -qq
$SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
