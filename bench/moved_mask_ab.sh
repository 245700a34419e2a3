#!/bin/bash
# The per-frame moved mask's cost at the server (issue 36), same run: a recording's reference
# visit streamed with its ground-truth poses and ended, then a later visit of the same place
# streamed twice, into a fresh lifemapd with changes.moved_enabled true and false, alternating.
# Prints the streams' frames per second per setting.
#
#   bench/moved_mask_ab.sh REFERENCE_DIR LATER_DIR [ROUNDS]
#   e.g. (a suite from `lifemap sim suite --seed 11 --places 2 --frames 150 --world rooms`):
#   bench/moved_mask_ab.sh SUITE/place_00/reference SUITE/place_00/subset5_scenery 3
set -eu
ref=$1 later=$2 rounds=${3:-3}
bin=$(cd "$(dirname "$0")/.." && pwd)/build/bin
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
echo '{"changes": {"moved_enabled": false}}' > "$out/off.json"
echo '{}' > "$out/on.json"
L="$bin/lifemap --server 127.0.0.1:50975"
for r in $(seq 1 "$rounds"); do
  for cfg in on off; do
    "$bin/lifemapd" --listen 127.0.0.1:50975 --db "$out/db-$cfg-$r" --log-level warn \
      --config "$out/$cfg.json" > /dev/null 2>&1 &
    pid=$!
    sleep 1.5
    $L maps create m > /dev/null
    $L stream m --tum "$ref" --use-groundtruth --end-visit --rate 0 --send compact \
      > /dev/null 2>&1
    for k in 1 2; do
      $L --json stream m --tum "$later" --use-groundtruth --end-visit --rate 0 \
        --send compact 2> /dev/null | tail -1 > "$out/$cfg-$r-$k.json"
    done
    kill "$pid"
    wait "$pid" 2> /dev/null || true
  done
done
python3 - "$out" <<'PY'
import glob, json, os, sys
rows = {}
for f in sorted(glob.glob(os.path.join(sys.argv[1], '*-*-*.json'))):
    cfg = os.path.basename(f).split('-')[0]
    rows.setdefault(cfg, []).append(json.load(open(f))['summary']['frames_per_s'])
for cfg in ('on', 'off'):
    print('moved mask %-3s fps:' % cfg, ', '.join('%.1f' % x for x in rows.get(cfg, [])))
PY
