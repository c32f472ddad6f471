#!/usr/bin/env bash
# Install gr_graph and everything it needs on a fresh Debian/Ubuntu machine with Python 3.11.
#   bash scripts/setup.sh          # the package
#   bash scripts/setup.sh --test   # the package and the test tools
# open3d's wheel loads the system library libusb-1.0 (Debian package libusb-1.0-0), and
# open3d / torch load libgomp; both are installed with apt-get when missing (as root, or
# through sudo). torch is pinned to the CPU build 2.13.0 in pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
case "${1:-}" in
  --test) extras="[test]" ;;
  --bench) extras="[test,bench]" ;;
  "") ;;
  *) echo "usage: bash scripts/setup.sh [--test|--bench]" >&2; exit 2 ;;
esac

missing=()
ldconfig -p | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
ldconfig -p | grep -q 'libgomp.so.1' || missing+=(libgomp1)
if [ "${#missing[@]}" -gt 0 ]; then
  if ! command -v apt-get >/dev/null; then
    echo "gr_graph needs the system libraries ${missing[*]}: install them with your package manager" >&2
    exit 1
  fi
  sudo_cmd=()
  [ "$(id -u)" -eq 0 ] || sudo_cmd=(sudo)
  echo "installing system libraries: ${missing[*]}"
  "${sudo_cmd[@]}" apt-get update -qq
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${missing[@]}" >/dev/null
fi

python_version=$(python -c 'import sys; print("%d.%d" % sys.version_info[:2])')
if [ "$python_version" != "3.11" ]; then
  echo "gr_graph needs Python 3.11 (found $python_version)" >&2
  exit 1
fi
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e ".${extras}"
python -c "import gr_graph, factors, training, gtsam, open3d, small_gicp, torch; print('gr_graph installed: torch', torch.__version__)"
