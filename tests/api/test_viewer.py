"""GET /viewer in a real browser (Debian's chromium, headless, driven by Playwright): the demo
mode streams by itself and the watch mode follows a session posted to over HTTP (acknowledging
the frames it draws); in both the frame counter grows with no error, and the picture is not
blank and changes as frames arrive.
Screenshots are kept under the test's tmp folder (and /tmp/elastreg-viewer-*.png) to look at."""

from __future__ import annotations

import io
import logging
import re
import shutil
import threading
import time

import numpy as np
import pytest

from ..conftest import IN_CI

CHROMIUM = shutil.which("chromium")
if IN_CI and CHROMIUM is None:  # .ci/run installs it: a skip there would hide a broken page
    pytest.fail("Debian's chromium is not installed (CI=true: .ci/run installs it)", pytrace=False)
playwright = pytest.importorskip("playwright.sync_api")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")
ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking"]


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        yield b
        b.close()


def state(page) -> dict:
    return page.evaluate("() => ({...window.elastregViewer, renderLog: undefined})")


def wait_frames(page, at_least: int, timeout: float = 90) -> dict:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        s = state(page)
        assert s["lastError"] is None, s["lastError"]
        if s["framesRendered"] >= at_least:
            return s
        time.sleep(0.2)
    raise AssertionError(f"only {state(page)['framesRendered']} frames rendered in {timeout} s")


def picture(page, path) -> np.ndarray:
    from PIL import Image

    png = page.screenshot(path=str(path))
    shutil.copy(path, f"/tmp/elastreg-viewer-{path.name}")
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float64)


def check_pictures(a: np.ndarray, b: np.ndarray) -> None:
    # the 3D view (right of the panel), not blank: many colours and a real spread of brightness
    for img in (a, b):
        view = img[:, 330:]
        assert view.std() > 10 and len(np.unique(view.reshape(-1, 3), axis=0)) > 200
    changed = np.abs(a[:, 330:] - b[:, 330:]).max(axis=2) > 8
    assert changed.mean() > 0.002, f"only {changed.mean():.4%} of the view changed between frames"


def test_demo_mode_renders_frames(live, browser, tmp_path):
    page = browser.new_page(viewport={"width": 960, "height": 640})
    page.goto(f"{live.url}/viewer?model=bar&demo=1&frames=12&points=200&rate=10")
    s = wait_frames(page, 4)
    assert s["mode"] == "demo" and s["session"].startswith("alpha-")
    assert s["pointsShown"] == 200
    a = picture(page, tmp_path / "demo-1.png")
    assert s["displacementShown"] and not page.is_visible("#notice")
    assert page.text_content("#legend-hi").endswith(" mm")
    wait_frames(page, s["framesRendered"] + 5)
    b = picture(page, tmp_path / "demo-2.png")
    check_pictures(a, b)
    page.close()


def test_watch_mode_follows_a_session(live, http, browser, support, clouds, tmp_path, caplog):
    caplog.set_level(logging.DEBUG, logger="service.api.routes.watch")  # its last line: the acks taken
    sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
    page = browser.new_page(viewport={"width": 960, "height": 640})
    page.goto(f"{live.url}/viewer?session={sid}#token=not-needed-here")
    page.wait_for_function(
        "() => window.elastregViewer.model === 'bar' || window.elastregViewer.lastError",
        timeout=60_000,
    )
    stop = threading.Event()

    def post():
        t = 0
        while not stop.is_set():
            http.post(
                f"/sessions/{sid}/frames",
                json={"points": clouds[t % len(clouds)].tolist(), "frame_id": t},
            )
            t += 1
            time.sleep(0.1)

    poster = threading.Thread(target=post)
    poster.start()
    try:
        s = wait_frames(page, 3)
        assert s["mode"] == "watch" and s["session"] == sid
        a = picture(page, tmp_path / "watch-1.png")
        s2 = wait_frames(page, s["framesRendered"] + 4)
        b = picture(page, tmp_path / "watch-2.png")
        assert s2["lastSeq"] > s["lastSeq"]
        assert s2["lastAck"] >= s["lastSeq"]  # it acknowledges what it has drawn
    finally:
        stop.set()
        poster.join()
    check_pictures(a, b)
    page.close()

    def acked() -> int | None:
        for rec in caplog.records:
            m = re.search(rf"watcher of {sid}: .* acknowledged up to (\d+)", rec.getMessage())
            if m:
                return int(m.group(1))
        return None

    deadline = time.monotonic() + 10
    while acked() is None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert (acked() or 0) >= s["lastSeq"], "the server took no acks from the viewer"
    http.delete(f"/sessions/{sid}")


