"""The browser view (issue 38) in headless Chromium against a real lifemapd on loopback.

ctest runs it as Browser.PagesAndAnnotationInHeadlessChromium (scripts/test-browser BUILD).
Environment: LIFEMAPD and LIFEMAP (the built binaries), SCREENSHOTS (a folder for one PNG per
page). Data: a synthetic place of two visits (`lifemap sim`), a forest trained on its first
visit's labels, both visits streamed with their poses, so the map has keyframes, floor plans,
labels and a semantic octree. Chromium draws WebGL with SwiftShader (no GPU).
"""
import base64
import io
import json
import os
import re
import shutil
import subprocess
import tarfile
import tempfile
import time
import unittest
import urllib.error
import urllib.request
from pathlib import Path

from PIL import Image
from selenium import webdriver
from selenium.webdriver.chrome.service import Service as ChromeService
from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import WebDriverWait

LIFEMAPD = os.environ.get("LIFEMAPD", "lifemapd")
LIFEMAP = os.environ.get("LIFEMAP", "lifemap")
SCREENSHOTS = Path(os.environ.get("SCREENSHOTS", tempfile.gettempdir()))


def run(*args, **kwargs):
    return subprocess.run([str(a) for a in args], check=True, capture_output=True, text=True,
                          **kwargs).stdout


class Server:
    """lifemapd with the browser view, both on free loopback ports, until stop()."""

    def __init__(self, db: Path, *flags: str, http: str = "127.0.0.1:0"):
        self.err = open(db.parent / f"server-{time.time_ns()}.err", "w")
        self.process = subprocess.Popen(
            [LIFEMAPD, "--db", str(db), "--listen", "127.0.0.1:0", "--http", http,
             "--log-level", "warn", "--shutdown-grace-s", "5", *flags],
            stdout=subprocess.PIPE, stderr=self.err, text=True)
        grpc_line = self.process.stdout.readline()
        http_line = self.process.stdout.readline()
        grpc_port = re.search(r"listening on port (\d+)", grpc_line)
        http_port = re.search(r"browser view on port (\d+)", http_line)
        if not grpc_port or not http_port:
            self.stop()
            raise RuntimeError(f"lifemapd did not start: {grpc_line!r} {http_line!r} "
                               f"{Path(self.err.name).read_text()}")
        self.target = f"127.0.0.1:{grpc_port.group(1)}"
        self.url = f"http://127.0.0.1:{http_port.group(1)}"

    def get(self, path, key=None):
        request = urllib.request.Request(self.url + path)
        if key:
            request.add_header("Authorization", f"Bearer {key}")
        with urllib.request.urlopen(request, timeout=120) as response:
            return response.read()

    def stop(self):
        if self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=30)
        self.process.stdout.close()
        self.err.close()


def not_blank(png: bytes, min_colours=20):
    """The number of distinct colours in a screenshot (a blank page has one or two)."""
    image = Image.open(io.BytesIO(png)).convert("RGB").resize((320, 240))
    colours = len(set(image.getdata()))
    return colours >= min_colours, colours


