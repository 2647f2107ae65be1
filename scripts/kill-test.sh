#!/usr/bin/env bash
# kill -9 at random points of N bakes and N `factors` runs (half of them anywhere in the
# run, half near its end, where the files are written), each into the same folder as the
# run before it, and check after every kill that the folder is whole and from one run:
# absent, or holding exactly the files its manifest.json lists, each with the size and
# SHA-256 listed there (and, for a factors folder, the SHA-256 that provenance.json
# records). Runs alternate seeds, so files of two runs differ. At the end one more run of
# each must succeed and leave no temporary sibling behind. Then N/5 pairs of runs of each
# kind are started together into one folder: both must succeed, leaving one whole folder.
#
#   scripts/kill-test.sh [N]        (default 50; RADIOSITY_BIN picks the binary,
#                                    default target/release/radiosity, else target/debug)
#
# Prints one line per kind: trials, how many kills left the previous folder, the new one or
# none (killed between the two renames), and the number of bad folders (must be 0).
set -euo pipefail
cd "$(dirname "$0")/.."
n="${1:-50}"
bin="${RADIOSITY_BIN:-}"
if [ -z "$bin" ]; then
  for b in target/release/radiosity target/debug/radiosity; do
    [ -x "$b" ] && { bin="$b"; break; }
  done
fi
[ -x "$bin" ] || { echo "kill-test: no radiosity binary (build it or set RADIOSITY_BIN)" >&2; exit 2; }
work="$(mktemp -d "${TMPDIR:-/tmp}/radiosity-kill.XXXXXX")"
trap 'rm -rf "$work"' EXIT

# verify DIR KIND: prints `absent` or the run id, or fails naming what is wrong.
verify() {
  python3 - "$1" "$2" <<'PY'
import hashlib, json, os, sys
d, kind = sys.argv[1], sys.argv[2]
if not os.path.exists(d):
    print("absent"); sys.exit(0)
m = json.load(open(os.path.join(d, "manifest.json")))
assert m["kind"] == kind, f"kind {m['kind']}"
listed = {f["name"]: f for f in m["files"]}
present = set(os.listdir(d)) - {"manifest.json"}
assert present == set(listed), f"files {sorted(present)} but manifest lists {sorted(listed)}"
for name, f in listed.items():
    data = open(os.path.join(d, name), "rb").read()
    assert len(data) == f["bytes"] and hashlib.sha256(data).hexdigest() == f["sha256"], name
if kind == "factors":
    p = json.load(open(os.path.join(d, "provenance.json")))
    for name, h in p["sha256"].items():
        assert hashlib.sha256(open(os.path.join(d, name), "rb").read()).hexdigest() == h, name
print(m["run"])
PY
}

# trials KIND ARGS...: N kill -9 trials of `radiosity ARGS... --seed K -o DIR`.
trials() {
  local kind="$1"; shift
  local dir="$work/$kind"
  # One run to time it and to start from a whole folder.
  local t0 t1
  t0=$(date +%s%N)
  "$bin" "$@" --seed 1 -o "$dir" >/dev/null 2>&1
  t1=$(date +%s%N)
  local ms=$(( (t1 - t0) / 1000000 + 1 ))
  local old new none bad prev now writing
  old=0; new=0; none=0; bad=0; writing=0
  prev="$(verify "$dir" "$kind")"
  for k in $(seq 1 "$n"); do
    "$bin" "$@" --seed $((k + 1)) -o "$dir" >/dev/null 2>&1 &
    local pid=$!
    # A random point: odd trials anywhere in the run (up to 1.2 times its measured length),
    # even ones in its last part (0.8 to 1.2 times), where the files are written.
    local lo=0
    [ $((k % 2)) = 0 ] && lo=0.8
    sleep "$(awk -v r="$RANDOM" -v ms="$ms" -v lo="$lo" \
      'BEGIN { printf "%.3f", (lo + r / 32768 * (1.2 - lo)) * ms / 1000 }')"
    kill -9 "$pid" 2>/dev/null || true
    wait "$pid" 2>/dev/null || true
    # Killed while writing: its temporary folder is still there.
    if [ -n "$(find "$work" -maxdepth 1 -name ".$kind.radiosity-*.$pid.*" -print -quit)" ]; then
      writing=$((writing + 1))
    fi
    if now="$(verify "$dir" "$kind" 2>&1)"; then
      if [ "$now" = absent ]; then none=$((none + 1))
      elif [ "$now" = "$prev" ]; then old=$((old + 1))
      else new=$((new + 1)); prev="$now"; fi
    else
      bad=$((bad + 1)); echo "kill-test: $kind trial $k: $now" >&2
    fi
    # Start the next trial from a whole folder again if this one left none.
    if [ "$now" = absent ]; then
      "$bin" "$@" --seed 1 -o "$dir" >/dev/null 2>&1
      prev="$(verify "$dir" "$kind")"
    fi
  done
  # A last run must succeed and clean the temporaries of the killed ones.
  "$bin" "$@" --seed 1 -o "$dir" >/dev/null 2>&1
  verify "$dir" "$kind" >/dev/null
  local stale
  stale=$(find "$work" -maxdepth 1 -name ".$kind.radiosity-*" | wc -l)
  echo "$kind: $n kills at random points of a ${ms} ms run ($writing while writing the" \
       "folder): previous folder kept $old, new folder $new, no folder $none; bad folders" \
       "$bad; temporaries left after the next run $stale"
  [ "$bad" = 0 ] && [ "$stale" = 0 ]
}

# concurrent KIND ARGS...: N/5 pairs of runs started together into one folder; both must
# succeed and leave a whole folder of one of them.
concurrent() {
  local kind="$1"; shift
  local dir="$work/$kind-concurrent" bad=0 k pairs=$(( (n + 4) / 5 ))
  for k in $(seq 1 "$pairs"); do
    "$bin" "$@" --seed $((2 * k)) -o "$dir" >/dev/null 2>&1 & local a=$!
    "$bin" "$@" --seed $((2 * k + 1)) -o "$dir" >/dev/null 2>&1 & local b=$!
    local ok=1
    wait "$a" || ok=0
    wait "$b" || ok=0
    if [ "$ok" = 0 ] || ! verify "$dir" "$kind" >/dev/null; then
      bad=$((bad + 1)); echo "kill-test: $kind concurrent pair $k failed" >&2
    fi
  done
  echo "$kind: $pairs pairs of concurrent runs into one folder; bad $bad"
  [ "$bad" = 0 ]
}

status=0
# Runs whose writing takes a good part of their time, so that the late kills land in it:
# a large preview (rendered and encoded inside the folder being written), and a
# hemisphere matrix with many entries per row (F.mtx and stderr.mtx of 16 and 18 MB).
trials bake bake cornell --patches 300 --size 2048x2048 || status=1
trials factors factors cornell --patches 2000 --estimator hemisphere --samples 16 \
  --replicates 4 || status=1
concurrent bake bake cornell --patches 300 --size 64x64 || status=1
concurrent factors factors cornell --patches 300 || status=1
exit $status
