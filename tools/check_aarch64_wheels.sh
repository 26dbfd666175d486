#!/usr/bin/env bash
# Does the robot install resolve to wheels on a Raspberry Pi (Linux aarch64, CPython 3.11)?
#
#   tools/check_aarch64_wheels.sh [EXTRAS]     (default EXTRAS: can,depthai,foxglove; ros2 has no aarch64 wheel, docs/ros2.md)
#
# Resolves robotd's dependencies (pyproject.toml [project] dependencies plus the optional
# EXTRAS a robot may install) for Linux aarch64 and CPython 3.11 with binary wheels only
# (`--only-binary :all:`), as pip on the robot would, without installing anything: a full
# resolve (dependencies of dependencies too) with `pip install --dry-run`, which reads the
# wheels' metadata from PyPI (PEP 658) instead of downloading them. It fails, naming the
# package, when any of them would have to be compiled on the robot.
#
# Exceptions: the packages that the docs say must compile on the robot (listed in
# MUST_COMPILE below; today only systemd-python, which builds against libsystemd:
# `./dev` installs libsystemd-dev, pkg-config and gcc for it, see systemd/README.md).
# They are left out of the resolve, and their own dependencies are checked by name.
#
# glibc: the oldest platform docs/install.md lists is Ubuntu 22.04 (glibc 2.35; Raspberry
# Pi OS / Debian bookworm ship 2.36), so wheels tagged up to manylinux_2_35 are accepted
# (GLIBC_MAX overrides, e.g. 2.31 for bullseye). Needs network access to PyPI only; about
# 10-30 s.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] && PY=.venv/bin/python
EXTRAS=${1:-can,depthai,foxglove}
GLIBC_MAX=${GLIBC_MAX:-2.35}
MUST_COMPILE=${MUST_COMPILE-systemd-python}  # the docs name these; empty: check them too

mapfile -t REQS < <("$PY" - "$EXTRAS" "$MUST_COMPILE" <<'EOF'
import re, sys, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
extras = [e for e in sys.argv[1].split(",") if e]
skip = {s.lower() for s in sys.argv[2].split()}
reqs = list(project["dependencies"])
for e in extras:
    if e not in project.get("optional-dependencies", {}):
        sys.exit(f"check_aarch64_wheels: no extra {e!r} in pyproject.toml")
    reqs += project["optional-dependencies"][e]
for r in reqs:
    name = re.split(r"[<>=!~;\[ ]", r, maxsplit=1)[0].strip().lower().replace("_", "-")
    if name not in skip:
        print(r)
EOF
)

platforms=(--platform manylinux2014_aarch64)
minor=${GLIBC_MAX#2.}
for ((m = 17; m <= minor; m++)); do platforms+=(--platform "manylinux_2_${m}_aarch64"); done

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
echo "resolving ${#REQS[@]} requirements for Linux aarch64, CPython 3.11, wheels only (glibc <= $GLIBC_MAX)"
if ! "$PY" -m pip install --disable-pip-version-check --quiet --dry-run --ignore-installed \
      --only-binary :all: "${platforms[@]}" --python-version 3.11 --implementation cp --abi cp311 \
      --target "$tmp/target" --report "$tmp/report.json" "${REQS[@]}" 2>"$tmp/err"; then
  cat "$tmp/err" >&2
  echo "check_aarch64_wheels: FAILED: a dependency has no Linux aarch64 / CPython 3.11 wheel (above)" >&2
  exit 1
fi
"$PY" - "$tmp/report.json" <<'EOF'
import json, sys
report = json.load(open(sys.argv[1]))
rows = sorted((i["metadata"]["name"], i["metadata"]["version"], i["download_info"]["url"].rsplit("/", 1)[-1])
              for i in report["install"])
bad = [r for r in rows if not r[2].endswith(".whl")]
for name, version, f in rows:
    print(f"  {name} {version}: {f}")
if bad:
    sys.exit(f"check_aarch64_wheels: FAILED: not wheels: {', '.join(r[0] for r in bad)}")
print(f"check_aarch64_wheels: ok, {len(rows)} packages resolve to aarch64 / cp311 wheels")
EOF
