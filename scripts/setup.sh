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
# through sudo). torch 2.13.0 (pyproject.toml) is installed as its CPU build, from PyTorch's CPU
# index, unless a torch 2.13.0 is there already. The active Python must be a virtual environment
# where the system manages its own (PEP 668); the script says so.
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

if ! command -v python >/dev/null; then
  echo "no 'python' command: create and activate a virtual environment first, e.g." >&2
  echo "  python3.11 -m venv .venv && . .venv/bin/activate && bash scripts/setup.sh" >&2
  exit 1
fi
if python -c 'import sys, sysconfig, pathlib; sys.exit(sys.prefix == sys.base_prefix and pathlib.Path(sysconfig.get_path("stdlib"), "EXTERNALLY-MANAGED").is_file())'; then :; else
  echo "this Python is managed by the system (PEP 668: pip may not install into it): create and activate a" >&2
  echo "virtual environment first, e.g.  python3.11 -m venv .venv && . .venv/bin/activate" >&2
  exit 1
fi

# the linker's cache, read once (a grep -q straight on ldconfig's pipe can kill it with SIGPIPE, which
# pipefail would take for a missing library); ldconfig may not be on a user's PATH (/sbin)
libraries=$(ldconfig -p 2>/dev/null || /sbin/ldconfig -p 2>/dev/null || true)
missing=()
grep -q 'libusb-1.0.so.0' <<< "$libraries" || missing+=(libusb-1.0-0)
grep -q 'libgomp.so.1' <<< "$libraries" || missing+=(libgomp1)
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
# torch: the CPU build. On Linux the plain torch==2.13.0 of PyPI is the CUDA build (several GB of CUDA
# libraries); PyTorch's CPU index has 2.13.0+cpu. A torch 2.13.0 already there (e.g. a CUDA build put
# in on purpose, for --device cuda) is kept.
torch_version=2.13.0
if ! python -c "import importlib.metadata as m, sys; sys.exit(m.version('torch').split('+')[0] != '$torch_version')" 2>/dev/null; then
  echo "installing torch $torch_version, CPU build (https://download.pytorch.org/whl/cpu)"
  python -m pip install -qq --disable-pip-version-check --root-user-action=ignore --no-deps --retries 1 \
    --extra-index-url https://download.pytorch.org/whl/cpu "torch==${torch_version}+cpu"
fi
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore "${constraints[@]}" -e ".${extras}"
python -c "import gr_graph, factors, training, gtsam, open3d, small_gicp, torch; print('gr_graph installed: torch', torch.__version__, '(CUDA ' + torch.version.cuda + ')' if torch.version.cuda else '(CPU build)')"
