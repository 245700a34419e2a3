#!/bin/bash
# The 20-visit growth figure of retention (issue 36), same run: a place's visits months apart
# (`lifemap sim --world rooms --visits 20`) streamed with their true poses into a fresh lifemapd twice, once
# with retention applied after each visit and once with dry runs only (the baseline), each
# scored by `lifemap eval retention` (bytes, appearance recall, keyframe reply times, changes).
# The simulated visits span years into the future: frames.max_future_s lets their timestamps in.
#
#   bench/retention_growth.sh VISITS_DIR OUT_DIR [CONFIG_MEMBERS [MODES]]
#   (CONFIG_MEMBERS: more sections of the server's config, e.g.
#   '"retention": {"recognised_within_visits": 2}'; MODES default "off on")
#   e.g. lifemap sim --world rooms --seed 8 --visits 20 --frames 90 --conditions scenery,lighting,dynamic \
#          --world building --out /tmp/ret8 && bench/retention_growth.sh /tmp/ret8 /tmp/ret8-out
set -eu
visits=$1 out=$2 members=${3:-} modes=${4:-"off on"}
bin=$(cd "$(dirname "$0")/.." && pwd)/build/bin
mkdir -p "$out"
scratch=$(mktemp -d)
trap 'rm -rf "$scratch"' EXIT
echo "{\"frames\": {\"max_future_s\": 400000000}${members:+, $members}}" > "$scratch/config.json"
for mode in $modes; do
  "$bin/lifemapd" --listen 127.0.0.1:50976 --db "$scratch/db-$mode" --log-level warn \
    --config "$scratch/config.json" > "$out/server-$mode.log" 2>&1 &
  pid=$!
  sleep 1.5
  "$bin/lifemap" --server 127.0.0.1:50976 eval retention --visits "$visits" --retention "$mode" \
    --send compact --out "$out/$mode" 2> "$out/eval-$mode.log" > /dev/null
  kill "$pid"
  wait "$pid" 2> /dev/null || true
done
python3 - "$out" <<'PY'
import json, os, sys
out = sys.argv[1]
for mode in ("off", "on"):
    if not os.path.exists(os.path.join(out, mode, "summary.json")):
        continue
    s = json.load(open(os.path.join(out, mode, "summary.json")))
    c = s["changes"]
    print(f"retention {mode:3}: bytes {s['bytes_first_visit']/1e6:.1f} MB -> "
          f"{s['bytes_last_visit']/1e6:.1f} MB ({s['bytes_ratio']:.2f}x); appearance "
          f"{s['appearance']['right']}/{s['appearance']['queried']} right "
          f"({s['appearance']['recall']:.3f}); keyframe replies p50 {s['keyframe_ms_p50']:.1f} ms "
          f"p95 {s['keyframe_ms_p95']:.1f} ms; changes P {json.dumps(c['precision'])} "
          f"R {json.dumps(c['recall'])}; first-last {json.dumps(s['first_last_changes'])}")
PY
