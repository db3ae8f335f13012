"""The viewer's optional token (``--token``): with one, the server answers only requests that
carry it, as ``?token=…`` in the URL (the printed URL has it) or as the ``lidarloc_token_PORT``
cookie that such a request sets (named by the port: browsers share a host's cookies across its
ports, so two viewers on one machine keep a cookie each). The browser's websocket upgrade to the same origin sends that cookie
(the page's own script adds no query parameter to it), so the page keeps working while a request
without the token gets a short refusal and a websocket without it is never opened: no scene, no
GUI message ever reaches it.

Why it is done this way: viser has no hook for authentication. Its server
(``viser/infra/_infra.py``) calls ``websockets.asyncio.server.serve(..., process_request=…)`` on
its own thread, and ``ViserServer()`` returns only once that server is bound (it waits for the
thread's "ready"), so every ``serve`` call of a server happens while its constructor runs. For
that time only, :func:`start_server` replaces ``websockets.asyncio.server.serve`` with a function
that puts :func:`_gate` in front of viser's ``process_request`` (the one place websockets lets a
server answer the opening request of an HTTP page and of a websocket alike), and restores it
afterwards. A module lock keeps two starts from overlapping. Should a later viser no
longer call ``serve`` that way, the new server is stopped and :func:`start_server` raises: the
viewer never serves without the gate it was asked for.

The same hook paces new websocket connections, with or without a token
(:mod:`lidarloc.app.viewer.pacing`: a client reconnecting in a loop cannot take the filter's
CPU); without a token a viser that no longer calls ``serve`` that way serves unpaced.

While a server starts, any other ``websockets.asyncio.server.serve`` call in the process
would be hooked too; lidarloc starts no other websockets server meanwhile.
"""

from __future__ import annotations

import contextlib
import hmac
import http
import io
import os
import re
import secrets
import threading
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs, urlsplit

from ...core.errors import LidarlocError

if TYPE_CHECKING:
    import viser

#: Where the token may come from instead of the command line (so that it is not shown by ``ps``).
TOKEN_ENV = "LIDARLOC_VIEWER_TOKEN"
COOKIE = "lidarloc_token"  # … followed by "_" and the server's port
AUTO = "auto"
_URLSAFE = re.compile(r"[A-Za-z0-9_-]+")
REFUSAL = (
    "This lidarloc viewer needs its token.\n"
    "Open the URL printed in the terminal that started it (the one ending in ?token=...).\n"
)

_starting = threading.Lock()


def resolve_token(value: str | None, *, option: str = "--token") -> str | None:
    """The token to use: None (no gate), a fresh random one for ``auto``, or ``value`` itself if
    it is made of URL-safe base64 characters (A-Z a-z 0-9 - _); otherwise one-line LidarlocError."""
    if value is None:
        return None
    if value == AUTO:
        return secrets.token_urlsafe(16)
    if not value:
        raise LidarlocError(f"{option}: the token is empty (give a word of A-Z a-z 0-9 - _, or auto)")
    if not _URLSAFE.fullmatch(value):
        raise LidarlocError(f"{option}: a token may only have the characters A-Z a-z 0-9 - _ (or use auto)")
    return value


def token_from(value: str | None) -> str | None:
    """``--token``'s value, else the ``LIDARLOC_VIEWER_TOKEN`` environment variable's, resolved
    (:func:`resolve_token`); None when neither is given."""
    if value is not None:
        return resolve_token(value)
    env = os.environ.get(TOKEN_ENV)
    return None if env is None else resolve_token(env, option=TOKEN_ENV)


def with_token(url: str, token: str | None) -> str:
    """``url`` as the user opens it: with ``?token=…`` when there is a token."""
    return url if token is None else f"{url}/?token={token}"


def cookie_name(port: int) -> str:
    """The token's cookie for the viewer on ``port``."""
    return f"{COOKIE}_{int(port)}"


def _presented(request: Any, cookie: str) -> tuple[list[str], bool]:
    """The tokens a request carries (its query's ``token`` values, its ``cookie`` cookies) and
    whether one came in the query."""
    query = parse_qs(urlsplit(request.path).query).get("token", [])
    cookies = []
    for header in request.headers.get_all("Cookie"):
        for part in header.split(";"):
            name, eq, val = part.strip().partition("=")
            if eq and name == cookie:
                cookies.append(val.strip().strip('"'))
    return query + cookies, bool(query)


def _matches(token: bytes, candidates: list[str]) -> bool:
    ok = False
    for c in candidates:  # every candidate compared, in constant time each
        ok |= hmac.compare_digest(token, c.encode("utf-8"))
    return ok


def _gate(token: str, delegate: Callable[..., Any] | None) -> Callable[..., Any]:
    """A ``process_request`` that refuses what lacks ``token`` and hands the rest to ``delegate``
    (viser's own: its page for HTTP, None for a websocket upgrade), adding the cookie to the
    answer of a request that brought the token in its URL."""
    expected = token.encode("ascii")

    def process_request(connection: Any, request: Any) -> Any:
        name = cookie_name(connection.local_address[1])
        cookie = f"{name}={token}; HttpOnly; SameSite=Strict; Path=/"
        candidates, in_query = _presented(request, name)
        if not _matches(expected, candidates):
            return connection.respond(http.HTTPStatus.FORBIDDEN, REFUSAL)
        response = None if delegate is None else delegate(connection, request)
        if not in_query:
            return response
        if isinstance(response, Awaitable):

            async def with_cookie():
                answer = await response
                if answer is not None:
                    answer.headers["Set-Cookie"] = cookie
                return answer

            return with_cookie()
        if response is not None:
            response.headers["Set-Cookie"] = cookie
        return response

    return process_request


def start_server(token: str | None, **kwargs: Any) -> viser.ViserServer:
    """``viser.ViserServer(**kwargs)``, behind the token gate when ``token`` is given (see the
    module's docstring), its new websocket connections paced (its ``lidarloc_pacer``, a
    :class:`~lidarloc.app.viewer.pacing.ConnectionPacer`, counts them). LidarlocError if the gate
    could not be put in place."""
    import viser  # here, not at the top: the command line reads tokens without loading viser
    import websockets.asyncio.server as ws_server

    from .loop_wakeups import install
    from .pacing import ConnectionPacer

    install()  # the buffers of the server made below wake their readers on its loop only
    if token is not None and resolve_token(token) != token:  # "auto" must be resolved by the caller, who prints it
        raise ValueError("start_server needs the token itself, not auto")
    pacer = ConnectionPacer()
    with _starting:
        original = ws_server.serve
        gated = []

        def serve(*args: Any, **serve_kwargs: Any) -> Any:
            hook = serve_kwargs.get("process_request")
            if token is not None:
                hook = _gate(token, hook)
            serve_kwargs["process_request"] = pacer.in_front_of(hook)
            gated.append(True)
            return original(*args, **serve_kwargs)

        ws_server.serve = serve
        try:
            # viser's banner names the address without the token, a link that leads only to the
            # refusal: the caller prints the URL with the token instead
            with contextlib.redirect_stdout(io.StringIO()) if token is not None else contextlib.nullcontext():
                server = viser.ViserServer(**kwargs)
        finally:
            ws_server.serve = original
    server.lidarloc_pacer = pacer  # what it admitted, delayed and refused (benchmarks read it)
    if not gated and token is not None:
        server.stop()
        raise LidarlocError(
            f"--token: viser {viser.__version__} no longer starts its server through "
            "websockets.asyncio.server.serve, so the viewer cannot check the token; not serving"
        )
    return server
