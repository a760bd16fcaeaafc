#!/bin/sh
# Entry point of the compose `replay` service: `sortie replay` of a recording, or of the
# newest recording in a folder (the recordings volume), with the options that follow.
#   replay.sh FILE|DIR [sortie replay options...]
set -eu
target="$1"
shift
if [ -d "$target" ]; then
    newest=$(ls -t "$target"/*.sortie 2>/dev/null | head -n 1 || true)
    if [ -z "$newest" ]; then
        echo "replay: no .sortie recording in $target (run the exercise first, or set REPLAY_FILE)" >&2
        exit 2
    fi
    target="$newest"
fi
echo "replay: serving $target" >&2
exec sortie replay "$target" "$@"
