"""The Python client against a real lifemapd (ctest: Python.*; scripts/test-python runs it).

Environment: LIFEMAPD and LIFEMAP (the built binaries), LIFEMAP_DATA (../shared/data; tests
that need a recording skip, saying so, when it is absent).
"""
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import unittest
from pathlib import Path

import grpc
import numpy as np

import lifemap
import lifemap.tum

LIFEMAPD = os.environ.get("LIFEMAPD", "lifemapd")
LIFEMAP = os.environ.get("LIFEMAP", "lifemap")
DATA = Path(os.environ.get("LIFEMAP_DATA", Path(__file__).resolve().parents[3] / ".." / "shared"
                           / "data"))
TUM = DATA / "tum_fr1_xyz_subset"
MOSD = DATA / "pcl_mosd_labeled_subset"


class Server:
    """lifemapd on a fresh database in `folder`, on a free port; stopped by stop()."""

    def __init__(self, folder: Path, *flags: str, listen: str = "127.0.0.1:0"):
        self.folder = folder
        self.db = folder / "lifemap.db"
        self.err = open(folder / "server.err", "w")
        self.process = subprocess.Popen(
            [LIFEMAPD, "--db", str(self.db), "--listen", listen, "--log-level", "warn",
             "--shutdown-grace-s", "5", *flags],
            stdout=subprocess.PIPE, stderr=self.err, text=True)
        line = self.process.stdout.readline()  # "lifemapd ... listening on port N ..."
        found = re.search(r"listening on port (\d+)", line)
        if not found:
            self.stop()
            raise RuntimeError(f"lifemapd did not start: {line!r} "
                               f"{(folder / 'server.err').read_text()}")
        self.target = f"127.0.0.1:{found.group(1)}"

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=30)
        self.process.stdout.close()
        self.err.close()


def synthetic_frame(width=160, height=120, seed=0):
    """A box on a floor seen from above: depth in TUM units (5000 per metre), a textured colour."""
    rng = np.random.default_rng(seed)
    depth = np.full((height, width), 2.0 * 5000, dtype=np.uint16)
    depth[40:80, 60:110] = int(1.6 * 5000)
    color = rng.integers(0, 255, size=(height, width, 3), dtype=np.uint8)
    return color, depth, (200.0, 200.0, width / 2 - 0.5, height / 2 - 0.5)


