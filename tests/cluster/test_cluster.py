"""Several lifemapd behind nginx, maps placed in PostgreSQL (issue 39), all on loopback.

ctest runs each test as Cluster.<name> (scripts/test-cluster BUILD NAME). Environment: LIFEMAPD
and LIFEMAP (the built binaries). Started by the test, in a temporary folder, on free ports: a
PostgreSQL cluster (initdb; as root its programs run as the `postgres` user, which refuses
root), three shards and nginx (`nginx -p DIR -c FILE`, the table written by
`lifemap admin shards nginx-config`). Robots are `lifemap stream` replaying a synthetic place
(`lifemap sim`) through nginx.
"""
import json
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
    """PostgreSQL, three shards and nginx, until stop()."""

    def __init__(self):
        self.folder = Path(tempfile.mkdtemp(prefix="lifemap-cluster-"))
        self.folder.chmod(0o755)  # the postgres user reaches its folder inside
        self.shards = {}
        self.nginx = None
        self.pg = PostgreSQL(self.folder / "pg")
        try:
            self.start()
        except BaseException:
            print(self.logs(), file=sys.stderr)
            self.stop()
            raise

    def start(self):
        self.ports = {name: free_port() for name in SHARDS}
        for name in SHARDS:
            self.admin("add", name, f"127.0.0.1:{self.ports[name]}")
        for name in SHARDS:
            self.start_shard(name)
        self.nginx_port = free_port()
        self.nginx_dir = self.folder / "nginx"
        self.nginx_dir.mkdir()
        self.write_nginx_table()
        self.start_nginx()
        self.target = f"127.0.0.1:{self.nginx_port}"

    def admin(self, *args, check=True):
        return run(LIFEMAP, "admin", "shards", "--placement", self.pg.uri, *args, check=check)

    def start_shard(self, name):
        with open(self.folder / f"{name}.log", "a") as err:
            p = subprocess.Popen(
                [LIFEMAPD, "--db", str(self.folder / f"{name}.db"), "--listen",
                 f"127.0.0.1:{self.ports[name]}", "--placement", self.pg.uri, "--shard", name,
                 "--log-level", "info", "--shutdown-grace-s", "5"],
                stdout=subprocess.DEVNULL, stderr=err)
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

    def stop_nginx(self):
        if self.nginx is not None and self.nginx.poll() is None:
            self.nginx.send_signal(signal.SIGQUIT)  # graceful: lets running requests finish
            try:
                self.nginx.wait(5)
            except subprocess.TimeoutExpired:
                self.nginx.kill()
                self.nginx.wait()

    def cli(self, *args, target=None, check=True, timeout=300):
        return run(LIFEMAP, "--server", target or self.target, *args, check=check,
                   timeout=timeout)

    def placement(self):
        """{map: shard} as the placement database has it."""
        out = run(PG_BIN / "psql", "-At", "-h", "127.0.0.1", "-p", self.pg.port, "-U", "lifemap",
                  "-d", "postgres", "-c", "SELECT name, shard FROM lifemap_maps").stdout
        return dict(line.split("|") for line in out.split())

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

    def logs(self):
        text = []
        for f in sorted(self.folder.glob("*.log")) + sorted(self.folder.glob("nginx/*.log")):
            text.append(f"--- {f.name}\n{f.read_text()[-3000:]}")
        return "\n".join(text)


# Maps created on each shard (the others drained meanwhile, so that nginx's hash has one choice).
HOMES = {"s1": ["lab", "hall"], "s2": ["office", "kitchen"], "s3": ["garage", "atrium"]}
MAPS = [m for names in HOMES.values() for m in names]


class ClusterTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.cluster = Cluster()
        cls.sim = cls.cluster.folder / "sim"
        run(LIFEMAP, "sim", "--world", "rooms", "--seed", "6", "--place-shape", "rect", "--visits",
            "1", "--frames", "30", "--out", cls.sim)

    @classmethod
    def tearDownClass(cls):
        cls.cluster.stop()
        if os.environ.get("KEEP") is None:
            shutil.rmtree(cls.cluster.folder, ignore_errors=True)

    def setUp(self):
        self.c = self.cluster

    def fail_with_logs(self, message):
        self.fail(f"{message}\n{self.c.logs()}")

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
                          *extra, check=check)

    def map_on(self, placed, shard):
        return next(m for m in MAPS if placed[m] == shard)

    def test_1_new_maps_are_placed_over_the_shards_and_listed_through_nginx(self):
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

    def test_2_robots_stream_to_maps_on_different_shards_at_once(self):
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

    def test_3_a_shard_asked_about_another_shards_map_says_where_it_lives(self):
        placed = self.ensure_maps()
        name = self.map_on(placed, "s2")
        wrong = f"127.0.0.1:{self.c.ports['s1']}"
        p = self.c.cli("maps", "show", name, target=wrong, check=False)
        self.assertNotEqual(0, p.returncode)
        self.assertIn(f"lives on shard 's2' (127.0.0.1:{self.c.ports['s2']})", p.stderr)

    def test_4_a_killed_shard_answers_unavailable_naming_it_and_the_others_go_on(self):
        placed = self.ensure_maps()
        self.c.reload_nginx()
        down = self.map_on(placed, "s3")
        up = self.map_on(placed, "s1")
        self.c.kill_shard("s3")
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
        finally:
            self.c.start_shard("s3")
        self.c.cli("maps", "show", down)

    def test_5_nginx_restarted_while_nothing_streams_comes_back_with_its_table(self):
        placed = self.ensure_maps()
        self.c.stop_nginx()
        p = self.c.cli("--connect-timeout", "1", "maps", "show", "lab", check=False)
        self.assertNotEqual(0, p.returncode)
        self.c.start_nginx()
        for name in MAPS:
            self.c.cli("maps", "show", name)
        self.assertEqual(placed, self.c.placement())


if __name__ == "__main__":
    unittest.main(argv=[sys.argv[0], *sys.argv[1:]], verbosity=2)
