#!/usr/bin/env bash
# Screenshot a report page with headless Chromium (Debian: `apt-get install -y chromium`).
#   scripts/screenshot_report.sh [REPORT_HTML] [OUT_PNG] [WIDTHxHEIGHT]
# Defaults: report/report.html -> docs/report_screenshot.png at 1280x2400 (the header, the model table,
# the SSIM / ATE-3D figure and the start of the example filmstrips).
set -euo pipefail

html="${1:-report/report.html}"
out="${2:-docs/report_screenshot.png}"
size="${3:-1280x2400}"

if [[ ! -f "$html" ]]; then
    echo "screenshot_report: $html does not exist; build it with 'rigidbench report runs/* --out report/'" >&2
    exit 2
fi
browser=""
for candidate in chromium chromium-browser google-chrome; do
    if command -v "$candidate" >/dev/null 2>&1; then browser="$candidate"; break; fi
done
if [[ -z "$browser" ]]; then
    echo "screenshot_report: no chromium found; install it with 'apt-get install -y chromium'" >&2
    exit 2
fi

mkdir -p "$(dirname "$out")"
abs_html="$(cd "$(dirname "$html")" && pwd)/$(basename "$html")"
abs_out="$(cd "$(dirname "$out")" && pwd)/$(basename "$out")"
# --no-sandbox: Chromium refuses to start as root (containers) without it.
# A throwaway profile keeps runs independent of any user profile.
profile="$(mktemp -d)"
trap 'rm -rf "$profile"' EXIT
"$browser" --headless --no-sandbox --disable-gpu --hide-scrollbars --user-data-dir="$profile" \
    --virtual-time-budget=10000 \
    --window-size="${size/x/,}" --screenshot="$abs_out" "file://$abs_html" >/dev/null 2>&1
if [[ ! -s "$abs_out" ]]; then
    echo "screenshot_report: $browser wrote no screenshot to $abs_out" >&2
    exit 1
fi
echo "wrote $out"
