"""Several lifemapd behind nginx, maps placed in PostgreSQL (issue 39), all on loopback.

ctest runs each test as Cluster.<name> (scripts/test-cluster BUILD NAME). Environment: LIFEMAPD
and LIFEMAP (the built binaries). Started by the test, in a temporary folder, on free ports: a
PostgreSQL cluster (initdb; as root its programs run as the `postgres` user, which refuses
root), three shards and nginx (`nginx -p DIR -c FILE`, the table written by
`lifemap admin shards nginx-config`). Robots are `lifemap stream` replaying a synthetic place
(`lifemap sim`) through nginx.
"""
import json
import shlex
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import unittest
from pathlib import Path

LIFEMAPD = os.environ.get("LIFEMAPD", "lifemapd")
LIFEMAP = os.environ.get("LIFEMAP", "lifemap")
PG_BIN = Path("/usr/lib/postgresql/15/bin")
NGINX = shutil.which("nginx") or "/usr/sbin/nginx"
SHARDS = ("s1", "s2", "s3")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, timeout=30.0, process=None, what="server"):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if process is not None and process.poll() is not None:
            raise RuntimeError(f"{what} exited with {process.returncode}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.05)
    raise RuntimeError(f"{what} did not listen on {port} within {timeout} s")


def run(*args, check=True, timeout=300):
    p = subprocess.run([str(a) for a in args], capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, args))} exited {p.returncode}:\n"
                             f"{p.stdout}\n{p.stderr}")
    return p