def test_a_session_without_displacements_is_shown_at_rest_and_said_so(live, http, browser, support, clouds):
    """A session whose outputs leave displacements out (`outputs: ["forces"]`): the page drew the
    rest shape with no word of it and a colour scale of "0 - 1000.00 mm" (1 m, for no range at
    all). It says the session returns no displacements and claims no range."""
    config = {"model": "bar", "support": support.tolist(), "outputs": ["forces"]}
    sid = http.post("/sessions", json=config).json()["session"]
    page = browser.new_page(viewport={"width": 640, "height": 480})
    page.goto(f"{live.url}/viewer?session={sid}")
    page.wait_for_function("() => window.elastregViewer.model === 'bar' || window.elastregViewer.lastError")
    for t in range(2):  # each drawn before the next: a watcher behind gets only the newest
        r = http.post(f"/sessions/{sid}/frames", json={"points": clouds[t + 3].tolist()})
        assert r.status_code == 200 and "displacement" not in r.json() and "surface_displacement" not in r.json()
        s = wait_frames(page, t + 1)
    legend = page.text_content("#legend")
    assert "1000" not in legend and "mm" not in legend, legend  # no range: it has none
    assert page.is_visible("#notice")
    assert "does not return displacements" in page.text_content("#notice")
    assert s.get("displacementShown") is False
    assert s["arrowsShown"] > 0  # the forces it asked for are drawn
    page.close()
    http.delete(f"/sessions/{sid}")


def test_a_hidden_watch_page_acknowledges_what_it_cannot_draw(live, http, browser, support, clouds):
    """A hidden tab gets no animation frames, so it draws nothing; it acknowledges each frame as
    it arrives, or its window would stay full and the server would close it."""
    sid = http.post("/sessions", json={"model": "bar", "support": support.tolist()}).json()["session"]
    page = browser.new_page(viewport={"width": 640, "height": 480})
    page.goto(f"{live.url}/viewer?session={sid}")
    page.wait_for_function("() => window.elastregViewer.model === 'bar' || window.elastregViewer.lastError")
    http.post(f"/sessions/{sid}/frames", json={"points": clouds[0].tolist()})
    drawn = wait_frames(page, 1)["framesRendered"]
    # hidden, as a background tab is: no more animation frames, document.hidden true
    page.evaluate(
        "() => { window.requestAnimationFrame = () => 0;"
        " Object.defineProperty(document, 'hidden', {configurable: true, get: () => true}); }"
    )
    time.sleep(0.2)  # an animation frame already scheduled may still run once
    drawn = state(page)["framesRendered"]
    for t in range(1, 7):
        http.post(f"/sessions/{sid}/frames", json={"points": clouds[t % len(clouds)].tolist()})
    page.wait_for_function("() => window.elastregViewer.lastAck >= 7", timeout=30_000)
    s = state(page)
    assert s["framesRendered"] == drawn and s["lastError"] is None  # acknowledged, not drawn
    page.close()
    http.delete(f"/sessions/{sid}")


def test_a_watch_that_the_server_ends_is_an_error(bar_store, browser):
    """The server going away under a watching page (a restart, a crash) ended its socket with a
    code other than 1000; the page wrote "closed (1012)" where the status goes and left lastError
    null, so a test or a tool polling it saw a healthy page that would never draw again."""
    import httpx

    from .conftest import start

    server = start(bar_store[0], instance_id="going")
    try:
        sid = httpx.post(f"{server.url}/sessions", json={"model": "bar"}).json()["session"]
        page = browser.new_page(viewport={"width": 640, "height": 480})
        page.goto(f"{server.url}/viewer?session={sid}")
        page.wait_for_function("() => window.elastregViewer.model === 'bar' || window.elastregViewer.lastError")
        assert state(page)["lastError"] is None
    finally:
        server.stop()
    page.wait_for_function("() => window.elastregViewer.lastError !== null", timeout=30_000)
    assert "closed" in state(page)["lastError"]
    page.close()


