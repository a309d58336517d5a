#!/usr/bin/env bash
# The README's quick start, run exactly as written: its first command (set up, then start the app on
# the built-in dataset) until the app answers over HTTP, then its second (the tests).
#
# Usage: bash scripts/newcomer.sh [--clone] [--app-timeout SECONDS]
#   --clone   run in a fresh clone of this checkout's HEAD (in a temporary folder, removed after),
#             as a new user would; without it, in this checkout.
# Exits with the first failing command's status; 3 when the app never answered.
set -euo pipefail
cd "$(dirname "$0")/.."
clone=0
app_timeout=600
while [ $# -gt 0 ]; do
  case "$1" in
    --clone) clone=1 ;;
    --app-timeout) app_timeout=$2; shift ;;
    *) echo "newcomer: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
if [ "$clone" = 1 ]; then
  work=$(mktemp -d)
  trap 'rm -rf "$work"' EXIT
  git clone -q . "$work/blurcalib"
  cd "$work/blurcalib"
fi
# The quick start: the lines of the first ```bash block under "## Quick start", comments dropped.
mapfile -t commands < <(awk '/^## Quick start/ {q = 1} q && /^```bash/ {b = 1; next} b && /^```/ {exit}
                             b {sub(/[[:space:]]+#.*$/, ""); if (length) print}' README.md)
if [ "${#commands[@]}" -ne 2 ]; then
  echo "newcomer: README.md's quick start has ${#commands[@]} commands, not 2" >&2
  exit 2
fi
echo "newcomer: 1/2: ${commands[0]}"
log=$(mktemp)
bash -c "${commands[0]}" >"$log" 2>&1 &
app=$!
stop_app() { kill -TERM "$app" 2>/dev/null || true; pkill -TERM -P "$app" 2>/dev/null || true; wait "$app" 2>/dev/null || true; }
url=""
for _ in $(seq "$app_timeout"); do
  url=$(grep -o 'blurcalib app: http://[^ ]*' "$log" | head -n 1 | sed 's/^blurcalib app: //') || true
  if [ -n "$url" ] && python3 -c "import sys, urllib.request; urllib.request.urlopen(sys.argv[1], timeout=5)" "$url" 2>/dev/null; then
    break
  fi
  url=""
  if ! kill -0 "$app" 2>/dev/null; then break; fi
  sleep 1
done
if [ -z "$url" ]; then
  stop_app
  echo "newcomer: the app did not answer; its output:" >&2
  tail -n 30 "$log" >&2
  exit 3
fi
echo "newcomer: the app answers at $url"
stop_app
echo "newcomer: 2/2: ${commands[1]}"
bash -c "${commands[1]}"