class PostgreSQL:
    """A throw-away PostgreSQL 15 cluster on a free port, trust authentication on loopback."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.port = free_port()
        folder.mkdir(parents=True, exist_ok=True)
        self.as_postgres = []
        if os.geteuid() == 0:  # initdb and postgres refuse to run as root
            shutil.chown(folder, "postgres", "postgres")
            self.as_postgres = ["runuser", "-u", "postgres", "--"]
        data = folder / "data"
        run(*self.as_postgres, PG_BIN / "initdb", "-D", data, "-U", "lifemap", "--auth=trust",
            "-E", "UTF8", "--no-sync")
        self.log = open(folder.parent / "postgres.log", "w")
        self.process = subprocess.Popen(
            [*self.as_postgres, str(PG_BIN / "postgres"), "-D", str(data), "-p", str(self.port),
             "-k", str(folder), "-c", "listen_addresses=127.0.0.1", "-c", "fsync=off"],
            stdout=self.log, stderr=subprocess.STDOUT)
        wait_port(self.port, process=self.process, what="postgres")
        self.uri = f"postgresql://lifemap@127.0.0.1:{self.port}/postgres"

    def stop(self):
        if self.process.poll() is None:
            run(*self.as_postgres, PG_BIN / "pg_ctl", "stop", "-D", self.folder / "data", "-m",
                "fast", check=False)
            self.process.wait(30)
        self.log.close()


class Cluster:
    """PostgreSQL, shards and nginx, until stop(). `cpu_quota`: each shard's share of one CPU
    (a cgroup v1 cfs quota; bench/cluster_scaling.py), None = unlimited."""

    def __init__(self, shards=SHARDS, cpu_quota=None, keys=False):
        self.names = tuple(shards)
        self.cpu_quota = cpu_quota
        self.cgroups = []
        self.folder = Path(tempfile.mkdtemp(prefix="lifemap-cluster-"))
        self.folder.chmod(0o755)  # the postgres user reaches its folder inside
        self.shards = {}
        self.nginx = None
        # With keys: every shard requires them; the first admin key is made on the first
        # shard's machine only (the others get it from the cluster's key ring).
        self.admin_key = None
        if keys:
            self.admin_key = self.folder / "admin.key"
            made = run(LIFEMAPD, "keys", "create", "admin", "--role", "admin", "--db",
                       self.folder / f"{self.names[0]}.db", "--create")
            self.admin_key.write_text(made.stdout)
        self.pg = PostgreSQL(self.folder / "pg")
        try:
            self.start()
        except BaseException:
            print(self.logs(), file=sys.stderr)
            self.stop()
            raise

    def start(self):
        self.ports = {name: free_port() for name in self.names}
        for name in self.names:
            self.admin("add", name, f"127.0.0.1:{self.ports[name]}")
        for name in self.names:
            self.start_shard(name)
        self.nginx_port = free_port()
        self.nginx_dir = self.folder / "nginx"
        self.nginx_dir.mkdir()
        self.write_nginx_table()
        self.start_nginx()
        self.target = f"127.0.0.1:{self.nginx_port}"

    def admin(self, *args, check=True):
        return run(LIFEMAP, "admin", "shards", "--placement", self.pg.uri, *args, check=check)

    def limit_cpu(self, pid, name):
        """Puts the process in a cgroup of its own with `cpu_quota` of one CPU."""
        group = Path(f"/sys/fs/cgroup/cpu/lifemap-{os.getpid()}-{name}")
        group.mkdir(exist_ok=True)
        (group / "cpu.cfs_period_us").write_text("100000")
        (group / "cpu.cfs_quota_us").write_text(str(int(self.cpu_quota * 100000)))
        (group / "cgroup.procs").write_text(str(pid))
        self.cgroups.append(group)

    def start_shard(self, name):
        with open(self.folder / f"{name}.log", "a") as err:
            p = subprocess.Popen(
                [LIFEMAPD, "--db", str(self.folder / f"{name}.db"), "--listen",
                 f"127.0.0.1:{self.ports[name]}", "--placement", self.pg.uri, "--shard", name,
                 "--log-level", "info", "--shutdown-grace-s", "5",
                 *(["--require-auth"] if self.admin_key else [])],
                stdout=subprocess.DEVNULL, stderr=err)
        if self.cpu_quota is not None:
            self.limit_cpu(p.pid, name)
        wait_port(self.ports[name], process=p, what=f"shard {name}")
        self.shards[name] = p

    def kill_shard(self, name):
        p = self.shards.pop(name)
        p.kill()
        p.wait(30)

    def write_nginx_table(self):
        self.admin("nginx-config", "--listen", f"127.0.0.1:{self.nginx_port}", "--prefix",
                   self.nginx_dir, "--out", self.nginx_dir / "nginx.conf")

    def start_nginx(self):
        with open(self.nginx_dir / "stderr.log", "a") as err:
            self.nginx = subprocess.Popen(
                [NGINX, "-p", str(self.nginx_dir), "-c", str(self.nginx_dir / "nginx.conf"), "-e",
                 str(self.nginx_dir / "error.log"), "-g", "daemon off;"],
                stdout=subprocess.DEVNULL, stderr=err)
        wait_port(self.nginx_port, process=self.nginx, what="nginx")

    def reload_nginx(self):
        self.write_nginx_table()
        run(NGINX, "-p", self.nginx_dir, "-c", self.nginx_dir / "nginx.conf", "-e",
            self.nginx_dir / "error.log", "-s", "reload")
        time.sleep(0.5)  # the new workers take over

    def reload_command(self):
        """What `maps move --reload-command` runs: the table written again, nginx reloaded."""
        nginx = shlex.join([NGINX, "-p", str(self.nginx_dir), "-c",
                            str(self.nginx_dir / "nginx.conf"), "-e",
                            str(self.nginx_dir / "error.log"), "-s", "reload"])
        return shlex.join([LIFEMAP, "admin", "shards", "--placement", self.pg.uri, "nginx-config",
                           "--listen", f"127.0.0.1:{self.nginx_port}", "--prefix",
                           str(self.nginx_dir), "--out", str(self.nginx_dir / "nginx.conf"),
                           "--reload-command", nginx])

    def move(self, name, to, *extra, stop_after=None, check=True):
        env = dict(os.environ)
        if stop_after:
            env["LIFEMAP_MOVE_STOP_AFTER"] = stop_after
        p = subprocess.run([LIFEMAP, *self.key_args(), "maps", "move", name, "--to", to,
                            "--placement", self.pg.uri,
                            "--reload-command", self.reload_command(), *extra],
                           capture_output=True, text=True, timeout=300, env=env)
        if check and p.returncode != 0:
            raise AssertionError(f"maps move {name} --to {to} exited {p.returncode}:\n"
                                 f"{p.stdout}\n{p.stderr}\n{self.logs()}")
        if p.returncode == 0 and not stop_after:
            self.wait_routed(name)
        return p

    def wait_routed(self, name, timeout_s=10):
        """Until nginx's new workers route `name` to where it lives: `nginx -s reload` returns
        before the old workers, with the old table, stop taking calls (their answer is a true
        UNAVAILABLE "retry"; the test_11 that followed a move got one)."""
        deadline = time.time() + timeout_s
        while True:
            w = self.cli("maps", "show", name, check=False, timeout=60)
            if w.returncode == 0 or "older than the placement" not in w.stderr:
                return
            if time.time() > deadline:
                raise AssertionError(f"nginx still routes '{name}' by its old table after "
                                     f"{timeout_s} s:\n{w.stderr}")
            time.sleep(0.2)

    def move_state(self, name):
        out = run(PG_BIN / "psql", "-At", "-h", "127.0.0.1", "-p", self.pg.port, "-U", "lifemap",
                  "-d", "postgres", "-c",
                  f"SELECT shard, state, coalesce(move_phase, '') FROM lifemap_maps "
                  f"WHERE name = '{name}'").stdout.strip()
        return tuple(out.split("|"))

    def stop_nginx(self):
        if self.nginx is not None and self.nginx.poll() is None:
            self.nginx.send_signal(signal.SIGQUIT)  # graceful: lets running requests finish
            try:
                self.nginx.wait(5)
            except subprocess.TimeoutExpired:
                self.nginx.kill()
                self.nginx.wait()

    def key_args(self, key=None):
        """The CLI's key flag: `key` (a file), else the admin key of a cluster with keys."""
        key = key or self.admin_key
        return ["--api-key-file", str(key)] if key else []

    def cli(self, *args, target=None, check=True, timeout=300, key=None):
        return run(LIFEMAP, "--server", target or self.target, *self.key_args(key), *args,
                   check=check, timeout=timeout)

    def placement(self):
        """{map: shard} as the placement database has it."""
        out = run(PG_BIN / "psql", "-At", "-h", "127.0.0.1", "-p", self.pg.port, "-U", "lifemap",
                  "-d", "postgres", "-c", "SELECT name, shard FROM lifemap_maps").stdout
        return dict(line.split("|", 1) for line in out.splitlines() if line)

    def stop(self):
        self.stop_nginx()
        for p in self.shards.values():
            p.send_signal(signal.SIGTERM)
        for p in self.shards.values():
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                p.kill()
        self.pg.stop()
        for group in self.cgroups:
            try:
                group.rmdir()
            except OSError:
                pass

    def logs(self):
        text = []
        for f in sorted(self.folder.glob("*.log")) + sorted(self.folder.glob("nginx/*.log")):
            text.append(f"--- {f.name}\n{f.read_text()[-3000:]}")
        return "\n".join(text)


