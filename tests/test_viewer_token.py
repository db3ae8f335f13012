"""The viewer's token (``--token``): with one, every page request and every websocket must bring
it (``?token=`` in the URL, or the cookie that URL sets) or be refused before any scene or GUI
message is sent; without one, the viewer answers as it always did. The real server, on a free
port; the command line's checks of a bad token; one real browser at the end."""

from __future__ import annotations

import http.client
import io
import subprocess
import sys

import pytest
from helpers import make_localizer

TOKEN = "s3cret-Token_0123456789"


def cookie(port: int, token: str = TOKEN) -> str:
    """The token's cookie as the browser sends it to the viewer on ``port``."""
    return f"lidarloc_token_{port}={token}"


def get(port: int, path: str = "/", headers: dict | None = None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.request("GET", path, headers=headers or {})
        resp = conn.getresponse()
        return resp.status, resp.getheader("Set-Cookie"), resp.read()
    finally:
        conn.close()


def ws_connect(port: int, headers: dict | None = None):
    """A websocket as viser's page opens it (its subprotocol), or the refusal's status code."""
    import viser
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    try:
        return connect(
            f"ws://127.0.0.1:{port}",
            subprotocols=[f"viser-v{viser.__version__}"],
            additional_headers=headers,
            open_timeout=10,
            max_size=None,
        )
    except InvalidStatus as exc:
        return exc.response.status_code


@pytest.fixture(scope="module")
def localizer(tmp_path_factory):
    from helpers import StreetSequence

    loc = make_localizer(StreetSequence(), tmp_path_factory.mktemp("token-cache"))
    yield loc
    loc.close()


@pytest.fixture(scope="module")
def gated(localizer):
    from lidarloc.app.viewer.serve import serve

    handle = serve(localizer, port=0, autoplay=False, token=TOKEN)
    yield handle
    handle.stop()


# ------------------------------------------------------------------------------ HTTP
def test_a_page_request_without_the_token_is_refused_with_a_short_note(gated):
    status, cookie, body = get(gated.port)
    assert status in (401, 403) and cookie is None
    assert b"<html" not in body.lower() and b"<script" not in body.lower() and len(body) < 300
    assert b"needs its token" in body and b"URL printed in the terminal" in body
    # nor any other file of the page
    assert get(gated.port, "/index.html")[0] in (401, 403)


def test_the_printed_url_opens_the_page_and_sets_the_cookie(gated):
    assert gated.url == f"http://127.0.0.1:{gated.port}/?token={TOKEN}"
    status, set_cookie, body = get(gated.port, f"/?token={TOKEN}")
    assert status == 200 and b"<html" in body.lower()
    assert set_cookie is not None
    parts = [p.strip() for p in set_cookie.split(";")]
    assert parts[0] == cookie(gated.port) and {"HttpOnly", "SameSite=Strict", "Path=/"} <= set(parts[1:])
    # the cookie alone then opens it (what the browser sends from then on)
    status, _, body = get(gated.port, "/", {"Cookie": f"other=1; {cookie(gated.port)}"})
    assert status == 200 and b"<html" in body.lower()
    # another viewer's cookie on the same host (another port) does not
    status, _, body = get(gated.port, "/", {"Cookie": cookie(gated.port + 1)})
    assert status in (401, 403)


@pytest.mark.parametrize(
    "path, headers",
    [
        (f"/?token={TOKEN[:-1]}", None),
        (f"/?token={TOKEN}x", None),
        ("/?token=", None),
        ("/", {"Cookie": f"lidarloc_token={TOKEN}"}),  # without the port
        ("/", {"Cookie": f"not_lidarloc_token={TOKEN}"}),
        ("/", {"Authorization": f"Bearer {TOKEN}"}),
    ],
    ids=["short", "longer", "empty", "portless-cookie", "other-cookie", "header"],
)
def test_a_wrong_token_is_refused(gated, path, headers):
    status, cookie, body = get(gated.port, path, headers)
    assert status in (401, 403) and cookie is None and b"<html" not in body.lower()


# ------------------------------------------------------------------------------ websocket
def test_a_websocket_without_the_cookie_is_refused_and_gets_nothing(gated):
    clients_before = len(gated.server.get_clients())
    assert ws_connect(gated.port) in (401, 403)
    assert ws_connect(gated.port, {"Cookie": cookie(gated.port, TOKEN[:-1])}) in (401, 403)
    assert len(gated.server.get_clients()) == clients_before  # never became a client


def test_a_websocket_with_the_cookie_is_accepted_and_gets_the_scene(gated):
    ws = ws_connect(gated.port, {"Cookie": cookie(gated.port)})
    assert not isinstance(ws, int), f"refused with {ws}"
    with ws:
        assert len(ws.recv(timeout=10)) > 0  # viser's first messages


# ------------------------------------------------------------------------------ no token
def test_without_a_token_the_viewer_answers_as_before(localizer):
    from lidarloc.app.viewer.serve import serve

    handle = serve(localizer, port=0, autoplay=False)
    try:
        assert handle.url == f"http://127.0.0.1:{handle.port}" and handle.token is None
        status, cookie, body = get(handle.port)
        assert status == 200 and cookie is None and b"<html" in body.lower()
        ws = ws_connect(handle.port)
        assert not isinstance(ws, int), f"refused with {ws}"
        with ws:
            assert len(ws.recv(timeout=10)) > 0
    finally:
        handle.stop()


# ------------------------------------------------------------------------------ the gate itself
def test_auto_gives_a_fresh_url_safe_token_each_time():
    from lidarloc.app.viewer.token_gate import resolve_token

    a, b = resolve_token("auto"), resolve_token("auto")
    assert a != b and a is not None and len(a) >= 22
    assert set(a) <= set("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789-_")
    assert resolve_token(None) is None and resolve_token(TOKEN) == TOKEN


def test_a_gated_server_prints_no_address_without_its_token(capsys):
    from lidarloc.app.viewer.token_gate import start_server

    server = start_server(TOKEN, host="127.0.0.1", port=0, verbose=False)
    try:
        assert "http://" not in capsys.readouterr().out  # viser's banner: a link that would be refused
        assert get(server.get_port())[0] in (401, 403)
    finally:
        server.stop()


def test_a_viser_that_no_longer_starts_through_websockets_serve_is_an_error(monkeypatch):
    """Nothing may serve without the gate it was asked for: a server started some other way is
    stopped and the start fails."""
    import viser
    import websockets.asyncio.server as ws_server
    from lidarloc.app.viewer.token_gate import start_server
    from lidarloc.core.errors import LidarlocError

    original = ws_server.serve
    stopped = []

    class ServerOfAnotherKind:
        def __init__(self, **kwargs):
            pass

        def stop(self):
            stopped.append(True)

    monkeypatch.setattr(viser, "ViserServer", ServerOfAnotherKind)
    with pytest.raises(LidarlocError, match="cannot check the token"):
        start_server(TOKEN, host="127.0.0.1", port=0)
    assert stopped == [True]
    assert ws_server.serve is original  # websockets is left as it was


def test_the_console_names_the_token_url_and_suggests_one_when_bound_beyond_loopback():
    from types import SimpleNamespace

    from lidarloc.app.viewer.serve import announce
    from rich.console import Console

    def said(host, token):
        out = io.StringIO()
        url = f"http://localhost:8080/?token={token}" if token else "http://localhost:8080"
        announce(SimpleNamespace(url=url, port=8080, token=token), host, Console(file=out, width=60))
        return out.getvalue()

    assert "warning: --host 0.0.0.0: anyone who can reach port 8080" in said("0.0.0.0", None)
    assert "--token auto" in said("0.0.0.0", None)
    with_token = said("0.0.0.0", TOKEN)
    assert f"http://localhost:8080/?token={TOKEN}" in with_token.replace("\n", "")
    assert "anyone who can reach" not in with_token
    assert "--token" not in said("127.0.0.1", None) and "warning" not in said("127.0.0.1", None)


# ------------------------------------------------------------------------------ command line
def _cli(*args, env_token=None):
    env = {"PATH": "/usr/bin:/bin", "LIDARLOC_CACHE": "/nonexistent-lidarloc-cache"}
    if env_token is not None:
        env["LIDARLOC_VIEWER_TOKEN"] = env_token
    return subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", *args], capture_output=True, text=True, env=env, timeout=120
    )


