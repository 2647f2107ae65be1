#!/usr/bin/env bash
# The measurements of docs/PERFORMANCE.md, section 8: `radiosity factors` (and a Jacobi
# bake) of the 32 x 32 cube (6,144 patches, semi-analytic estimator at its defaults) on
# one process and on 1, 2 and 4 MPI ranks of this machine, the configurations alternating
# within each round, so that a change in the machine's load hits them alike.
#
#   scripts/mpi-bench.sh [ROUNDS] [OUT]     (default 3 rounds, folder bench-out/mpi)
#   MPI_BENCH_CONFIGS="np1-t1 np2 p1-t2" scripts/mpi-bench.sh 5   (some configurations)
#
# Needs the binary built with the feature (`cargo build --release --features mpi`, or
# `./dev mpirun 1 scenes` once; RADIOSITY_BIN names another copy). Writes OUT/runs.csv (one line per run: configuration,
# round, wall and CPU seconds of the whole process tree from /usr/bin/time, peak resident
# memory of the largest process, the `form factors` stage's seconds) and keeps each run's
# summary (with its per-rank table) as OUT/CONFIG-ROUND.txt. Prints the load average
# before and after each round.
set -euo pipefail
cd "$(dirname "$0")/.."
rounds="${1:-3}"
out="${2:-bench-out/mpi}"
bin="${RADIOSITY_BIN:-target/release/radiosity}"
[ -x "$bin" ] || { echo "build first: cargo build --release --features mpi" >&2; exit 1; }
mkdir -p "$out"
if [ "$(id -u)" = 0 ]; then
  export OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1
fi
scene=(cube --max-edge 0.03125)
declare -A cmd=(
  [p1-t1]="$bin factors ${scene[*]} --threads 1"
  [p1-t2]="$bin factors ${scene[*]} --threads 2"
  [np1-t1]="mpirun -np 1 $bin factors ${scene[*]} --threads 1"
  [np2]="mpirun -np 2 $bin factors ${scene[*]}"
  [np2-unbound]="mpirun --bind-to none -np 2 $bin factors ${scene[*]}"
  [np4]="mpirun --oversubscribe -np 4 $bin factors ${scene[*]}"
  [bake-p1-t2]="$bin bake ${scene[*]} --solver jacobi --size 64x64 --threads 2"
  [bake-np2]="mpirun -np 2 $bin bake ${scene[*]} --solver jacobi --size 64x64"
)
order=(${MPI_BENCH_CONFIGS:-np1-t1 np2 p1-t2 np2-unbound p1-t1 np4 bake-p1-t2 bake-np2})
[ -f "$out/runs.csv" ] || echo "config,round,wall_s,user_s,sys_s,max_rss_kb,form_factors_s" >"$out/runs.csv"
for r in $(seq 1 "$rounds"); do
  echo "round $r: load $(cut -d' ' -f1-3 /proc/loadavg)" >&2
  for c in "${order[@]}"; do
    rm -rf "$out/dir-$c"
    /usr/bin/time -f "%e %U %S %M" -o "$out/time.txt" \
      ${cmd[$c]} -o "$out/dir-$c" >"$out/$c-$r.txt" 2>&1
    ff=$(grep -o 'form factors [0-9.]*s' "$out/$c-$r.txt" | head -1 | grep -o '[0-9.]*' || echo "")
    read -r wall user sys rss <"$out/time.txt"
    echo "$c,$r,$wall,$user,$sys,$rss,$ff" | tee -a "$out/runs.csv" >&2
  done
  echo "round $r done: load $(cut -d' ' -f1-3 /proc/loadavg)" >&2
done
rm -rf "$out"/dir-* "$out/time.txt"
