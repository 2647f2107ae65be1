#!/bin/sh
# Remakes docs/suite/: exports the suite, runs this program's estimators and the peers on it,
# scores each and draws the board (docs/suite/board.md, .svg, .png). Not a test; takes
# minutes. Usage: scripts/suite-board.sh [WORKDIR]   (from the repository root)
set -eu
work="${1:-$(mktemp -d)}"
out=docs/suite
mkdir -p "$out" "$work"
cargo build --release --quiet
rm -f "$out"/*.json
bin=target/release/radiosity
$bin suite export "$work/suite"
score() { # name command-description score-args...
    name=$1; shift; what=$1; shift
    $bin suite score --suite "$work/suite" --tool "$name" --command "$what" \
        --json "$out/$(echo "$name" | tr ' /=' '___').json" "$@" > "$work/$(echo "$name" | tr ' /=' '___').txt"
    tail -n 14 "$work/$(echo "$name" | tr ' /=' '___').txt"
}
run() { # name run-args...
    name=$1; shift
    $bin suite run --suite "$work/suite" -o "$work/$name" "$@" > /dev/null
}
run semi
score "radiosity semi (default)" "radiosity suite run -o semi" --factors "$work/semi"
run semi-tight --tol 1e-9 --samples 8 --rays 8 --replicates 8
score "radiosity semi --tol 1e-9 --samples 8 --rays 8 --replicates 8" \
    "radiosity suite run -o semi-tight --tol 1e-9 --samples 8 --rays 8 --replicates 8" --factors "$work/semi-tight"
run stratified --estimator stratified --samples 16 --replicates 16
score "radiosity stratified 16x16x16" "radiosity suite run -o stratified --estimator stratified --samples 16 --replicates 16" \
    --factors "$work/stratified"
run hemisphere --estimator hemisphere --samples 64 --replicates 16
score "radiosity hemisphere 64x64x16" "radiosity suite run -o hemisphere --estimator hemisphere --samples 64 --replicates 16" \
    --factors "$work/hemisphere"
export PEERS_VENV="$work/venv"
scripts/suite-peers.sh pyviewfactor --suite "$work/suite" -o "$work/pyviewfactor" > /dev/null
score "pyViewFactor 1.1.0" "scripts/suite-peers.sh pyviewfactor -o pyviewfactor" --matrix "$work/pyviewfactor"
scripts/suite-peers.sh raystrack --suite "$work/suite" -o "$work/raystrack.csv" > /dev/null
score "raystrack 2.0.0 (4x4 cells x 16 rays x 4 replicates)" "scripts/suite-peers.sh raystrack -o raystrack.csv" \
    --csv "$work/raystrack.csv"
scripts/suite-peers.sh radiance --suite "$work/suite" -o "$work/radiance.csv" --rays 100000 > /dev/null
score "Radiance rfluxmtx -c 100000" "scripts/suite-peers.sh radiance -o radiance.csv --rays 100000" \
    --csv "$work/radiance.csv"
$bin suite board -o "$out/board" "$out"/*.json
