#!/usr/bin/env bash
# One-command set-up for a fresh Debian machine (run as root, from the repository):
#   bash scripts/bootstrap.sh gui    install everything, open the GUI on the built-in demo leg
#   bash scripts/bootstrap.sh test   install everything, run the whole test suite (GUI under Xvfb)
set -euo pipefail
cd "$(dirname "$0")/.."
mode="${1:-}"
case "$mode" in gui|test) ;; *) echo "usage: bash scripts/bootstrap.sh gui|test" >&2; exit 64 ;; esac

# --- system packages: Python, venv, and the X/GL libraries a Qt + VTK window needs -----------
apt_pkgs=(python3 python3-venv python3-pip xvfb xauth libgl1 libegl1 libxrender1 libdbus-1-3
  libxkbcommon-x11-0 libxcb-icccm4 libxcb-image0 libxcb-keysyms1 libxcb-randr0
  libxcb-render-util0 libxcb-shape0 libxcb-xinerama0 libxcb-xkb1 libxcb-cursor0 fontconfig)
missing=()
for p in "${apt_pkgs[@]}"; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
if [ "${#missing[@]}" -gt 0 ]; then
  if [ "$(id -u)" -ne 0 ]; then echo "need root to apt-get install: ${missing[*]}" >&2; exit 1; fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq "${missing[@]}" >/dev/null
fi

# --- Python environment (reuses already-installed wheels where the system has them) ----------
if [ ! -x .venv/bin/python ]; then
  python3 -m venv --system-site-packages .venv
fi
.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"

if [ "$mode" = test ]; then
  export QT_API=pyside6 PYTHONDONTWRITEBYTECODE=1
  exec xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/python -m pytest -p no:cacheprovider "${@:2}"
fi

# gui: open the window on the demo leg; with no display, run it on a virtual screen and save a
# screenshot so a headless machine still shows what the window looks like.
if [ -n "${DISPLAY:-}${WAYLAND_DISPLAY:-}" ]; then
  exec .venv/bin/kneegui-gui "${@:2}"
fi
echo "No display: running the GUI on a virtual screen; screenshot -> kneegui-demo.png"
exec xvfb-run -a -s "-screen 0 1600x1000x24" .venv/bin/kneegui-gui --screenshot kneegui-demo.png "${@:2}"
