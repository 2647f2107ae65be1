#!/usr/bin/env bash
# Validates .glb files (a bake's mesh.glb) with the Khronos glTF validator, from npm.
#
#   scripts/validate-gltf.sh out/mesh.glb [more.glb ...]
#
# Installs the npm package `gltf-validator` (pinned below) on first use into
# $GLTF_VALIDATOR_DIR (default: ${TMPDIR:-/tmp}/radiosity-gltf-validator; needs node and
# npm, and registry.npmjs.org once), then prints, per file, the counts of errors, warnings,
# infos and hints and every issue. Exit status: 0 when no file has an error, 1 when one
# does, 2 when node or the validator is missing.
set -euo pipefail
VERSION=2.0.0-dev.3.10
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
dir=${GLTF_VALIDATOR_DIR:-${TMPDIR:-/tmp}/radiosity-gltf-validator}
if [ $# -eq 0 ]; then
  echo "usage: $0 FILE.glb..." >&2
  exit 2
fi
for tool in node npm; do
  if ! command -v "$tool" >/dev/null; then
    echo "validate-gltf: $tool not found (install Node.js 18 or later)" >&2
    exit 2
  fi
done
if [ ! -f "$dir/node_modules/gltf-validator/package.json" ] ||
  ! grep -q "\"version\": \"$VERSION\"" "$dir/node_modules/gltf-validator/package.json"; then
  mkdir -p "$dir"
  echo "validate-gltf: installing gltf-validator $VERSION into $dir" >&2
  if ! (cd "$dir" && npm install --no-audit --no-fund --silent "gltf-validator@$VERSION" >&2); then
    echo "validate-gltf: npm install gltf-validator@$VERSION failed" >&2
    exit 2
  fi
fi
GLTF_VALIDATOR_DIR=$dir exec node "$here/validate-gltf.mjs" "$@"
