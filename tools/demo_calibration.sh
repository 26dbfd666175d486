#!/usr/bin/env bash
# Make the demo's calibration file again: a calibration drive of the virtual robot (the
# calibration route, the figure eight driven four times over the default floor, seed 11:
# not the demo's own route or seed, but the demo's robot: --base-seed 0 gives it the wheel
# and gyro errors of the demo's seed-0 base), then `robotd calibrate loop-curve` and
# `robotd calibrate odometry` on the same drive, exactly as on a robot. Writes
# robotd/app/data/demo_calibration.yml (shipped with the package; `robotd demo` uses it
# when the config names no calibration file that exists). About an hour on 2 cores.
# DRIVE=path.mcap reuses a recording of that drive made before (the same command line as
# below) instead of recording it again; KEEP_THRESHOLDS=1 keeps the shipped file's loop
# thresholds and fits only the odometry model; ODOMETRY_PLOT=path.png keeps the residual
# plot.
set -euo pipefail
cd "$(dirname "$0")/.."
ROBOTD=${ROBOTD:-.venv/bin/robotd}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
drive=${DRIVE:-$work/drive.mcap}
if [ -z "${DRIVE:-}" ]; then
    # Lossless frames: the thresholds are trained on the pixels the camera gave (a JPEG
    # recording, robotd record's default, shifts them; see README "Compact recordings").
    printf '[recording]\nimage_format = "png"\n' > "$work/record.toml"
    "$ROBOTD" record "$drive" --virtual --route calibration --seed 11 --base-seed 0 \
        --config "$work/record.toml"
fi
out=robotd/app/data/demo_calibration.yml
rm -f "$out.new"
if [ -n "${KEEP_THRESHOLDS:-}" ]; then
    # Keep the shipped loop thresholds and fit only the odometry model.
    cp "$out" "$out.new"
else
    "$ROBOTD" calibrate loop-curve "$drive" --calibration "$out.new" \
        --plot "$work/curves.png" --json "$work/train.json"
fi
# The odometry model from the same drive: the loop-corrected trajectory (with the
# thresholds just trained) against the wheels and the gyro.
"$ROBOTD" calibrate odometry "$drive" --calibration "$out.new" \
    --plot "${ODOMETRY_PLOT:-$work/odometry.png}" --json "$work/odometry.json"
mv "$out.new" "$out"
echo "wrote $out"
