#!/usr/bin/env bash
# The install a robot gets, checked without the repository's ./dev: build robotd's wheel,
# install it into a new virtualenv (its dependencies from the package index, systemd-python
# compiled as on the robot: docs/install.md), then run what a new user runs first.
# Usage: tools/check_wheel_install.sh [PYTHON]   (CI: .ci/run)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-${PYTHON:-python3}}
work=$(mktemp -d /tmp/robotd-wheel-XXXXXX)
trap 'rm -rf "$work"' EXIT

echo "==> building the wheel"
"$PY" -m pip wheel --quiet --disable-pip-version-check --no-deps -w "$work/dist" . > "$work/build.log" 2>&1 \
  || { tail -n 30 "$work/build.log" >&2; echo "building the wheel failed" >&2; exit 1; }
wheel=$(ls "$work"/dist/robotd-*.whl)
echo "    $(basename "$wheel")"

echo "==> installing it into a new virtualenv"
"$PY" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install --quiet --disable-pip-version-check "$wheel" > "$work/pip.log" 2>&1 \
  || { tail -n 30 "$work/pip.log" >&2; echo "pip install of the wheel failed" >&2; exit 1; }

robotd="$work/venv/bin/robotd"
echo "==> robotd --version";            "$robotd" --version
echo "==> robotd config check";         "$robotd" config check systemd/robotd.toml
echo "==> a 5 s demo (from /tmp, away from the repository)"
(cd "$work" && "$robotd" demo --route square --duration 5 --no-plot --out "$work/demo" > "$work/demo.txt" 2>&1) \
  || { tail -n 30 "$work/demo.txt" >&2; echo "the demo from the wheel failed" >&2; exit 1; }
grep -E "^(route|keyframes|map links)" "$work/demo.txt"
test -s "$work/demo/map.sqlite" && test -s "$work/demo/corrected.tum"
echo "wheel install: OK"
