#!/usr/bin/env python3
"""Issue 39's figures: throughput of 1, 2 and 3 CPU-limited shards behind nginx, and what nginx
adds per frame. Everything on loopback, started here (tests/cluster/test_cluster.py's Cluster).

  /usr/bin/python3 bench/cluster_scaling.py BUILD_DIR [--quota 0.5] [--rounds 2] [--frames 100]

Scaling: k = 1, 2, 3 shards, each in a cgroup of its own limited to --quota of one CPU (so that
more shards means more CPU on a 2-core machine); six maps spread round-robin over the k shards
(6 divides evenly by 1, 2 and 3); the load generator streams to the six maps at once through
nginx (posed frames, compact, no result images, as fast as the shards take them). Per k:
aggregate frames/s.
nginx: one unlimited shard, one stream at 30 Hz and one at the maximum rate, straight to the
shard and through nginx, alternated. Prints a Markdown table and writes JSON beside it.
"""
import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO / "tests" / "cluster"))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("build")
    ap.add_argument("--quota", type=float, default=0.5)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--tum", default=str(REPO.parent / "shared/data/tum_fr1_xyz_subset"))
    ap.add_argument("--out", default="/tmp/cluster_scaling.json")
    args = ap.parse_args()
    build = Path(args.build).resolve()
    os.environ["LIFEMAPD"] = str(build / "bin/lifemapd")
    os.environ["LIFEMAP"] = str(build / "bin/lifemap")
    os.environ["PATH"] += ":/usr/sbin"
    import test_cluster as tc  # reads LIFEMAPD / LIFEMAP at import
    loadgen = build / "bin/load_generator"

    def load(target, maps, streams, rate, frames):
        p = subprocess.run(
            [str(loadgen), "--server", target, "--tum", args.tum, "--streams", str(streams),
             "--maps", ",".join(maps), "--frames", str(frames), "--rate", str(rate), "--send",
             "compact", "--result-images", "none", "--json"],
            capture_output=True, text=True, timeout=1800)
        if p.returncode != 0:
            raise RuntimeError(f"load_generator: {p.stderr[-2000:]}")
        return json.loads(p.stdout)["runs"]

    def place(cluster, maps_by_shard):
        """Creates each map on its shard: the others drained meanwhile."""
        for home, names in maps_by_shard.items():
            for shard in cluster.names:
                cluster.admin("activate" if shard == home else "drain", shard)
            cluster.reload_nginx()
            for name in names:
                cluster.cli("maps", "create", name)
        for shard in cluster.names:
            cluster.admin("activate", shard)
        cluster.reload_nginx()

    results = {"quota": args.quota, "scaling": [], "nginx": []}
    maps = [f"m{i}" for i in range(6)]
    for r in range(args.rounds):
        for k in (1, 2, 3):
            shards = [f"s{i + 1}" for i in range(k)]
            c = tc.Cluster(shards=shards, cpu_quota=args.quota)
            try:
                place(c, {s: [m for j, m in enumerate(maps) if j % k == i]
                          for i, s in enumerate(shards)})
                runs = load(c.target, maps, len(maps), 0, args.frames)
                many = [x for x in runs if x["name"].startswith(f"{len(maps)} stream")][0]
                results["scaling"].append({"round": r, "shards": k, "run": many})
                print(f"round {r} shards {k}: {many['frames_per_s']:.1f} frames/s "
                      f"(p50 {many['latency_ms']['p50']:.0f} ms, errors {many['errors']})",
                      flush=True)
            finally:
                c.stop()
    c = tc.Cluster(shards=["s1"])
    try:
        place(c, {"s1": ["m0"]})
        direct = f"127.0.0.1:{c.ports['s1']}"
        for r in range(args.rounds):
            for way, target in (("direct", direct), ("nginx", c.target)):
                for rate in (30, 0):
                    runs = load(target, ["m0"], 1, rate, args.frames)
                    one = [x for x in runs if x["name"].startswith("1 stream")][0]
                    results["nginx"].append({"round": r, "way": way, "rate": rate, "run": one})
                    print(f"round {r} {way} rate {rate or 'max'}: {one['frames_per_s']:.1f} "
                          f"frames/s, p50 {one['latency_ms']['p50']:.1f} ms, "
                          f"p99 {one['latency_ms']['p99']:.1f} ms", flush=True)
    finally:
        c.stop()
    Path(args.out).write_text(json.dumps(results, indent=1))
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
