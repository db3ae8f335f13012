"""`lidarloc demo` as a user starts it: prints its URL, serves HTTP 200 on loopback, and ends
within 2 s of Ctrl-C."""

import os
import re
import signal
import subprocess
import sys
import time
import urllib.request


def test_demo_serves_and_stops_on_ctrl_c(tmp_path):
    env = dict(os.environ, LIDARLOC_CACHE=str(tmp_path / "cache"))
    # a short drive keeps the first (uncached) start of this test quick; the default town's
    # first-start time is measured in BENCHMARKS.md
    proc = subprocess.Popen([sys.executable, "-m", "lidarloc.app.cli", "demo", "--port", "0", "--scans", "30"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        url, seen = None, ""
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and url is None:
            line = proc.stdout.readline()
            if not line:
                break
            seen += line
            m = re.search(r"lidarloc viewer: (http://[\w.\-]+:\d+)", line)
            if m:
                url = m.group(1)
        assert url is not None, seen
        assert url.startswith("http://127.0.0.1:"), "binds loopback by default"
        status = None
        while time.monotonic() < deadline and status is None:
            try:
                status = urllib.request.urlopen(url, timeout=5).status
            except OSError:
                time.sleep(0.2)  # retry pacing while the server comes up, not synchronisation
        assert status == 200
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        proc.wait(timeout=30)
        assert time.monotonic() - t0 <= 2.0, f"stopped after {time.monotonic() - t0:.2f} s"
        assert proc.returncode == 0
    finally:
        if proc.poll() is None:
            proc.kill()