# Maps created on each shard (the others drained meanwhile, so that nginx's hash has one choice).
HOMES = {"s1": ["lab", "hall"], "s2": ["office", "kitchen"], "s3": ["garage", "atrium"]}
MAPS = [m for names in HOMES.values() for m in names]


class ClusterCase(unittest.TestCase):
    """A test class over one Cluster (made by setUpClass as cls.cluster), stopped at its end."""

    @classmethod
    def tearDownClass(cls):
        cls.cluster.stop()
        if os.environ.get("KEEP") is None:
            shutil.rmtree(cls.cluster.folder, ignore_errors=True)

    def setUp(self):
        self.c = self.cluster

    def fail_with_logs(self, message):
        self.fail(f"{message}\n{self.c.logs()}")

    def direct(self, shard):
        return f"127.0.0.1:{self.c.ports[shard]}"


class ClusterTest(ClusterCase):
    @classmethod
    def setUpClass(cls):
        cls.cluster = Cluster()
        cls.sim = cls.cluster.folder / "sim"
        run(LIFEMAP, "sim", "--world", "rooms", "--seed", "6", "--place-shape", "rect", "--visits",
            "1", "--frames", "60", "--out", cls.sim)

    def ensure_maps(self):
        """Every map of HOMES on its shard: each shard in turn the only active one."""
        placed = self.c.placement()
        if all(placed.get(m) == shard for shard, names in HOMES.items() for m in names):
            return placed
        try:
            for home, names in HOMES.items():
                for shard in SHARDS:
                    self.c.admin("activate" if shard == home else "drain", shard)
                self.c.reload_nginx()
                for name in names:
                    if name not in placed:
                        self.c.cli("maps", "create", name)
        finally:
            for shard in SHARDS:
                self.c.admin("activate", shard)
            self.c.reload_nginx()
        return self.c.placement()

    def stream(self, name, *extra, check=True, frames=30):
        return self.c.cli("--json", "stream", name, "--tum", self.sim / "visit_00",
                          "--use-groundtruth", "--max-frames", frames, "--result-images", "none",
                          "--reconnect-s", "60", *extra, check=check)

    def map_on(self, placed, shard):
        return next(m for m in MAPS if placed[m] == shard)

    def test_01_new_maps_are_placed_over_the_shards_and_listed_through_nginx(self):
        placed = self.ensure_maps()
        self.assertEqual({m: s for s, names in HOMES.items() for m in names},
                         {m: placed[m] for m in MAPS})
        # With every shard active, nginx's consistent hash spreads new maps (12 names all on one
        # shard of three: p = 3^-11).
        spread = [f"spread-{i}" for i in range(12)]
        for name in spread:
            self.c.cli("maps", "create", name)
        placed = self.c.placement()
        self.assertGreaterEqual(len({placed[m] for m in spread}), 2, placed)
        for name in spread:
            self.c.cli("maps", "delete", name, "--yes")
        self.assertFalse(set(spread) & set(self.c.placement()), "deleted maps stay placed")
        # Each map is held by its shard's own database and nowhere else.
        for shard in SHARDS:
            direct = f"127.0.0.1:{self.c.ports[shard]}"
            out = json.loads(self.c.cli("--json", "maps", "list", target=direct).stdout)
            held = sorted(m["name"] for m in out.get("maps", []))
            self.assertEqual(sorted(HOMES[shard]), held)
        # Through nginx, the client fans ListMaps out to every shard and merges.
        out = json.loads(self.c.cli("--json", "maps", "list").stdout)
        self.assertEqual(sorted(MAPS), sorted(m["name"] for m in out["maps"]))
        # Names are unique over the cluster, ignoring case, whichever shard the call reaches.
        dup = self.c.cli("maps", "create", "LAB", check=False)
        self.assertNotEqual(0, dup.returncode)
        self.assertIn(f"exists on shard '{placed['lab']}'", dup.stderr)

    def test_02_robots_stream_to_maps_on_different_shards_at_once(self):
        placed = self.ensure_maps()
        self.c.reload_nginx()  # every placed map pinned by name
        targets = [self.map_on(placed, s) for s in SHARDS]
        outs = {}

        def robot(name):
            outs[name] = self.stream(name, "--robot", f"robot-{name}", check=False)

        threads = [threading.Thread(target=robot, args=(m,)) for m in targets]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        for name in targets:
            p = outs[name]
            if p.returncode != 0:
                self.fail_with_logs(f"stream into {name} failed: {p.stderr}")
            summary = json.loads(p.stdout.strip().splitlines()[-1])["summary"]
            committed = int(summary["keyframes_stored"])
            self.assertGreater(committed, 0, summary)
            # The keyframes are on the map's own shard, as acknowledged.
            direct = f"127.0.0.1:{self.c.ports[placed[name]]}"
            info = json.loads(self.c.cli("--json", "maps", "show", name, target=direct).stdout)
            self.assertGreaterEqual(int(info["keyframe_count"]), committed)
        # Calls over every map are fanned out by the client library and merged. GetStats: the
        # shards' sums.
        merged = json.loads(self.c.cli("--json", "admin", "stats").stdout)
        alone = [json.loads(self.c.cli("--json", "admin", "stats", target=self.direct(s)).stdout)
                 for s in SHARDS]
        for field in ("maps", "keyframes"):
            self.assertEqual(sum(int(a.get(field, 0)) for a in alone), int(merged[field]),
                             (field, merged, alone))
        # QueryPlace by frames: every shard's ranking, merged by score; the three maps hold a
        # visit of this very recording, one map per shard.
        q = json.loads(self.c.cli("--json", "places", "query", "--tum", self.sim / "visit_00",
                                  "--method", "architecture", "--max", "10").stdout)
        found = {m["map"] for m in q.get("matches", [])}
        self.assertGreaterEqual(len(found & set(targets)), 2, q)
        scores = [float(m.get("score", 0)) for m in q.get("matches", [])]
        self.assertEqual(sorted(scores, reverse=True), scores, q)

    def test_03_a_shard_asked_about_another_shards_map_says_where_it_lives(self):
        placed = self.ensure_maps()
        name = self.map_on(placed, "s2")
        wrong = f"127.0.0.1:{self.c.ports['s1']}"
        p = self.c.cli("maps", "show", name, target=wrong, check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn(f"lives on shard 's2' (127.0.0.1:{self.c.ports['s2']})", p.stderr)
        # The same call sent by nginx (a table older than the placement, as right after a move
        # while nginx's old workers still serve open connections): UNAVAILABLE, so the client
        # retries (the stream's reconnection did not, CI stop 49).
        try:
            import grpc
            from lifemap.v1 import map_service_pb2 as map_pb
            from lifemap.v1 import map_service_pb2_grpc as map_grpc
        except ImportError:
            self.skipTest("the Python client is not installed (scripts/test-cluster installs it)")
        with grpc.insecure_channel(wrong) as channel:
            with self.assertRaises(grpc.RpcError) as refused:
                map_grpc.MapServiceStub(channel).GetMap(
                    map_pb.GetMapRequest(name=name),
                    metadata=[("lifemap-map", name), ("lifemap-routed-by", "nginx")], timeout=10)
        self.assertEqual(grpc.StatusCode.UNAVAILABLE, refused.exception.code())
        self.assertIn("nginx's table is older than the placement", refused.exception.details())
        self.assertIn(f"lives on shard 's2' (127.0.0.1:{self.c.ports['s2']})",
                      refused.exception.details())

    def test_04_a_killed_shard_answers_unavailable_naming_it_and_the_others_go_on(self):
        placed = self.ensure_maps()
        self.c.reload_nginx()
        down = self.map_on(placed, "s3")
        up = self.map_on(placed, "s1")
        self.c.kill_shard("s3")
        killed_at = time.time()
        try:
            p = self.c.cli("maps", "show", down, check=False)
            self.assertNotEqual(0, p.returncode)
            self.assertIn("shard s3", p.stderr)
            self.assertIn("unreachable", p.stderr)
            self.assertIn("UNAVAILABLE", p.stderr.upper())
            self.c.cli("maps", "show", up)
            streamed = self.stream(up, "--robot", "robot-while-s3-is-down", check=False)
            if streamed.returncode != 0:
                self.fail_with_logs(f"a map on s1 failed while s3 was down: {streamed.stderr}")
            listed = json.loads(self.c.cli("--json", "maps", "list").stdout)
            self.assertTrue(any(u.startswith("s3") for u in listed.get("unreachable_shards", [])), listed)
            self.assertNotIn(down, [m["name"] for m in listed["maps"]])
            # A move to a shard the placement reports down (no heartbeat for 10 s) is refused
            # before anything changes.
            time.sleep(max(0.0, killed_at + 11.0 - time.time()))
            moved = self.c.move(up, "s3", check=False)
            self.assertNotEqual(0, moved.returncode)
            self.assertIn("shard 's3'", moved.stderr)
            self.assertIn("is down", moved.stderr)
            self.assertEqual(("s1", "active", ""), self.c.move_state(up))
        finally:
            self.c.start_shard("s3")
        self.c.cli("maps", "show", down)

    def test_05_nginx_restarted_while_nothing_streams_comes_back_with_its_table(self):
        placed = self.ensure_maps()
        self.c.stop_nginx()
        p = self.c.cli("--connect-timeout", "1", "maps", "show", "lab", check=False)
        self.assertNotEqual(0, p.returncode)
        self.c.start_nginx()
        for name in MAPS:
            self.c.cli("maps", "show", name)
        self.assertEqual(placed, self.c.placement())

    def keyframes(self, name, target=None):
        out = json.loads(self.c.cli("--json", "keyframes", "list", name, target=target).stdout)
        return sorted(int(k["id"]) for k in out.get("keyframes", []))

    def visits(self, name, target=None):
        out = json.loads(self.c.cli("--json", "visits", "list", name, target=target).stdout)
        return sorted((int(v["id"]), v.get("ended", False)) for v in out.get("visits", []))

    def shard_of(self, name):
        return self.c.placement()[name]

    def test_06_a_map_moves_while_idle_and_keeps_its_ids(self):
        placed = self.ensure_maps()
        name = HOMES["s1"][1]  # hall
        source = placed[name]
        self.stream(name, "--robot", "before-the-move", "--end-visit")
        keyframes, visits = self.keyframes(name), self.visits(name)
        self.assertTrue(keyframes)
        target = "s2" if source != "s2" else "s3"
        self.c.move(name, target)
        self.assertEqual((target, "active", ""), self.c.move_state(name))
        # Through nginx: the same visits and keyframes, with the same ids, on the target alone.
        self.assertEqual(keyframes, self.keyframes(name))
        self.assertEqual(visits, self.visits(name))
        self.assertEqual(keyframes, self.keyframes(name, target=self.direct(target)))
        held = json.loads(self.c.cli("--json", "maps", "list", target=self.direct(source)).stdout)
        self.assertNotIn(name, [m["name"] for m in held.get("maps", [])])
        # New visits go on where it lives now; its ids come from the target's range.
        self.stream(name, "--robot", "after-the-move", "--end-visit")
        self.assertGreater(len(self.keyframes(name)), len(keyframes))
        self.c.move(name, source)  # and back home
        self.assertEqual(source, self.shard_of(name))

    def test_07_a_map_moves_while_a_robot_streams_to_it_and_loses_nothing(self):
        placed = self.ensure_maps()
        name = HOMES["s2"][1]  # kitchen
        source = placed[name]
        target = "s3" if source != "s3" else "s1"
        out = {}

        def robot():
            out["p"] = self.stream(name, "--robot", "moving-robot", "--rate", "6", "--end-visit",
                                   check=False, frames=60)

        t = threading.Thread(target=robot)
        t.start()
        deadline = time.time() + 60
        while time.time() < deadline:  # some keyframes stored before the move
            info = json.loads(self.c.cli("--json", "maps", "show", name).stdout)
            if int(info.get("keyframe_count", 0)) >= 2:
                break
            time.sleep(0.2)
        self.c.move(name, target)
        t.join()
        p = out["p"]
        if p.returncode != 0:
            self.fail_with_logs(f"the stream did not survive the move: {p.stdout[-2000:]}\n"
                                f"{p.stderr}")
        summary = json.loads(p.stdout.strip().splitlines()[-1])["summary"]
        self.assertGreaterEqual(int(summary["reconnections"]), 1, summary)
        self.assertEqual(60, int(summary["results"]), summary)
        acknowledged = {int(k) for k in summary["keyframe_ids"]}
        stored = set(self.keyframes(name, target=self.direct(target)))
        self.assertTrue(acknowledged, summary)
        self.assertFalse(acknowledged - stored,
                         f"acknowledged keyframes missing on the target: "
                         f"{sorted(acknowledged - stored)}")
        self.assertEqual((target, "active", ""), self.c.move_state(name))
        self.c.move(name, source)

    def test_08_two_moves_of_one_map_at_once_the_second_is_refused(self):
        self.ensure_maps()
        name = HOMES["s3"][0]  # garage
        # A move running elsewhere holds the map's lock: a session holding it stands in for it.
        holder = subprocess.Popen(
            [str(PG_BIN / "psql"), "-h", "127.0.0.1", "-p", str(self.c.pg.port), "-U", "lifemap",
             "-d", "postgres", "-c",
             f"SELECT pg_advisory_lock(hashtext('lifemap-move:{name}')), pg_sleep(4)"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            time.sleep(1.0)
            p = self.c.move(name, "s1", check=False)
            self.assertNotEqual(0, p.returncode)
            self.assertIn("another `lifemap maps move`", p.stderr)
            self.assertEqual(("s3", "active", ""), self.c.move_state(name))
        finally:
            holder.wait(30)  # its session ends with the sleep: the lock is free again
        # A move cut short stands: another target is refused until it is finished or aborted.
        p = self.c.move(name, "s1", stop_after="exported", check=False)
        self.assertEqual(-9, p.returncode, p.stderr)
        self.assertEqual(("s3", "moving", "frozen"), self.c.move_state(name))
        other = self.c.move(name, "s2", check=False)
        self.assertNotEqual(0, other.returncode)
        self.assertIn("already moving to shard 's1'", other.stderr)
        # Writes are refused meanwhile, saying why; reads go on.
        self.c.cli("maps", "show", name)
        w = self.c.cli("maps", "set", name, "--description", "frozen?", check=False)
        self.assertNotEqual(0, w.returncode)
        self.assertIn("is moving from shard 's3' to shard 's1'", w.stderr)
        a = self.c.move(name, "s1", "--abort")
        self.assertIn("move aborted", a.stderr)
        self.assertEqual(("s3", "active", ""), self.c.move_state(name))
        self.c.cli("maps", "set", name, "--description", "writable again")

    def test_09_a_move_killed_at_any_step_is_finished_by_running_it_again(self):
        placed = self.ensure_maps()
        name = HOMES["s3"][1]  # atrium
        self.stream(name, "--robot", "kill-test", "--end-visit")
        keyframes = self.keyframes(name)
        home = placed[name]
        where = home
        for step in ["begun", "drained", "exported", "imported", "switched", "reloaded",
                     "deleted"]:
            to = "s1" if where != "s1" else "s2"
            p = self.c.move(name, to, stop_after=step, check=False)
            self.assertEqual(-9, p.returncode, f"{step}: {p.stderr}")
            self.c.move(name, to)
            where = to
            self.assertEqual((to, "active", ""), self.c.move_state(name), step)
            self.assertEqual(keyframes, self.keyframes(name), f"after a kill at {step}")
            for shard in SHARDS:
                held = json.loads(self.c.cli("--json", "maps", "list",
                                             target=self.direct(shard)).stdout)
                has = name in [m["name"] for m in held.get("maps", [])]
                self.assertEqual(shard == to, has, f"{shard} after a kill at {step}")
        self.c.move(name, home)

    def test_10_a_shard_back_with_a_copy_of_a_map_that_moved_is_refused(self):
        placed = self.ensure_maps()
        name = HOMES["s1"][0]  # lab
        self.assertEqual("s1", placed[name])
        # The source goes away after the switch: the move cannot delete its copy.
        p = self.c.move(name, "s2", stop_after="switched", check=False)
        self.assertEqual(-9, p.returncode)
        self.c.kill_shard("s1")
        try:
            p = self.c.move(name, "s2", check=False)
            self.assertNotEqual(0, p.returncode)
            self.assertIn("was not deleted", p.stderr)
            self.c.cli("maps", "show", name)  # served by s2 through nginx meanwhile
        finally:
            self.c.start_shard("s1")
        # Back, s1 holds the old copy: refused, saying where the map is.
        w = self.c.cli("maps", "show", name, target=self.direct("s1"), check=False)
        self.assertNotEqual(0, w.returncode)
        self.assertIn("moved to shard 's2'", w.stderr)
        self.c.move(name, "s2")  # finishes: the copy goes
        self.assertEqual(("s2", "active", ""), self.c.move_state(name))
        w = self.c.cli("maps", "show", name, target=self.direct("s1"), check=False)
        self.assertIn("lives on shard 's2'", w.stderr)
        self.c.move(name, "s1")

    def test_11_the_python_client_routes_through_nginx_too(self):
        try:
            import lifemap
        except ImportError:
            self.skipTest("the Python client is not installed (scripts/test-cluster installs it)")
        placed = self.ensure_maps()
        with lifemap.Client(self.c.target) as client:
            self.assertEqual(sorted(MAPS), sorted(m.name for m in client.maps()))
            for name in MAPS:
                self.assertEqual(name, client.get_map(name).name)
                for v in client.visits(name):
                    self.assertEqual(name, v.map)
            # GetStats fanned out: the shards' sums.
            total = 0
            for shard in SHARDS:
                with lifemap.Client(self.direct(shard)) as one:
                    total += one.stats().maps
            self.assertEqual(total, client.stats().maps)
            # Straight to one shard: that shard's maps alone (no fan-out through it).
        with lifemap.Client(self.direct("s3")) as client:
            self.assertEqual(sorted(m for m in MAPS if placed[m] == "s3"),
                             sorted(m.name for m in client.maps()))
        # An archive imported through nginx lands where nginx routes its manifest's name.
        with lifemap.Client(self.c.target) as client:
            archive = client.export(HOMES["s2"][0], "map")
            client.delete_map(HOMES["s2"][0])
            imported = client.import_map(archive)
            self.assertEqual(HOMES["s2"][0], imported.name)
            self.assertIn(HOMES["s2"][0], self.c.placement())

    def test_13_map_names_in_any_script_route_through_nginx(self):
        """Issue 52: a name beyond ASCII aborted the clients; nginx routes on its encoded form."""
        names = ["Küche", "Büro 2", "東京"]
        for name in names:
            self.c.cli("maps", "create", name)
        self.c.reload_nginx()  # the table now pins each by its encoded name
        placed = self.c.placement()
        for name in names:
            self.assertIn(name, placed)
            self.stream(name, "--end-visit", frames=10)
            self.assertTrue(self.keyframes(name))  # routed to its shard: no "lives on" refusal
            self.assertEqual(self.keyframes(name),
                             self.keyframes(name, target=self.direct(placed[name])))
        # Moved, it is found where it lives now.
        target = "s1" if placed["Küche"] != "s1" else "s2"
        before = self.keyframes("Küche")
        self.c.move("Küche", target)
        self.assertEqual(before, self.keyframes("Küche"))
        try:
            import lifemap
        except ImportError:
            lifemap = None
        if lifemap is not None:
            with lifemap.Client(self.c.target) as client:
                for name in names:
                    self.assertEqual(name, client.get_map(name).name)
        for name in names:
            self.c.cli("maps", "delete", name, "--yes")
        self.assertFalse(set(names) & set(self.c.placement()))

    def test_12_bad_input_is_refused_saying_what_to_do(self):
        self.ensure_maps()
        p = self.c.move("nowhere", "s2", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("map 'nowhere' is not placed on any shard", p.stderr)
        p = self.c.move(HOMES["s1"][0], "s9", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("shard 's9' is not in the placement database", p.stderr)
        self.assertEqual(("s1", "active", ""), self.c.move_state(HOMES["s1"][0]))
        p = self.c.admin("add", "bad name", "127.0.0.1:1", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("shard name 'bad name' must be", p.stderr)
        p = self.c.admin("add", "s4", "no-port", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("has no port", p.stderr)
        p = self.c.admin("add", "s1", "127.0.0.1:1", check=False)
        self.assertIn("already", p.stderr)
        p = self.c.admin("nginx-config", "--out", "-", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("--prefix", p.stderr)
        p = self.c.admin("remove", "s2", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("still holds maps", p.stderr)
        p = run(LIFEMAP, "admin", "shards", "--placement",
                "postgresql://lifemap@127.0.0.1:1/x?connect_timeout=2", "list", check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn("placement database", p.stderr)


class ClusterKeysTest(ClusterCase):
    """One key ring for every shard: keys in PostgreSQL, copied into each shard's store."""

    @classmethod
    def setUpClass(cls):
        cls.cluster = Cluster(shards=("s1", "s2"), keys=True)

    def key_file(self, name, secret):
        path = self.c.folder / f"{name}.key"
        path.write_text(secret)
        return path

    def eventually(self, check, what, timeout=15.0):
        deadline = time.time() + timeout
        while time.time() < deadline:
            if check():
                return
            time.sleep(0.25)
        self.fail_with_logs(f"{what} within {timeout} s")

    def test_keys_made_anywhere_hold_on_every_shard_and_follow_a_moved_map(self):
        # s2 was started requiring keys with none of its own: it took the cluster's admin key.
        for shard in ("s1", "s2"):
            self.c.cli("maps", "list", target=self.direct(shard))
        anonymous = run(LIFEMAP, "--server", self.c.target, "maps", "list", check=False)
        self.assertNotEqual(0, anonymous.returncode)
        self.assertIn("UNAUTHENTICATED", anonymous.stderr)
        self.c.cli("maps", "create", "lab", target=self.direct("s1"))
        self.c.cli("maps", "create", "office", target=self.direct("s2"))
        self.c.reload_nginx()

        # A robot key limited to one map, made through nginx (whichever shard took the call).
        made = self.c.cli("keys", "create", "robot1", "--role", "robot", "--maps", "office")
        robot = self.key_file("robot1", made.stdout)
        self.c.cli("maps", "show", "office", key=robot)  # nginx passes the key through
        self.c.cli("maps", "show", "office", key=robot, target=self.direct("s2"))
        denied = self.c.cli("maps", "show", "lab", key=robot, check=False)
        self.assertNotEqual(0, denied.returncode)
        self.assertIn("may use only the maps (none) on this shard, not 'lab'", denied.stderr)
        for shard in ("s1", "s2"):  # every shard lists the whole ring, maps by name
            keys = json.loads(self.c.cli("--json", "keys", "list",
                                         target=self.direct(shard)).stdout)["keys"]
            robot1 = next(k for k in keys if k["name"] == "robot1")
            self.assertEqual(["office"], robot1.get("maps"), shard)

        # The map moves to s1: the key follows it by name.
        self.c.move("office", "s1")
        self.c.cli("maps", "show", "office", key=robot)
        self.c.cli("maps", "show", "office", key=robot, target=self.direct("s1"))

        # A key made on a shard's machine while it runs joins the ring and holds on the other.
        late = run(LIFEMAPD, "keys", "create", "late", "--role", "operator", "--db",
                   self.c.folder / "s2.db")
        late_key = self.key_file("late", late.stdout)
        self.eventually(lambda: self.c.cli("maps", "list", key=late_key, check=False,
                                           target=self.direct("s1")).returncode == 0,
                        "a key made on s2's machine did not hold on s1")

        # nginx terminating TLS in front of the same shards (the table written with --tls-cert):
        # the client verifies nginx's certificate and its key passes through to the shards.
        tls = self.c.folder / "nginx-tls"
        tls.mkdir()
        run("openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1", "-subj",
            "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost", "-keyout",
            tls / "key.pem", "-out", tls / "cert.pem")
        port = free_port()
        self.c.admin("nginx-config", "--listen", f"127.0.0.1:{port}", "--prefix", tls, "--out",
                     tls / "nginx.conf", "--tls-cert", tls / "cert.pem", "--tls-key",
                     tls / "key.pem")
        nginx = subprocess.Popen([NGINX, "-p", str(tls), "-c", str(tls / "nginx.conf"), "-e",
                                  str(tls / "error.log"), "-g", "daemon off;"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            wait_port(port, process=nginx, what="nginx with TLS")
            over_tls = f"127.0.0.1:{port}"
            shown = json.loads(self.c.cli("--json", "--tls-ca", tls / "cert.pem", "maps", "show",
                                          "office", key=robot, target=over_tls).stdout)
            self.assertEqual("office", shown["name"])
            plain = self.c.cli("--connect-timeout", "2", "maps", "show", "office", key=robot,
                               target=over_tls, check=False)
            self.assertNotEqual(0, plain.returncode, "plaintext to a TLS port must fail")
        finally:
            nginx.send_signal(signal.SIGQUIT)
            nginx.wait(10)

        # A map deleted from the cluster leaves the keys limited to it (as on a lone server).
        self.c.cli("maps", "create", "attic", target=self.direct("s2"))
        self.c.cli("keys", "create", "attic-robot", "--role", "robot", "--maps", "attic,office")
        self.c.cli("maps", "delete", "attic", "--yes", target=self.direct("s2"))
        keys = json.loads(self.c.cli("--json", "keys", "list",
                                     target=self.direct("s1")).stdout)["keys"]
        self.assertEqual(["office"],
                         next(k for k in keys if k["name"] == "attic-robot").get("maps"), keys)

        # Revoked through nginx: refused on every shard.
        self.c.cli("keys", "revoke", "robot1")
        for shard in ("s1", "s2"):
            self.eventually(
                lambda: "revoked" in self.c.cli("maps", "list", key=robot, check=False,
                                                target=self.direct(shard)).stderr,
                f"a key revoked through nginx was still taken by {shard}")


if __name__ == "__main__":
    unittest.main(argv=[sys.argv[0], *sys.argv[1:]], verbosity=2)
