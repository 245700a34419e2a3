#!/usr/bin/env python3
"""Issue 39: how long `lifemap maps move` refuses writes, by map size. On loopback, started here
(tests/cluster/test_cluster.py's Cluster: PostgreSQL, two shards, nginx).

  /usr/bin/python3 bench/move_duration.py BUILD_DIR [--visits 1,4,16] [--frames 240] [--rounds 2]

Per size: one synthetic recording of --frames frames (lifemap sim, rooms world, posed; ~66
keyframes) streamed that many times, a visit each, into a new map on shard s1, then the map moved
to s2 and back (--rounds moves in all). The move
prints the elapsed time at each step; writes are refused from its start (the freeze) until the
switch, so "switched" is the window a robot's stream waits (it reconnects and resumes). Prints a
Markdown table and writes JSON beside it.
"""
import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests" / "cluster"))
STEPS = {"drained": r"drained its writes \(([\d.]+) s\)", "exported": r"exported from .*\(([\d.]+) s\)",
         "imported": r"imported into .*\(([\d.]+) s\)", "switched": r"switched: .*\(([\d.]+) s\)",
         "done": r"done: .*\(([\d.]+) s\)"}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("build")
    ap.add_argument("--visits", default="1,4,16")
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default="/tmp/move_duration.json")
    args = ap.parse_args()
    build = Path(args.build).resolve()
    os.environ["LIFEMAPD"] = str(build / "bin/lifemapd")
    os.environ["LIFEMAP"] = str(build / "bin/lifemap")
    os.environ["PATH"] += ":/usr/sbin"
    import test_cluster as tc  # reads LIFEMAPD / LIFEMAP at import

    cluster = tc.Cluster(shards=("s1", "s2"))
    results = []
    try:
        cluster.admin("drain", "s2")  # new maps on s1
        cluster.reload_nginx()
        sim = cluster.folder / "sim"
        tc.run(tc.LIFEMAP, "sim", "--world", "rooms", "--seed", "6", "--visits", "1",
               "--frames", args.frames, "--out", sim)
        for visits in [int(v) for v in args.visits.split(",")]:
            name = f"visits-{visits}"
            cluster.cli("maps", "create", name)
            cluster.reload_nginx()
            for _ in range(visits):
                cluster.cli("stream", name, "--tum", sim / "visit_00", "--use-groundtruth",
                            "--result-images", "none", "--end-visit", timeout=1800)
            info = json.loads(cluster.cli("--json", "maps", "show", name).stdout)
            where = "s1"
            for _ in range(args.rounds):
                to = "s2" if where == "s1" else "s1"
                p = cluster.move(name, to)
                steps = {k: float(m.group(1)) for k, rx in STEPS.items()
                         if (m := re.search(rx, p.stderr))}
                results.append({"visits": visits, "keyframes": int(info.get("keyframe_count", 0)),
                                "stored_bytes": int(info.get("stored_bytes", 0)), "to": to,
                                **steps})
                where = to
                print(json.dumps(results[-1]), file=sys.stderr, flush=True)
    finally:
        cluster.stop()
    Path(args.out).write_text(json.dumps(results, indent=2))
    print("| visits | keyframes | stored | drained s | exported s | imported s | writes refused"
          " (switched) s | done s |")
    print("|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r['visits']} | {r['keyframes']} | {r['stored_bytes'] / 1e6:.1f} MB | "
              f"{r.get('drained', 0):.1f} | {r.get('exported', 0):.1f} | {r.get('imported', 0):.1f}"
              f" | {r.get('switched', 0):.1f} | {r.get('done', 0):.1f} |")


if __name__ == "__main__":
    main()
