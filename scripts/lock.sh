#!/usr/bin/env bash
# Refresh scripts/constraints.txt, the tested set of package versions that scripts/setup.sh
# installs with by default:
#   bash scripts/lock.sh
# Resolves pyproject.toml's ranges (with every extra) in a new, empty virtual environment and
# writes what pip installed. Local version labels (torch's "+cpu") are dropped so the file
# also works where that build is not on disk; pyproject.toml keeps torch on its CPU pin.
# Run the test suite after a refresh (bash .ci/run) before committing the new file.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --disable-pip-version-check --root-user-action=ignore ".[test,bench]"
{
  echo "# Tested package versions: bash scripts/setup.sh installs with them (-c) by default."
  echo "# Made by 'bash scripts/lock.sh' with $("$work/venv/bin/python" --version) on $(date -u +%Y-%m-%d); refresh the same way."
  "$work/venv/bin/python" -m pip freeze --disable-pip-version-check --exclude-editable \
    | grep -v -i '^gr-graph' | sed -E 's/^([^=]+==[^+]+)\+.*$/\1/'
} > scripts/constraints.txt.tmp
mv scripts/constraints.txt.tmp scripts/constraints.txt
echo "wrote scripts/constraints.txt ($(grep -vc '^#' scripts/constraints.txt) packages)"