@pytest.mark.parametrize(
    "args, env_token, needle",
    [
        (["demo", "--token", ""], None, "--token: the token is empty"),
        (["demo", "--token", "has space"], None, "--token: a token may only have"),
        (["view", "--run", "nowhere", "--token", "pa=ss"], None, "--token: a token may only have"),
        (["demo"], "tok/en", "LIDARLOC_VIEWER_TOKEN: a token may only have"),
        (["demo"], "", "LIDARLOC_VIEWER_TOKEN: the token is empty"),
    ],
    ids=["empty", "space", "view-run", "env", "env-empty"],
)
def test_a_bad_token_is_one_line_and_exit_2_before_anything_starts(args, env_token, needle):
    r = _cli(*args, env_token=env_token)
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    assert needle in lines[0], lines[0]
    assert "lidarloc viewer:" not in r.stdout + r.stderr


@pytest.mark.parametrize("command", ["demo", "view"])
def test_the_token_reaches_the_viewer_from_the_option_or_the_environment(command, monkeypatch):
    from helpers import viewer_options

    monkeypatch.delenv("LIDARLOC_VIEWER_TOKEN", raising=False)
    assert viewer_options(command, [], monkeypatch)["token"] is None
    assert viewer_options(command, ["--token", TOKEN], monkeypatch)["token"] == TOKEN
    auto = viewer_options(command, ["--token", "auto"], monkeypatch)["token"]
    assert auto not in (None, "auto") and len(auto) >= 22
    monkeypatch.setenv("LIDARLOC_VIEWER_TOKEN", TOKEN)
    assert viewer_options(command, [], monkeypatch)["token"] == TOKEN
    assert viewer_options(command, ["--token", "other"], monkeypatch)["token"] == "other"  # the option wins


