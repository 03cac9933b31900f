"""The web dashboard (mll_server --http_address) in a real headless Chromium, driven over its
DevTools protocol on a pipe (--remote-debugging-pipe): the page lists environments created and
stepped by a client, and the live view of one receives frames that change as it steps. The last
screenshot is kept in the test's tmp dir (dashboard_list.png, dashboard_view.png)."""

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import threading
import time
import urllib.error
import urllib.request

import pytest

import multi_lunar_lander as mll
from mll_test_helpers import url_in_log

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = pytest.mark.skipif(
    not os.path.exists(CHROMIUM), reason="Debian's chromium is not installed (scripts/setup.sh)"
)
TIMEOUT_S = 30


class DevTools:
    """Chromium's DevTools protocol over --remote-debugging-pipe: JSON messages ended by NUL,
    commands on the child's fd 3, replies and events on its fd 4."""

    def __init__(self, user_data_dir):
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()
        # The child's ends above fd 9, so that moving them to 3 and 4 overwrites neither.
        to_child_r, from_child_w = (self._high(fd) for fd in (to_child_r, from_child_w))
        # bash (dash takes one-digit fds only) puts the pipes on fds 3 and 4 and execs the browser: no Python runs in the
        # forked child (grpcio is loaded in this process).
        command = (
            f'exec 3<&{to_child_r} 4>&{from_child_w} {to_child_r}<&- {from_child_w}>&-; '
            f'exec "$0" "$@"'
        )
        self._process = subprocess.Popen(
            ["/bin/bash", "-c", command, CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
             "--disable-dev-shm-usage",
             "--remote-debugging-pipe", f"--user-data-dir={user_data_dir}",
             "--window-size=1200,800", "about:blank"],
            pass_fds=(to_child_r, from_child_w),
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._next_id = 0
        self._buffer = b""

    @staticmethod
    def _high(fd):
        high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
        os.close(fd)
        return high

    def close(self):
        os.close(self._to_child)
        self._process.terminate()
        try:
            self._process.wait(10)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait()
        os.close(self._from_child)

    def call(self, method, params=None, session=None):
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_child, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            while b"\0" not in self._buffer:
                left = deadline - time.monotonic()
                assert left > 0, f"no reply to {method} within {TIMEOUT_S} s"
                ready, _, _ = select.select([self._from_child], [], [], left)
                if ready:
                    chunk = os.read(self._from_child, 1 << 20)
                    assert chunk, "chromium closed its DevTools pipe"
                    self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._next_id:
                assert "error" not in reply, f"{method}: {reply['error']}"
                return reply["result"]


class Page:
    def __init__(self, devtools, url):
        self.devtools = devtools
        target = devtools.call("Target.createTarget", {"url": url})["targetId"]
        self.session = devtools.call(
            "Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]

    def eval(self, expression):
        result = self.devtools.call(
            "Runtime.evaluate", {"expression": expression, "returnByValue": True},
            self.session)
        return result["result"].get("value")

    def wait_for(self, expression, what):
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline:
            value = self.eval(expression)
            if value:
                return value
            time.sleep(0.1)
        raise AssertionError(f"{what}: not within {TIMEOUT_S} s; page text: "
                             f"{self.eval('document.body.innerText')!r}")

    def screenshot(self, path):
        data = self.devtools.call("Page.captureScreenshot", {"format": "png"}, self.session)
        png = base64.b64decode(data["data"])
        assert png.startswith(b"\x89PNG")
        path.write_bytes(png)
        return png


def dashboard_url(server):
    return url_in_log(server, r"dashboard on (http://[\d.]+:\d+/)", TIMEOUT_S)


@pytest.fixture
def dashboard_server():
    with mll.ServerProcess(threads=2, extra_args=("--http_address=127.0.0.1:0",)) as server:
        yield server, dashboard_url(server)


@pytest.fixture
def browser(tmp_path):
    devtools = DevTools(tmp_path / "chromium-profile")
    yield devtools
    devtools.close()


def test_the_page_lists_envs_and_streams_frames_that_change(dashboard_server, browser, tmp_path):
    server, url = dashboard_server
    flying = mll.parallel_env(address=server.address, n_landers=3)
    waiting = mll.parallel_env(address=server.address, n_landers=2)
    try:
        flying.reset(seed=3)
        waiting.reset(seed=4)
        for _ in range(5):
            flying.step({agent: 0 for agent in flying.agents})

        page = Page(browser, url)
        listed = page.wait_for(
            "(() => { const names = [...document.querySelectorAll('#envs tr')]"
            ".map((tr) => tr.dataset.name);"
            f" return names.includes({json.dumps(flying.name)}) &&"
            f" names.includes({json.dumps(waiting.name)}) ? names : null; }})()",
            "both envs listed by name")
        assert len(listed) == 2
        row = page.eval(f"document.querySelector('tr[data-name=\"{flying.name}\"]').innerText")
        assert "\t3\t1\t5\t" in row, row  # landers, episode, step
        page.screenshot(tmp_path / "dashboard_list.png")

        # Open the flying env's live view, as a click on its row does, and keep it stepping.
        page.eval(f"document.querySelector('tr[data-name=\"{flying.name}\"]').click()")
        stop = threading.Event()

        def fly():
            observations = None
            while not stop.is_set():
                if not flying.agents:
                    observations, _ = flying.reset()
                actions = {agent: 2 for agent in flying.agents}
                observations, *_ = flying.step(actions)
                time.sleep(0.02)

        stepper = threading.Thread(target=fly)
        stepper.start()
        try:
            page.wait_for("Number(document.getElementById('frames').textContent) >= 3",
                          "three frames received")
            first = page.eval("[document.getElementById('frame').dataset.version,"
                              " document.getElementById('frame').src.length]")
            page.wait_for(
                f"document.getElementById('frame').dataset.version !== {json.dumps(first[0])}",
                "a newer frame")
            assert page.eval("document.getElementById('frame').naturalWidth") == 600
            assert page.eval("document.getElementById('frame').src.startsWith("
                             "'data:image/png;base64,')")
            png = page.screenshot(tmp_path / "dashboard_view.png")
            assert len(png) > 10_000
        finally:
            stop.set()
            stepper.join()
        versions = page.eval("document.getElementById('frame').dataset.version")
        assert versions.startswith(("1.", "2.", "3.")), versions
    finally:
        flying.close()
        waiting.close()


def test_with_auth_the_page_asks_for_a_token_and_shows_only_its_envs(tmp_path, browser):
    tokens = tmp_path / "tokens.txt"
    tokens.write_text("red-token\nblue-token\n")
    with mll.ServerProcess(threads=2, extra_args=(
            "--http_address=127.0.0.1:0", f"--auth_token_file={tokens}")) as server:
        url = dashboard_url(server)
        red = mll.parallel_env(address=server.address, n_landers=1, token="red-token")
        blue = mll.parallel_env(address=server.address, n_landers=1, token="blue-token")
        try:
            red.reset(seed=1)
            blue.reset(seed=2)
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(url + "api/envs", timeout=10)
            assert refused.value.code == 401

            page = Page(browser, url)
            page.wait_for("getComputedStyle(document.getElementById('login')).display !== 'none'",
                          "the token form")
            page.eval("document.getElementById('token').value = 'blue-token';"
                      " document.getElementById('login').requestSubmit()")
            names = page.wait_for(
                "(() => { const n = [...document.querySelectorAll('#envs tr')]"
                ".map((tr) => tr.dataset.name); return n.length ? n : null; })()",
                "the token's envs listed")
            assert names == [blue.name]
            page.screenshot(tmp_path / "dashboard_auth.png")
        finally:
            red.close()
            blue.close()