class ClientTest(unittest.TestCase):
    def setUp(self):
        self.folder = Path(tempfile.mkdtemp(prefix="lifemap-py-"))
        self.servers = []

    def tearDown(self):
        for s in self.servers:
            s.stop()
        shutil.rmtree(self.folder, ignore_errors=True)

    def start(self, *flags, listen="127.0.0.1:0") -> Server:
        server = Server(self.folder, *flags, listen=listen)
        self.servers.append(server)
        return server

    def test_process_returns_the_entropy_mask_as_an_array_and_stores_a_keyframe(self):
        server = self.start()
        with lifemap.Client(server.target) as client:
            self.assertEqual(client.create_map("lab").name, "lab")
            self.assertEqual([m.name for m in client.maps()], ["lab"])
            color, depth, intrinsics = synthetic_frame()
            result = client.process("lab", color, depth, intrinsics, depth_scale=5000.0,
                                    pose=(0, 0, 0, 0, 0, 0, 1))
            self.assertIsNone(result.error)
            self.assertEqual(result.entropy_mask.shape, (120, 160))
            self.assertEqual(result.entropy_mask.dtype, np.bool_)
            self.assertEqual(result.entropy_score.shape, (120, 160))
            self.assertIsNotNone(result.keyframe_id, "a map's first frame is a keyframe")
            self.assertEqual(result.pose, (0, 0, 0, 0, 0, 0, 1))
            self.assertIsNone(result.labels)  # no model: said why
            computed, reason = result.outputs["FRAME_OUTPUT_CLASS_LABELS"]
            self.assertFalse(computed)
            self.assertIn("model", reason)
            stored = client.keyframes("lab")
            self.assertEqual([k.id for k in stored], [result.keyframe_id])
            keyframe = client.keyframe("lab", result.keyframe_id)
            self.assertEqual((keyframe.summary.intrinsics.width, keyframe.depth.height), (160, 120))
            # Nothing stored without a map.
            self.assertIsNone(client.process(None, color, depth, intrinsics).keyframe_id)
            # Issue 53: a frame never joins a visit unasked. A stream leaves its visit open;
            # a frame processed hours later gets a visit of its own (it used to join the open
            # one and be refused for the time gap), ended once answered.
            streamed = list(client.stream("lab", [(color, depth, (0, 0, 0, 0, 0, 0, 1), 1000.0)],
                                          intrinsics=intrinsics))
            left_open = streamed[0].visit_id
            later = client.process("lab", color, depth, intrinsics, pose=(0, 0, 0, 0, 0, 0, 1),
                                   timestamp_s=1000.0 + 6 * 3600)
            self.assertNotEqual(left_open, later.visit_id)
            visits = {v.id: v for v in client.visits("lab")}
            self.assertTrue(visits[later.visit_id].ended)
            self.assertFalse(visits[left_open].ended, "the stream's visit is left as it was")
            client.end_visit(left_open)

    def test_map_names_in_any_script(self):
        """Issue 52: 'Büro 3' raised "metadata was invalid" (a header must be ASCII)."""
        server = self.start()
        color, depth, intrinsics = synthetic_frame()
        with lifemap.Client(server.target) as client:
            for name in ("Büro 3", "Küche", "東京"):
                self.assertEqual(client.create_map(name).name, name)
                result = client.process(name, color, depth, intrinsics, depth_scale=5000.0,
                                        pose=(0, 0, 0, 0, 0, 0, 1))
                self.assertIsNotNone(result.keyframe_id)
                self.assertEqual([k.id for k in client.keyframes(name)], [result.keyframe_id])
                self.assertEqual(client.get_map(name).name, name)
            self.assertEqual(sorted(m.name for m in client.maps()), ["Büro 3", "Küche", "東京"])
            with self.assertRaises(lifemap.Error) as e:
                client.create_map("new\nline")
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            self.assertIn("any script", e.exception.details)

    def test_errors_carry_the_grpc_code_and_the_servers_message(self):
        server = self.start()
        with lifemap.Client(server.target) as client:
            client.create_map("lab")
            with self.assertRaises(lifemap.Error) as e:
                client.create_map("lab")
            self.assertEqual(e.exception.code, grpc.StatusCode.ALREADY_EXISTS)
            self.assertIn("lab", e.exception.details)
            with self.assertRaises(lifemap.Error) as e:
                client.get_map("nowhere")
            self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
            color, depth, intrinsics = synthetic_frame()
            with self.assertRaises(lifemap.Error) as e:  # cx outside the image
                client.process("lab", color, depth, (200.0, 200.0, 500.0, 60.0))
            self.assertEqual(e.exception.code, grpc.StatusCode.INVALID_ARGUMENT)
            self.assertIn("principal point", e.exception.details)
            # Arrays of the wrong kind are refused before anything is sent.
            with self.assertRaisesRegex(ValueError, "uint16"):
                client.process("lab", color, depth.astype(np.float32), intrinsics)
            with self.assertRaisesRegex(ValueError, "register depth"):
                client.process("lab", color, depth[:60], intrinsics)
            # A stream whose frames fail raises their error, not gRPC's.
            with self.assertRaisesRegex(ValueError, "H x W x 3"):
                list(client.stream("lab", [(color[..., 0], depth)], intrinsics=intrinsics))
            # A frame that is neither a Frame nor a tuple is named, with what a frame must be.
            with self.assertRaisesRegex(TypeError, r"frame 0 is a dict: .*lifemap.Frame"):
                list(client.stream("lab", [{"color": color, "depth": depth}],
                                   intrinsics=intrinsics))
            with self.assertRaisesRegex(TypeError, r"frame 0 is a tuple of 1 values"):
                client.query_place([(color,)], intrinsics=intrinsics)
            with self.assertRaises(lifemap.Error) as e:
                list(client.stream("nowhere", [(color, depth)], intrinsics=intrinsics))
            self.assertEqual(e.exception.code, grpc.StatusCode.NOT_FOUND)
        with lifemap.Client("127.0.0.1:1", timeout_s=2) as nobody:
            with self.assertRaises(lifemap.Error) as e:
                nobody.maps()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAVAILABLE)

    def test_streams_a_tum_recording_with_labels_and_fused_labels_as_arrays(self):
        if not TUM.is_dir() or not MOSD.is_dir():
            self.skipTest(f"needs {TUM} and {MOSD} (../shared/data)")
        model = self.folder / "m.model"
        subprocess.run([LIFEMAP, "train", "--data", str(MOSD / "learn"), "--trees", "1",
                        "--depth", "10", "--pixels", "300", "--candidates", "50", "--out",
                        str(model)], check=True, stdout=subprocess.DEVNULL)
        server = self.start()
        with lifemap.Client(server.target) as client:
            client.create_map("office")
            info = client.upload_model(model, "mosd")
            self.assertGreater(len(info.class_names), 1)
            client.activate_model("mosd", "office")
            frames = lifemap.tum.frames(TUM, groundtruth=True)
            results = list(client.stream("office", frames, robot="py", visit_label="xyz"))
            self.assertGreaterEqual(len(results), 30)
            self.assertEqual([r.sequence for r in results], list(range(len(results))))
            for r in results:
                self.assertIsNone(r.error)
                self.assertEqual(r.entropy_mask.shape, (480, 640))
                self.assertEqual(r.labels.shape, (480, 640))
                self.assertTrue(set(np.unique(r.labels)) <= set(r.classes) | {255})
            self.assertTrue(0.0 < np.mean([r.entropy_mask.mean() for r in results]) < 1.0)
            self.assertTrue(any(r.fused_labels is not None for r in results))
            acknowledged = {r.keyframe_id for r in results if r.keyframe_id is not None}
            self.assertGreater(len(acknowledged), 3)
            visit = results[0].visit_id
            self.assertEqual({k.id for k in client.keyframes("office", visit)}, acknowledged)
            client.end_visit(visit)
            poses = client.export("office", "poses", out=self.folder / "poses.txt").decode()
            self.assertEqual(len([l for l in poses.splitlines() if l and l[0].isdigit()]),
                             len(acknowledged))
            self.assertEqual((self.folder / "poses.txt").read_text(), poses)
            # Its own frames recognise the place by appearance (a vocabulary now: it has too
            # few keyframes for the server to train one by itself).
            self.assertTrue(client.rebuild_appearance_index(retrain=True).has_vocabulary)
            again = list(lifemap.tum.frames(TUM, max_frames=3, stride=10))
            answer = client.query_place(again, methods=["appearance"])
            self.assertTrue(any(m.map == "office" and m.visit_id == visit
                                for m in answer.matches), answer)

    def test_the_example_script_streams_a_recording(self):
        if not TUM.is_dir():
            self.skipTest(f"needs {TUM} (../shared/data)")
        server = self.start()
        example = Path(__file__).resolve().parents[1] / "examples" / "stream_tum.py"
        out = self.folder / "masks.npz"
        run = subprocess.run([sys.executable, str(example), server.target, str(TUM), "office", "--groundtruth", "--out", str(out)],
                             capture_output=True, text=True, timeout=300)
        self.assertEqual(run.returncode, 0, run.stderr)
        self.assertIn("stored as keyframe", run.stdout)
        saved = np.load(out)
        self.assertEqual(saved["entropy_masks"].shape[1:], (480, 640))

    def test_a_navigation_grid_and_a_whole_map_moved_between_servers(self):
        import yaml
        from PIL import Image
        sim = self.folder / "sim"
        subprocess.run([LIFEMAP, "sim", "--world", "rooms", "--seed", "6", "--place-shape", "rect", "--visits", "1",
                        "--frames", "30", "--out", str(sim)], check=True,
                       stdout=subprocess.DEVNULL)
        server = self.start()
        with lifemap.Client(server.target) as client:
            client.create_map("room")
            subprocess.run([LIFEMAP, "--server", server.target, "stream", "room", "--tum",
                            str(sim / "visit_00"), "--use-groundtruth", "--rate", "0",
                            "--end-visit", "--send", "compact"], check=True,
                           stdout=subprocess.DEVNULL)
            cells, info = client.export_grid("room", self.folder / "nav")
            self.assertEqual(cells.shape, (info.height, info.width))
            self.assertLess(abs(info.floor_z), 0.1, "the sim's floor is z = 0")
            self.assertEqual(set(np.unique(cells)) - {0, 205, 254}, set())
            self.assertGreater((cells == 254).sum(), (cells == 0).sum())
            # map_server's two files, read by a YAML reader and an image reader.
            meta = yaml.safe_load((self.folder / "nav" / "room.yaml").read_text())
            self.assertEqual(meta["image"], "room.pgm")
            self.assertAlmostEqual(meta["resolution"], info.resolution_m)
            self.assertAlmostEqual(meta["origin"][0], info.origin_x, places=5)
            pgm = np.asarray(Image.open(self.folder / "nav" / "room.pgm"))
            np.testing.assert_array_equal(pgm, cells)
            octree = client.export("room", "occupancy")
            self.assertTrue(octree.startswith(b"# Octomap OcTree binary file"))

            archive = client.export("room", "map", out=self.folder / "room.lifemap")
            self.assertTrue(archive.startswith(b"lifemap-map-archive 1\n"))
            copy = client.import_map(self.folder / "room.lifemap", "room2")
            self.assertEqual(copy.keyframe_count, client.get_map("room").keyframe_count)
            with self.assertRaises(lifemap.Error) as e:
                client.import_map(archive)
            self.assertEqual(e.exception.code, grpc.StatusCode.ALREADY_EXISTS)
            poses = [l for l in client.export("room").decode().splitlines() if l[0] != "#"]
            again = [l for l in client.export("room2").decode().splitlines() if l[0] != "#"]
            self.assertEqual(poses, again)

    def test_api_keys_and_tls(self):
        subprocess.run(["openssl", "version"], check=True, stdout=subprocess.DEVNULL)
        certs = self.folder
        key = "-newkey ec -pkeyopt ec_paramgen_curve:prime256v1 -nodes"
        (certs / "server.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
        for command in (
                f"openssl req -x509 {key} -keyout ca.key -out ca.pem -days 2 -subj /CN=py-ca",
                f"openssl req {key} -keyout server.key -out server.csr -subj /CN=localhost",
                "openssl x509 -req -in server.csr -CA ca.pem -CAkey ca.key -CAcreateserial "
                "-out server.pem -days 2 -extfile server.ext"):
            subprocess.run(command, shell=True, cwd=certs, check=True, capture_output=True)

        def create_key(name, role):
            return subprocess.run([LIFEMAPD, "keys", "create", "--db", str(certs / "lifemap.db"),
                                   "--create", "--name", name, "--role", role], check=True,
                                  capture_output=True, text=True).stdout.strip()

        admin = create_key("root", "admin")
        robot = create_key("bot", "robot")
        # Listening beyond loopback: keys are required.
        server = self.start("--tls-cert", str(certs / "server.pem"), "--tls-key",
                            str(certs / "server.key"), listen="0.0.0.0:0")
        with lifemap.Client(server.target, root_certificates=certs / "ca.pem") as anonymous:
            with self.assertRaises(lifemap.Error) as e:
                anonymous.maps()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAUTHENTICATED)
            self.assertIn("authorization", e.exception.details)
        with lifemap.Client(server.target, api_key=admin,
                            root_certificates=(certs / "ca.pem").read_bytes()) as operator:
            operator.create_map("lab")
        with lifemap.Client(server.target, api_key=robot,
                            root_certificates=str(certs / "ca.pem")) as bot:
            self.assertEqual([m.name for m in bot.maps()], ["lab"])
            with self.assertRaises(lifemap.Error) as e:
                bot.create_map("hall")
            self.assertEqual(e.exception.code, grpc.StatusCode.PERMISSION_DENIED)
            color, depth, intrinsics = synthetic_frame()
            self.assertIsNotNone(bot.process("lab", color, depth, intrinsics,
                                             pose=(0, 0, 0, 0, 0, 0, 1)).keyframe_id)
        # Without the server's CA, TLS does not connect.
        with lifemap.Client(server.target, api_key=admin, timeout_s=3) as plain:
            with self.assertRaises(lifemap.Error) as e:
                plain.maps()
            self.assertEqual(e.exception.code, grpc.StatusCode.UNAVAILABLE)


