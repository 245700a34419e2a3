#!/usr/bin/env bash
# Throughput before and after a change, in the same run (docs/BENCHMARKS.md asks for it on every
# issue): two lifemapd binaries, alternated round by round (the order reversed every other
# round, so a machine that slows down or warms up favours neither), each run on a fresh
# database, the same load generator and frames for both. Prints one table of frames/s and the
# server's CPU ms per frame (GetStats: the server process alone), every round's figure.
#
# Usage: bench/throughput_ab.sh BEFORE_LIFEMAPD AFTER_LIFEMAPD [ROUNDS, default 2] [OUT_DIR]
#   BEFORE: e.g. a worktree of the issue's first commit built with scripts/build:
#     git worktree add /tmp/before REV && (cd /tmp/before && scripts/build)
#     bench/throughput_ab.sh /tmp/before/build/bin/lifemapd build/bin/lifemapd 2
# Needs ../shared/data (the TUM subset; the mOSD subset for the labels' model) and a build of
# this tree (build/bin/load_generator, build/bin/lifemap).
# Runs (the configurations of docs/BENCHMARKS.md "Issue 37"):
#   tracked30: 1 stream at 30 Hz without poses (the server tracks), 150 frames;
#   posed2: 2 streams at the maximum rate, posed, 200 frames each;
#   posed1: 1 stream at the maximum rate, posed, 200 frames.
# Each load generator call runs its own set (keyframes stored with and without labels, and the
# ProcessFrame baseline); all are in the table.
set -euo pipefail
cd "$(dirname "$0")/.."
BEFORE="${1:?usage: bench/throughput_ab.sh BEFORE_LIFEMAPD AFTER_LIFEMAPD [ROUNDS] [OUT_DIR]}"
AFTER="${2:?usage: bench/throughput_ab.sh BEFORE_LIFEMAPD AFTER_LIFEMAPD [ROUNDS] [OUT_DIR]}"
ROUNDS="${3:-2}"
OUT="${4:-$(mktemp -d /tmp/throughput-ab-XXXXXX)}"
DATA="${LIFEMAP_DATA:-../shared/data}"
TUM="$DATA/tum_fr1_xyz_subset"
MOSD="$DATA/pcl_mosd_labeled_subset/learn"
for f in "$BEFORE" "$AFTER" build/bin/load_generator build/bin/lifemap; do
  [ -x "$f" ] || { echo "throughput_ab: $f is not an executable: build it first" >&2; exit 2; }
done
[ -d "$TUM" ] || { echo "throughput_ab: no $TUM (../shared/data)" >&2; exit 2; }
[ -d "$MOSD" ] || { echo "throughput_ab: no $MOSD (../shared/data)" >&2; exit 2; }
mkdir -p "$OUT"
MODEL="$OUT/mosd.model"
if [ ! -s "$MODEL" ]; then
  build/bin/lifemap train --data "$MOSD" --out "$MODEL" > "$OUT/train.log" 2>&1
fi

declare -A ARGS=(
  [tracked30]="--streams 1 --frames 150 --rate 30 --no-poses"
  [posed2]="--streams 2 --frames 200 --rate 0"
  [posed1]="--streams 1 --frames 200 --rate 0"
)
# THROUGHPUT_AB_CONFIGS="tracked30 posed1": only these.
read -r -a CONFIGS <<< "${THROUGHPUT_AB_CONFIGS:-tracked30 posed2 posed1}"

# One run: a fresh lifemapd of binary $2 on a free port, the load generator's JSON into $3.
run_one() {
  local config="$1" binary="$2" out="$3" db port pid
  db="$(mktemp -d "$OUT/db-XXXXXX")"
  port=$(/usr/bin/python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
  "$binary" --listen "127.0.0.1:$port" --db "$db/lifemap.db" --log-level warn \
    > "$out.server.log" 2>&1 &
  pid=$!
  for _ in $(seq 100); do
    if build/bin/lifemap --server "127.0.0.1:$port" --connect-timeout 1 server info \
         > /dev/null 2>&1; then break; fi
    sleep 0.1
  done
  # shellcheck disable=SC2086  # ARGS holds several flags
  build/bin/load_generator --server "127.0.0.1:$port" --tum "$TUM" --send compact \
    --model "$MODEL" --json ${ARGS[$config]} > "$out" 2> "$out.err" || true
  kill -TERM "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  rm -rf "$db"
}

for round in $(seq "$ROUNDS"); do
  order=(before after)
  if (( round % 2 == 0 )); then order=(after before); fi
  for config in "${CONFIGS[@]}"; do
    for which in "${order[@]}"; do
      binary="$BEFORE"
      if [ "$which" = after ]; then binary="$AFTER"; fi
      echo "throughput_ab: round $round, $config, $which" >&2
      run_one "$config" "$binary" "$OUT/$config.$which.r$round.json"
    done
  done
done

/usr/bin/python3 - "$OUT" "$ROUNDS" "${CONFIGS[@]}" <<'EOF'
import json, sys, pathlib
out, rounds, configs = pathlib.Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3:]
def runs(path):
    """The load generator's runs by name; a name that comes again gets " (2)", " (3)"..."""
    try:
        listed = json.loads(path.read_text())["runs"]
    except (OSError, ValueError, KeyError):
        return {}
    named = {}
    for r in listed:
        name, n = r["name"], 2
        while name in named:
            name, n = f"{r['name']} ({n})", n + 1
        named[name] = r
    return named
print("| run | before (r1 / r2 / ...) | after (r1 / r2 / ...) | errors |")
print("|---|---|---|---|")
for config in configs:
    names = []
    for r in range(1, rounds + 1):
        for which in ("before", "after"):
            for n in runs(out / f"{config}.{which}.r{r}.json"):
                if n not in names:
                    names.append(n)
    for name in names:
        cells, errors = [], 0
        for which in ("before", "after"):
            figures = []
            for r in range(1, rounds + 1):
                run = runs(out / f"{config}.{which}.r{r}.json").get(name)
                if run is None:
                    figures.append("failed")
                    continue
                errors += run["errors"]
                cpu = run.get("server_cpu_ms_per_frame")
                figures.append(f"{run['frames_per_s']:.1f} fps, "
                               f"{'?' if cpu is None else f'{cpu:.1f}'} ms")
            cells.append(" / ".join(figures))
        print(f"| {config}: {name} | {cells[0]} | {cells[1]} | {errors} |")
print(f"\n(raw JSON and logs: {out})", file=sys.stderr)
EOF