class BrowserViewTest(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.folder = Path(tempfile.mkdtemp(prefix="lifemap-browser-"))
        sim = cls.folder / "sim"
        run(LIFEMAP, "sim", "--world", "rooms", "--seed", "6", "--place-shape", "rect",
            "--visits", "2", "--frames", "40", "--out", sim)
        model = cls.folder / "sim.model"
        run(LIFEMAP, "train", "--data", sim / "visit_00", "--frame-stride", "4", "--trees", "1",
            "--depth", "12", "--pixels", "500", "--candidates", "100", "--out", model)
        db = cls.folder / "lifemap.db"
        cls.keys = {}
        for name, role in [("admin1", "admin"), ("robot1", "robot"), ("op1", "operator")]:
            cls.keys[role] = run(LIFEMAPD, "keys", "create", name, "--role", role, "--db", db,
                                 "--create").strip().splitlines()[-1]
        cls.server = Server(db, "--require-auth")
        admin = ["--server", cls.server.target, "--api-key", cls.keys["admin"]]
        run(LIFEMAP, *admin, "maps", "create", "room", "--description", "two visits")
        run(LIFEMAP, *admin, "models", "upload", model, "sim")
        run(LIFEMAP, *admin, "models", "activate", "sim", "room")
        for visit in ("visit_00", "visit_01"):
            run(LIFEMAP, *admin, "stream", "room", "--tum", sim / visit, "--use-groundtruth",
                "--rate", "0", "--result-images", "none", "--end-visit")
        options = webdriver.ChromeOptions()
        for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                     "--window-size=1400,1000", "--use-angle=swiftshader",
                     "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"):
            options.add_argument(flag)
        options.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
        service = ChromeService(executable_path=shutil.which("chromedriver"))
        cls.browser = webdriver.Chrome(options=options, service=service)
        cls.browser.set_script_timeout(120)
        SCREENSHOTS.mkdir(parents=True, exist_ok=True)

    @classmethod
    def tearDownClass(cls):
        cls.browser.quit()
        cls.server.stop()
        shutil.rmtree(cls.folder, ignore_errors=True)

    # -- helpers -----------------------------------------------------------------------------
    def api(self, path, role="robot"):
        return json.loads(self.server.get(path, self.keys[role]))

    def open(self, hash_path, key=None):
        """Opens a page (with `key` entered in the key form first when given); waits for it."""
        b = self.browser
        b.get(self.server.url + "/" + hash_path)
        if key is not None:
            b.execute_script("sessionStorage.setItem('lifemap-api-key', arguments[0])", key)
            b.refresh()
        self.wait_ready()

    def wait_ready(self, timeout=180):
        WebDriverWait(self.browser, timeout).until(
            lambda b: b.execute_script("return document.body.dataset.ready") in ("1", "error"))

    def shoot(self, name):
        png = self.browser.get_screenshot_as_png()
        (SCREENSHOTS / f"{name}.png").write_bytes(png)
        ok, colours = not_blank(png)
        self.assertTrue(ok, f"{name}: the screenshot has only {colours} colours")
        return png

    def text(self, css):
        return self.browser.find_element(By.CSS_SELECTOR, css).text

    # -- pages -------------------------------------------------------------------------------
    def test_1_without_a_key_the_pages_are_refused_and_say_how(self):
        with self.assertRaises(urllib.error.HTTPError) as e:
            self.server.get("/api/maps")
        self.assertEqual(e.exception.code, 401)
        self.open("#/")
        self.assertIn("needs an API key", self.text("#error"))
        self.assertTrue(self.browser.find_element(By.ID, "key-form").is_displayed())
        # The key typed into the form opens the pages.
        self.browser.find_element(By.ID, "key-input").send_keys(self.keys["robot"])
        self.browser.find_element(By.CSS_SELECTOR, "#key-form button").click()
        self.wait_ready()
        self.assertEqual(self.browser.execute_script("return document.body.dataset.ready"), "1")
        self.assertIn("room", self.text("#maps"))

    def test_2_the_maps_page_lists_the_maps_with_their_counts(self):
        maps = self.api("/api/maps")["maps"]
        self.open("#/", self.keys["robot"])
        rows = self.browser.find_elements(By.CSS_SELECTOR, "tr.map-row")
        self.assertEqual(len(rows), len(maps))
        self.assertEqual(self.text(".keyframe-count"), str(maps[0]["keyframe_count"]))
        self.assertGreater(maps[0]["keyframe_count"], 5)
        self.shoot("maps")

    def test_3_a_map_shows_its_visits_plans_and_keyframes(self):
        room = self.api("/api/maps/room")
        self.open("#/map/room", self.keys["robot"])
        self.assertEqual(self.text("#visit-count"), "2")
        self.assertEqual(self.text("#keyframe-count"), str(room["keyframe_count"]))
        visits = self.browser.find_elements(By.CSS_SELECTOR, "tr.visit-row")
        self.assertEqual(len(visits), 2)
        self.assertEqual(len(self.browser.find_elements(By.CSS_SELECTOR, "g.visit-bar")), 2)
        self.assertIn("map frame", visits[0].text)
        # Thumbnails of the first page of keyframes.
        WebDriverWait(self.browser, 60).until(lambda b: b.execute_script(
            "return [...document.querySelectorAll('#strip img')].filter(i => i.naturalWidth > 0)"
            ".length") == min(48, room["keyframe_count"]))
        # A visit's floor plan with its keyframes on it.
        with_plan = [v for v in room["visits"] if v["has_plan"]]
        self.assertTrue(with_plan, "no visit has a floor plan")
        v = with_plan[0]
        self.browser.find_element(By.CSS_SELECTOR, f".plan-button[data-visit='{v['id']}']").click()
        WebDriverWait(self.browser, 30).until(
            lambda b: b.find_elements(By.CSS_SELECTOR, "#plan circle.keyframe"))
        markers = self.browser.find_elements(By.CSS_SELECTOR, "#plan circle.keyframe")
        self.assertEqual(len(markers), v["keyframe_count"])
        self.shoot("map")

    def test_4_a_keyframe_shows_its_overlays_and_matches(self):
        keyframes = self.api("/api/maps/room/keyframes?limit=5")["keyframes"]
        k = keyframes[2]
        self.open(f"#/keyframe/room/{k['id']}", self.keys["robot"])
        self.assertEqual(self.text("#keyframe-id"), str(k["id"]))
        for overlay in ("entropy", "labels", "fused"):
            self.browser.find_element(By.CSS_SELECTOR,
                                      f".overlay-toggle[value='{overlay}']").click()
            WebDriverWait(self.browser, 60).until(lambda b: b.execute_script(
                f"const i = document.querySelector('img.overlay[data-overlay=\"{overlay}\"]');"
                "return i !== null && i.naturalWidth > 0"))
        self.assertEqual(self.text("#overlay-status"), "")
        # Its visit's floor plan matches the other visit's (the same place).
        self.assertIn("visit", self.text("#architecture"))
        self.shoot("keyframe")

    def test_5_the_3d_view_draws_the_map_and_a_robot_key_cannot_annotate(self):
        self.open("#/3d/room", self.keys["robot"])
        WebDriverWait(self.browser, 60).until(
            lambda b: b.execute_script("return window.lifemapScene.frames") > 0)
        # Turned round the map, frame by frame: every frame drawn (SwiftShader: no GPU here).
        times = self.browser.execute_script("return window.lifemapScene.orbit(10)")
        self.assertEqual(len(times), 10)
        print(f"3D view: {sorted(times)[5]:.1f} ms a frame (median of 10, SwiftShader)")
        octree = self.api("/api/maps/room/octree")
        names = [c["name"] for c in octree["classes"] if c["voxels"] > 0]
        shown = [e.text for e in self.browser.find_elements(By.CSS_SELECTOR, ".class-name")]
        self.assertEqual(shown, [c["name"] for c in octree["classes"]])
        self.assertGreater(self.browser.execute_script("return window.lifemapScene.points"), 1000)
        # The WebGL canvas itself holds the drawing (not only the page around it).
        data_url = self.browser.execute_script(
            "return document.getElementById('scene-canvas').toDataURL('image/png')")
        canvas_png = base64.b64decode(data_url.split(",", 1)[1])
        ok, colours = not_blank(canvas_png)
        self.assertTrue(ok, f"the 3D canvas has only {colours} colours")
        self.shoot("3d")
        # A robot key reads but may not annotate: the page says so.
        self.browser.find_element(By.CSS_SELECTOR, ".select-class").click()
        self.browser.find_element(By.ID, "annotation-class").send_keys(names[0])
        self.browser.find_element(By.ID, "annotate").click()
        WebDriverWait(self.browser, 30).until(lambda b: "operator" in self.text("#annotate-status"))
        self.assertEqual(self.text("#annotation-count"), "0")

    def test_6_an_annotation_made_in_the_page_is_in_the_training_folder(self):
        self.open("#/3d/room", self.keys["operator"])
        octree = self.api("/api/maps/room/octree")
        target = max(octree["classes"][1:], key=lambda c: c["voxels"])  # not the background
        self.browser.find_element(By.CSS_SELECTOR,
                                  f".select-class[data-class='{target['id']}']").click()
        self.assertEqual(self.text("#selected-count"), str(target["voxels"]))
        self.browser.find_element(By.ID, "annotation-class").send_keys("my-" + target["name"])
        self.browser.find_element(By.ID, "annotate").click()
        WebDriverWait(self.browser, 30).until(lambda b: self.text("#annotation-count") == "1")
        self.shoot("annotate")
        tar = tarfile.open(fileobj=io.BytesIO(self.server.get("/api/maps/room/training.tar",
                                                              self.keys["robot"])))
        names = tar.getnames()
        classes = tar.extractfile("room-training/labels/classes.txt").read().decode().split()
        self.assertEqual(classes, ["background", "my-" + target["name"]])
        labels = [n for n in names if n.startswith("room-training/labels/") and n.endswith(".png")]
        self.assertGreater(len(labels), 3)
        # ... and `lifemap train` reads the folder.
        out = self.folder / "training"
        tar.extractall(out)
        model = self.folder / "annotated.model"
        log = run(LIFEMAP, "train", "--data", out / "room-training", "--frame-stride", "1",
                  "--trees", "1", "--depth", "6", "--pixels", "100", "--candidates", "20",
                  "--out", model)
        self.assertIn("2 classes", log)

    def test_7_beyond_loopback_the_view_needs_a_key_even_without_require_auth(self):
        db = self.folder / "other.db"
        run(LIFEMAPD, "keys", "create", "a", "--role", "admin", "--db", db, "--create")
        server = Server(db, http="0.0.0.0:0")
        try:
            with self.assertRaises(urllib.error.HTTPError) as e:
                server.get("/api/maps")
            self.assertEqual(e.exception.code, 401)
            self.assertIn(b"<!doctype html>", server.get("/"))  # the page itself holds no data
        finally:
            server.stop()


if __name__ == "__main__":
    unittest.main()