def test_view_run_hands_the_token_to_the_recorded_runs_viewer(monkeypatch, tmp_path):
    from lidarloc.app import cli
    from lidarloc.app.viewer import runs
    from typer.testing import CliRunner

    seen: dict = {}
    monkeypatch.setattr(runs, "serve_runs", lambda run_dirs, **kwargs: seen.update(kwargs))
    monkeypatch.delenv("LIDARLOC_VIEWER_TOKEN", raising=False)
    result = CliRunner().invoke(cli.app, ["view", "--run", str(tmp_path), "--token", TOKEN])
    assert result.exit_code == 0, result.output
    assert seen["token"] == TOKEN


def test_help_offers_the_token_on_every_viewer_command():
    for command in ("demo", "view"):
        r = _cli(command, "--help")
        assert r.returncode == 0 and "--token" in r.stdout and "LIDARLOC_VIEWER_TOKEN" in r.stdout, r.stdout


# ------------------------------------------------------------------------------ a real browser
@pytest.mark.browser
def test_the_printed_url_opens_the_viewer_in_a_browser_and_the_bare_one_does_not(browser, gated):
    from browser import LOAD_TIMEOUT

    # the panel's status line ("Scan – of 24 · paused …"), sent over the websocket
    status_shown = "/Scan \\S+ of \\d+/.test(document.body.innerText)"

    context = browser.new_context()
    try:
        page = context.new_page()
        page.goto(f"http://127.0.0.1:{gated.port}/", timeout=LOAD_TIMEOUT)
        assert "needs its token" in page.inner_text("body")
        assert page.query_selector("canvas") is None
        page.goto(gated.url, timeout=LOAD_TIMEOUT)  # the printed URL: the websocket brings the cookie
        page.wait_for_function(status_shown, timeout=LOAD_TIMEOUT)
        assert any(c["name"] == f"lidarloc_token_{gated.port}" and c["httpOnly"] for c in context.cookies())
        fresh = browser.new_context()  # another browser: no cookie
        try:
            other = fresh.new_page()
            other.goto(f"http://127.0.0.1:{gated.port}/", timeout=LOAD_TIMEOUT)
            assert "needs its token" in other.inner_text("body")
        finally:
            fresh.close()
    finally:
        context.close()