class ClusterMergeTest(unittest.TestCase):
    """A cluster's fanned-out answers merged as the C++ client merges them (ClusterMerge.*)."""

    def test_place_rankings_merge_by_score_per_method(self):
        from lifemap.client import _merge_place_answers, _merge_stats
        from lifemap.v1 import admin_service_pb2 as admin_pb
        from lifemap.v1 import frame_service_pb2 as frame_pb
        from lifemap.v1 import place_service_pb2 as place_pb
        fused, arch, app = (frame_pb.MATCH_METHOD_FUSED, frame_pb.MATCH_METHOD_ARCHITECTURE,
                            frame_pb.MATCH_METHOD_APPEARANCE)
        s1 = place_pb.QueryPlaceResponse(descriptor_text="corner 1")
        s1.matches.add(map="lab", score=0.6, method=fused)
        s1.matches.add(map="lab", score=0.5, method=arch)
        s1.matches.add(map="lab", score=0.9, method=app)
        s1.frames.add(index=0, reason="no verified match")
        s1.method_status.add(method=arch, computed=True)
        s1.method_status.add(method=app, computed=False, reason="no vocabulary yet")
        s2 = place_pb.QueryPlaceResponse()
        s2.matches.add(map="office", score=0.8, method=fused)
        s2.matches.add(map="hall", score=0.7, method=fused)
        s2.matches.add(map="office", score=0.95, method=app)
        s2.frames.add(index=0).matches.add(map="office", score=0.95, method=app)
        s2.method_status.add(method=arch, computed=False, reason="no places stored")
        s2.method_status.add(method=app, computed=True)
        merged = _merge_place_answers([("s1", s1), ("s2", s2)], 2)
        self.assertEqual([("office", fused), ("hall", fused), ("lab", arch), ("office", app),
                          ("lab", app)], [(m.map, m.method) for m in merged.matches])
        self.assertEqual(1, len(merged.frames[0].matches))
        self.assertEqual("", merged.frames[0].reason)
        self.assertEqual("corner 1", merged.descriptor_text)
        self.assertTrue(all(m.computed for m in merged.method_status))
        alone = _merge_place_answers([("s2", s2)], 10)
        self.assertEqual("s2: no places stored", alone.method_status[0].reason)

        a = admin_pb.Stats(maps=2, keyframes=100, uptime_s=300, process_cpu_s=12.5)
        b = admin_pb.Stats(maps=3, keyframes=100, uptime_s=100, process_cpu_s=12.5)
        stats = _merge_stats([a, b])
        self.assertEqual((5, 200, 100.0, 25.0),
                         (stats.maps, stats.keyframes, stats.uptime_s, stats.process_cpu_s))


if __name__ == "__main__":
    unittest.main()
