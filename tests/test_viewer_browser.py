"""`warpnerf view` in a real headless browser: the system's Chromium (driven by selenium through
the system's chromedriver) loads the page of a tiny run on a free localhost port, waits for the
first rendered frame, and the screenshot shows the scene; the panel's camera-path editor saves a
path into the run; the server then stops cleanly on Ctrl-C, within 5 s, and frees its port.
Skipped, with the reason, where no browser is installed (`.ci/run` installs Chromium and its
driver with apt)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome")
                 if shutil.which(n)), None)  # fmt: skip
DRIVER = shutil.which("chromedriver")

pytestmark = pytest.mark.skipif(
    CHROMIUM is None or DRIVER is None,
    reason="no Chromium/chromedriver on this machine (apt-get install chromium chromium-driver)",
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _red_run(tmp_path) -> Path:
    """A one-step NeRF run whose field is opaque and pure red everywhere: whatever the camera,
    a rendered frame is red, and a blank page is not."""
    from warpnerf.cli.parser import main
    from warpnerf.outputs import load_checkpoint, save_checkpoint

    run = tmp_path / "red"
    assert main(["train", "nerf", "--data", "builtin", "--iters", "1", "--batch", "32",
                 "--samples", "8", "--layers", "2", "--width", "16", "--builtin-size", "16",
                 "--val-images", "0", "--quiet", "--no-tensorboard",
                 "--out", str(run)]) == 0  # fmt: skip
    ck = load_checkpoint(run / "checkpoint.pt")
    f = ck["fields"]["coarse"]
    f["color_out.weight"].zero_()
    f["color_out.bias"].copy_(torch.tensor([10.0, -10.0, -10.0]))
    f["sigma_head.weight"].zero_()
    f["sigma_head.bias"].fill_(20.0)
    save_checkpoint(run / "checkpoint.pt", ck)
    return run


@pytest.mark.slow
def test_view_page_shows_the_rendered_scene(tmp_path):
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    run = _red_run(tmp_path)
    port = _free_port()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "warpnerf.cli", "view", str(run), "--port", str(port),
         "--max-resolution", "256", "--exit-after", "240"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    driver, lines = None, []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()  # (the output, read as it comes: the URL with its token is printed first)
    try:
        deadline, url = time.time() + 90, None
        while url is None:  # the server is up once it prints its URL
            m = re.search(r"warpnerf view: (http://\S+)", "".join(lines))
            url = m.group(1) if m else None
            assert url is not None or proc.poll() is None, "".join(lines)
            assert time.time() < deadline, "the viewer did not print its URL"
            time.sleep(0.2)
        assert re.fullmatch(rf"http://localhost:{port}/\?token=[\w-]{{32,}}", url), url
        opts = webdriver.ChromeOptions()
        opts.binary_location = CHROMIUM
        for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                  "--window-size=1000,700", "--use-gl=angle", "--use-angle=swiftshader",
                  "--enable-unsafe-swiftshader"):  # fmt: skip
            opts.add_argument(a)
        driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
        driver.get(f"http://127.0.0.1:{port}")  # without the token: refused
        assert "needs its token" in driver.execute_script("return document.body.innerText")
        driver.get(url)
        deadline, text, shown = time.time() + 120, "", 0
        while time.time() < deadline:  # the panel's status line counts the frames shown
            text = driver.execute_script("return document.body.innerText")
            m = re.search(r"rendered frames: (\d+)", text)
            shown = int(m.group(1)) if m else 0
            if shown > 0:
                break
            time.sleep(0.5)
        assert shown > 0, text[:500]
        shot = Path(os.environ.get("WARPNERF_VIEWER_SHOT", tmp_path / "viewer.png"))
        import imageio.v3 as iio

        deadline = time.time() + 30  # the browser draws the frame it received (the first is
        while True:  # small and fast; a loaded machine's software WebGL may take seconds)
            time.sleep(1.0)
            driver.save_screenshot(str(shot))
            img = iio.imread(shot)[..., :3].astype(int)
            red = (img[..., 0] > 180) & (img[..., 1] < 80) & (img[..., 2] < 80)
            if red.mean() > 0.3 or time.time() > deadline:
                break
        # the rendered frame fills the background; the control panel covers about a third
        assert red.mean() > 0.3, f"only {red.mean():.1%} of the page shows the rendered scene"
        # the camera-path editor from the page: two keyframes of this view, saved in the run
        from selenium.webdriver.common.by import By

        def click(label):
            driver.find_element(By.XPATH, f"//button[contains(., '{label}')]").click()
            time.sleep(0.5)

        click("Add keyframe")
        click("Add keyframe")
        click("Save path")
        deadline = time.time() + 30
        while not (run / "camera_path.json").exists() and time.time() < deadline:
            time.sleep(0.5)
        from warpnerf.data.camera_path import load_camera_path

        path = load_camera_path(run / "camera_path.json")
        assert path.keyframes.shape == (2, 4, 4)
    finally:
        if driver is not None:
            driver.quit()
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
        took = time.perf_counter() - t0
        reader.join(10)
        out = "".join(lines)
    assert proc.returncode == 0, out
    assert "stopped after" in out
    assert took < 5.0, f"the viewer took {took:.1f} s to stop after Ctrl-C"
    # no noise: the port probes above and the browser leaving print no traceback or warning
    assert "Traceback" not in out and "Warning" not in out, out
    with socket.socket() as s:  # no leaked listener (SO_REUSEADDR: closed connections may linger)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()
    np.testing.assert_equal(proc.poll(), 0)
