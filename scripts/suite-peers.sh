#!/bin/sh
# Other programs on the benchmark suite (not a test): runs one adapter of scripts/suite-peers.py
# in a throwaway virtual environment with pyViewFactor 1.1.0, raystrack 2.0.0 and pyradiance
# 1.3.1 (whose wheel carries the Radiance programs, rfluxmtx among them).
# Usage: scripts/suite-peers.sh pyviewfactor|raystrack|radiance --suite DIR -o OUT [...]
set -eu
venv="${PEERS_VENV:-$(mktemp -d)/venv}"
if [ ! -x "$venv/bin/python" ]; then
    python3 -m venv "$venv"
fi
"$venv/bin/pip" install --quiet raystrack==2.0.0 pyViewFactor==1.1.0 pyradiance==1.3.1
rad="$("$venv/bin/python" -c 'import os, pyradiance; print(os.path.dirname(pyradiance.__file__))')"
PATH="$rad/bin:$PATH" RAYPATH="$rad/lib" "$venv/bin/python" "$(dirname "$0")/suite-peers.py" "$@"