def test_a_token_holding_plus_reaches_the_server_as_it_is_or_percent_encoded(bar_store, browser):
    """The page read #token= as a form (URLSearchParams): a base64 token's '+' became a space and
    the server refused it (401). Written as it is, or percent-encoded (as `elastreg demo --viewer`
    writes it), the token the page sends is the one given."""
    from urllib.parse import quote

    import httpx

    from .conftest import start

    token = "plus+slash/Token=Base64xx"
    server = start(bar_store[0], instance_id="plus", api_tokens=token)
    try:
        auth = {"authorization": f"Bearer {token}"}
        sid = httpx.post(f"{server.url}/sessions", json={"model": "bar"}, headers=auth).json()["session"]
        for fragment in (token, quote(token, safe="")):
            page = browser.new_page(viewport={"width": 640, "height": 480})
            page.goto(f"{server.url}/viewer?session={sid}#token={fragment}")
            page.wait_for_function("() => window.elastregViewer.model === 'bar' || window.elastregViewer.lastError")
            s = state(page)
            assert s["lastError"] is None and s["session"] == sid, (fragment, s["lastError"])
            page.close()
    finally:
        server.stop()


def test_the_demo_goes_on_after_a_frame_refused_under_overload(bar_store, browser, clouds):
    """Under overload a stream's frame gets error 503 with retry_after and the stream stays open
    (API.md); the demo took it for a fatal error and never sent another frame. It says the server
    is busy and sends again after retry_after: its frame count grows once the load has gone."""
    import httpx

    from .conftest import start

    # one solver thread and one place in its queue (the page's start fetches two things in the
    # pool at once): with three other sessions' FEM frames going, the demo's frames meet a full pool
    server = start(bar_store[0], instance_id="busy", solver_threads=1, solve_queue=1)
    stop = threading.Event()
    clients = [httpx.Client(base_url=server.url, timeout=60) for _ in range(3)]
    try:
        # opened before the demo starts: opening a session needs the solver thread too
        sids = [c.post("/sessions", json={"model": "bar", "method": "fem"}).json()["session"] for c in clients]
        page = browser.new_page(viewport={"width": 640, "height": 480})
        page.goto(f"{server.url}/viewer?model=bar&demo=1&frames=8&points=200&rate=20")
        wait_frames(page, 2)

        def load(client: httpx.Client, sid: str) -> None:  # another session's FEM frames, back to back
            t = 0
            while not stop.is_set():
                client.post(f"/sessions/{sid}/frames", json={"points": clouds[t % len(clouds)].tolist()})
                t += 1

        threads = [threading.Thread(target=load, args=(c, sid)) for c, sid in zip(clients, sids, strict=True)]
        for t in threads:
            t.start()
        try:
            page.wait_for_function(
                "() => window.elastregViewer.overloads > 0 || window.elastregViewer.lastError", timeout=60_000
            )
        finally:
            stop.set()
            for t in threads:
                t.join()
        s = state(page)
        assert s["lastError"] is None, s["lastError"]
        assert "capacity" in s["lastOverload"]
        wait_frames(page, s["framesRendered"] + 5, timeout=30)  # sent again, and on it goes
        page.close()
    finally:
        for c in clients:
            c.close()
        server.stop()


def test_the_page_asks_again_for_what_a_busy_pool_refused(bar_store, browser):
    """The page's start-up requests (the mesh, the demo sequence) go through the solve pool; on
    a server whose pool is busy they were refused (503) and the page stopped with that error.
    It now asks again after Retry-After: a page opened while the only solver thread is held and
    the pool has no queue is refused, then starts its demo once the thread is free."""
    from .conftest import occupied, start

    server = start(bar_store[0], instance_id="full", solver_threads=1, solve_queue=0)
    try:
        page = browser.new_page(viewport={"width": 640, "height": 480})
        with occupied(server.app.state.pool, 1):  # the one thread taken before the page asks
            page.goto(f"{server.url}/viewer?model=bar&demo=1&frames=4&points=200&rate=20")
            page.wait_for_function(
                "() => window.elastregViewer.overloads > 0 || window.elastregViewer.lastError", timeout=60_000
            )
        wait_frames(page, 2)
        s = state(page)
        assert s["lastError"] is None and s["overloads"] > 0, s
        page.close()
    finally:
        server.stop()
