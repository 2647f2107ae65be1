#!/usr/bin/env bash
# Provisions Embree 4 for the build: fetches the PyPI wheel embreex==4.4.0.post1 (a
# manylinux build of Embree 4.4 with its TBB) with `python3 -m pip download` (binary only,
# explicit platform tags, so the local Python version does not matter), checks it against
# a pinned sha256, and unpacks its two libraries into the cache folder that build.rs looks
# in: $RADIOSITY_EMBREE_CACHE, else $XDG_CACHE_HOME/radiosity, else ~/.cache/radiosity,
# each with the subfolder embree-4.4.0 (holding a libembree4.so link and a READY stamp).
#
# Idempotent: does nothing when the cache is ready. Prints the folder on stdout.
# Usage: scripts/provision-embree.sh      (needs python3 with pip, and the network once)
set -euo pipefail

WHEEL_REQ="embreex==4.4.0.post1"
WHEEL_FILE="embreex-4.4.0.post1-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl"
WHEEL_SHA256="2cd0f7d5c6342e6247e31f700761689cae7829454d8c6de0c41e62124a023e1f"
# The libraries inside the wheel (auditwheel renames them with a hash suffix).
WHEEL_EMBREE="embreex.libs/libembree4-4aef3270.so.4"
WHEEL_TBB="embreex.libs/libtbb-dcf63f8c.so.12"
CACHE_SUBDIR="embree-4.4.0"

say() { printf 'provision-embree: %s\n' "$*" >&2; }

if [ -n "${RADIOSITY_EMBREE_CACHE:-}" ]; then
  base="$RADIOSITY_EMBREE_CACHE"
elif [ -n "${XDG_CACHE_HOME:-}" ]; then
  base="$XDG_CACHE_HOME/radiosity"
elif [ -n "${HOME:-}" ]; then
  base="$HOME/.cache/radiosity"
else
  say "no cache folder: set RADIOSITY_EMBREE_CACHE or HOME"; exit 1
fi
dir="$base/$CACHE_SUBDIR"

if [ -e "$dir/READY" ] && [ -e "$dir/libembree4.so" ]; then
  printf '%s\n' "$dir"; exit 0
fi
if [ "$(uname -s)" != Linux ] || [ "$(uname -m)" != x86_64 ]; then
  say "the provisioned copy exists only for x86_64 Linux: set EMBREE_DIR to an Embree 4 install"
  exit 1
fi

say "fetching Embree 4.4 from PyPI ($WHEEL_REQ) into $dir"
mkdir -p "$base"
# Work in a private folder and rename at the end, so a concurrent build never sees half.
work="$(mktemp -d "$base/.$CACHE_SUBDIR.XXXXXX")"
chmod 755 "$work"
trap 'rm -rf "$work"' EXIT
python3 -m pip download --quiet --no-deps --only-binary=:all: \
  --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 \
  --python-version 3.11 --implementation cp --abi cp311 \
  -d "$work" "$WHEEL_REQ"
wheel="$work/$WHEEL_FILE"
got="$(sha256sum "$wheel" | cut -d' ' -f1)"
if [ "$got" != "$WHEEL_SHA256" ]; then
  say "$wheel has sha256 $got, expected $WHEEL_SHA256"; exit 1
fi
python3 -m zipfile -e "$wheel" "$work/wheel"
mv "$work/wheel/$WHEEL_EMBREE" "$work/wheel/$WHEEL_TBB" "$work/"
ln -s "$(basename "$WHEEL_EMBREE")" "$work/libembree4.so"
rm -rf "$work/wheel" "$wheel"
printf '%s\nsha256 %s\n' "$WHEEL_REQ" "$WHEEL_SHA256" >"$work/READY"
if [ ! -e "$dir/READY" ]; then
  rm -rf "$dir"
  mv "$work" "$dir" || [ -e "$dir/READY" ]
fi
printf '%s\n' "$dir"
