#!/bin/sh
# Side by side with peers (not a test): radiosity, raystrack 2.0.0 and pyViewFactor 1.1.0 on
# the same cases in one run. Makes a throwaway virtual environment, builds the release binary.
# Usage: scripts/peers.sh [--cases ...] [--tools ...]   (from the repository root; --help lists them)
set -eu
venv="${PEERS_VENV:-$(mktemp -d)/venv}"
python3 -m venv "$venv"
"$venv/bin/pip" install --quiet raystrack==2.0.0 pyViewFactor==1.1.0
cargo build --release --quiet
RADIOSITY="$(pwd)/target/release/radiosity" "$venv/bin/python" "$(dirname "$0")/peers.py" "$@"
