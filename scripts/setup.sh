#!/usr/bin/env bash
# Install gr_graph and everything it needs on a fresh Debian/Ubuntu machine with Python 3.11,
# into the Python environment that is active (a virtual environment is recommended).
#   bash scripts/setup.sh               # the package
#   bash scripts/setup.sh --test        # the package and the test tools
#   bash scripts/setup.sh --bench       # ... and the benchmark baselines (kiss-icp)
#   bash scripts/setup.sh --unlocked    # any of the above, resolving pyproject.toml's ranges
#                                       # instead of the tested versions in scripts/constraints.txt
# By default every package is installed at the version in scripts/constraints.txt, the set the
# tests were run with (refresh it with bash scripts/lock.sh).
# open3d's wheel loads the system library libusb-1.0 (Debian package libusb-1.0-0), and
# open3d / torch load libgomp; both are installed with apt-get when missing (as root, or
# through sudo). torch is pinned to the CPU build 2.13.0 in pyproject.toml.
set -euo pipefail
cd "$(dirname "$0")/.."

extras=""
locked=1
for arg in "$@"; do
  case "$arg" in
    --test) extras="[test]" ;;
    --bench) extras="[test,bench]" ;;
    --unlocked) locked=0 ;;
    *) echo "usage: bash scripts/setup.sh [--test|--bench] [--unlocked]" >&2; exit 2 ;;
  esac
done

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
constraints=()
[ "$locked" -eq 1 ] && constraints=(-c scripts/constraints.txt)
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore "${constraints[@]}" -e ".${extras}"
python -c "import gr_graph, factors, training, gtsam, open3d, small_gicp, torch; print('gr_graph installed: torch', torch.__version__)"
