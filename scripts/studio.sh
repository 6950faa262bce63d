#!/usr/bin/env bash
# Opens a folder of reconstructions (e.g. the demo's silvr-demo/) in the studio:
#   scripts/studio.sh DIR [silvr serve options, e.g. --port 0]
# Installs the studio's build tools (scripts/setup.sh studio), builds the studio (trunk build --release) when
# dist/ is missing or older than its sources, then runs `silvr serve DIR`, which prints the link to open.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 1 ] || { echo "usage: scripts/studio.sh DIR [silvr serve options]" >&2; exit 2; }
dir="$1"
shift
[ -d "$dir" ] || { echo "scripts/studio.sh: $dir is not a folder (run scripts/demo.sh first?)" >&2; exit 2; }
scripts/setup.sh studio
if [ ! -f dist/index.html ] || [ -n "$(find index.html web worker core shaders -newer dist/index.html -type f -print -quit)" ]; then
  PATH="$PWD/web/node_modules/.bin:$PATH" trunk build --release
fi
exec cargo run --release -q -p silvr -- serve "$dir" --studio dist "$@"
