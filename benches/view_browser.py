#!/usr/bin/env python3
"""Frame rate and input-to-frame latency of `texavatars view`, as a browser sees them.

Starts the viewer (the given binary and arguments), opens its page in headless Chromium
(driven over the DevTools protocol on a pipe: Python's standard library only), waits for the
first frame, then drags the jawOpen slider back and forth once per animation frame for
--seconds, as a user's hand would. Reported from the page's own records (window.viewer):
frames shown per second, and the latency from each input to the frame that shows it
(median, 90th percentile). Optionally saves a screenshot of the page.

    python3 benches/view_browser.py --bin target/release/texavatars --seconds 20 \
        --screenshot docs/images/view.png -- --checkpoint out/paper/run \
        --motion out/paper/data/union/transforms_test.json

Needs Chromium (`apt-get install chromium`; or --chromium PATH). Exits 0 with a message
when there is none.
"""
import argparse
import base64
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time


class Browser:
    """Headless Chromium with --remote-debugging-pipe (fd 3: commands in, fd 4: replies)."""

    def __init__(self, exe, width, height):
        cmd_r, self.cmd_w = os.pipe()
        self.res_r, res_w = os.pipe()
        self.profile = tempfile.mkdtemp(prefix="texavatars-view-bench-")

        def fds():
            os.dup2(cmd_r, 3)
            os.dup2(res_w, 4)

        self.proc = subprocess.Popen(
            [exe, "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
             "--no-first-run",
             f"--window-size={width},{height}", "--remote-debugging-pipe",
             f"--user-data-dir={self.profile}", "about:blank"],
            preexec_fn=fds, close_fds=False,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(cmd_r)
        os.close(res_w)
        self.buf = b""
        self.next = 1
        self.session = None

    def call(self, method, params=None, page=True):
        mid = self.next
        self.next += 1
        msg = {"id": mid, "method": method, "params": params or {}}
        if page and self.session:
            msg["sessionId"] = self.session
        os.write(self.cmd_w, json.dumps(msg).encode() + b"\0")
        while True:
            while b"\0" not in self.buf:
                chunk = os.read(self.res_r, 1 << 20)
                if not chunk:
                    raise RuntimeError("chromium closed its DevTools pipe")
                self.buf += chunk
            raw, self.buf = self.buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == mid:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def open(self, url):
        target = self.call("Target.createTarget", {"url": url}, page=False)["targetId"]
        self.session = self.call("Target.attachToTarget",
                                 {"targetId": target, "flatten": True}, page=False)["sessionId"]

    def eval(self, expression, wait=False):
        r = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                           "awaitPromise": wait})
        return r["result"].get("value")

    def until(self, expression, timeout=120):
        start = time.time()
        while self.eval(expression) is not True:
            if time.time() - start > timeout:
                raise RuntimeError(f"waited {timeout} s for {expression}")
            time.sleep(0.1)

    def close(self):
        self.proc.kill()
        self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)


# Drags jawOpen between 0 and 1 once per animation frame for `ms`, then resolves.
SWEEP = """
new Promise((done) => {
  const input = document.querySelector('input[data-name="jawOpen"]');
  const start = performance.now();
  const first = window.viewer.latencies.length;
  function step(now) {
    const t = (now - start) / 1000;
    input.value = String(0.5 - 0.5 * Math.cos(2 * Math.PI * t / 2));
    input.dispatchEvent(new Event('input'));
    if (now - start < %d) requestAnimationFrame(step);
    else setTimeout(() => done({ first, end: performance.now(), start }), 1500);
  }
  requestAnimationFrame(step);
})
"""


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bin", default="target/release/texavatars")
    ap.add_argument("--chromium", default=None)
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--window", default="1280x900", help="browser window, WxH")
    ap.add_argument("--scale", default="1", help="the page's size setting: 1, 0.75 or 0.5")
    ap.add_argument("--screenshot", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("view_args", nargs="*", help="arguments of `texavatars view` after --")
    a = ap.parse_args()
    exe = a.chromium or next((c for c in ("chromium", "chromium-browser", "google-chrome")
                              if shutil.which(c)), None)
    if not exe:
        print("skipped: no chromium on the PATH (apt-get install chromium)")
        return 0
    port = free_port()
    server = subprocess.Popen([a.bin, "view", "--port", str(port), *a.view_args],
                              stdout=subprocess.PIPE, text=True)
    line = server.stdout.readline()
    while line and "open http" not in line:
        print(line.rstrip())
        line = server.stdout.readline()
    if not line:
        print("the viewer did not start", file=sys.stderr)
        return 1
    print(line.rstrip())
    w, h = (int(v) for v in a.window.split("x"))
    b = Browser(exe, w, h)
    try:
        b.open(f"http://127.0.0.1:{port}/")
        b.until("!!(window.viewer && window.viewer.ready && window.viewer.framesShown >= 1)")
        b.eval(f"(() => {{ const s = document.getElementById('scale'); s.value = '{a.scale}'; "
               "s.dispatchEvent(new Event('change')); return true; })()")
        time.sleep(2)
        r = b.eval(SWEEP % int(a.seconds * 1000), wait=True)
        lat = b.eval(f"window.viewer.latencies.slice({r['first']})")
        shown = b.eval(f"window.viewer.shownAt.slice({r['first']})")
        header = b.eval("window.viewer.lastHeader")
        span = (shown[-1] - shown[0]) / 1000 if len(shown) > 1 else float("nan")
        fps = (len(shown) - 1) / span if len(shown) > 1 else 0.0
        lat_sorted = sorted(lat)
        report = {
            "frames": len(lat),
            "seconds": round(span, 2),
            "fps": round(fps, 2),
            "latency_median_ms": round(statistics.median(lat_sorted), 1),
            "latency_p90_ms": round(lat_sorted[int(0.9 * (len(lat_sorted) - 1))], 1),
            "size": [header["width"], header["height"]],
            "gaussians": header["gaussians"],
            "stages_ms": header["timings_ms"]["stages"],
            "dropped": header["dropped"],
        }
        print(json.dumps(report))
        if a.json:
            with open(a.json, "w") as f:
                json.dump(report, f, indent=2)
        if a.screenshot:
            # A dataset motion: its middle camera at motion frame 1, with the ground truth.
            b.eval("(() => { const p = document.getElementById('preset'); "
                   "if (p.options.length > 1 && !p.disabled) { "
                   "p.value = p.options[1 + Math.floor((p.options.length - 1) / 2)].value; "
                   "p.dispatchEvent(new Event('change')); } "
                   "const s = document.getElementById('scrub'); s.value = '1'; "
                   "s.dispatchEvent(new Event('input')); return true; })()")
            time.sleep(4)
            png = b.call("Page.captureScreenshot", {"format": "png"})["data"]
            with open(a.screenshot, "wb") as f:
                f.write(base64.b64decode(png))
            print(f"screenshot: {a.screenshot}")
    finally:
        b.close()
        server.terminate()
        server.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
