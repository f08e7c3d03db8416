"""Who may use the dashboard: an ASGI guard in front of every route.

- The access token (made at start with secrets.token_urlsafe, or given: check_token refuses a weak
  one) is presented once, as `/?token=...` in the URL ccrp printed. The guard answers with a
  redirect to `/` without it, and a session cookie (HttpOnly, SameSite=Strict, one name per port):
  a random session id, not the token, so the token is in no cookie, page, event or log line.
- A client address that sent TOKEN_FAILURES_ALLOWED wrong tokens within TOKEN_FAILURE_WINDOW_S
  gets 429 (with Retry-After) for any token until the oldest of them is that old.
- A session ends after SESSION_IDLE_S without a request, and SESSION_MAX_S after it opened in any
  case; an event stream open with it ends too. POST /api/logout ends it at once.
- Every request needs that session (401 without), and a Host this server answers to (403: a DNS
  rebinding page sends its own name).
- Only GET, HEAD and POST exist. A POST changes state: it needs the session, an Origin (or, without
  one, a Referer) of this very server, and the session's CSRF token in the X-CCRP-CSRF header
  (403). The CSRF token is in the page (a meta tag), bound to its session, worthless without the
  cookie.
- Responses carry a Content-Security-Policy allowing only this server's scripts, no framing, no
  referrer, no caching.
- Only HTTP reaches the app: a websocket is closed (1008) before it, whatever it carries; the
  lifespan (the server's start and stop) passes.
- The access log is this guard's: method, path (never the query string), status.
"""

from __future__ import annotations

import hmac
import logging
import math
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from http.cookies import SimpleCookie
from urllib.parse import parse_qs, urlsplit

from ..errors import InputError

log = logging.getLogger("ccrp.dashboard")

CSRF_HEADER = "x-ccrp-csrf"
MAX_SESSIONS = 64
# A session unused this long ends (a page left open, a browser walked away from); none outlives
# the second, however busy: a stolen cookie is worth hours, not the server's whole life.
SESSION_IDLE_S = 30 * 60
SESSION_MAX_S = 12 * 3600
# Wrong tokens one client address may send within the window; then it waits. The token's entropy
# is the defence; this slows a guesser to a few tries a minute per address, and says on stderr that
# one is at it. The addresses kept are bounded: a flood of them cannot fill the memory.
TOKEN_FAILURES_ALLOWED = 5
TOKEN_FAILURE_WINDOW_S = 60
MAX_CLIENTS_KEPT = 1024
# A token given with --token: at least this long, and not a few characters repeated (16 times "a"
# passed the length alone). A random 16-character one passes (hex: 99 times in 100).
MIN_TOKEN_CHARS = 16
MIN_TOKEN_DISTINCT = 8
SECURITY_HEADERS = [
    (b"content-security-policy",
     b"default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' data:; connect-src 'self'; "
     b"base-uri 'none'; form-action 'none'; frame-ancestors 'none'"),
    (b"x-frame-options", b"DENY"),
    (b"x-content-type-options", b"nosniff"),
    (b"referrer-policy", b"no-referrer"),
    (b"cache-control", b"no-store"),
]
LOGIN_PAGE = (b"<!doctype html><meta charset=utf-8><title>ccrp dashboard</title>"
              b"<p>This dashboard needs its access token: open the URL that <code>ccrp dashboard</code> "
              b"printed when it started (it ends in <code>?token=</code>).</p>")


def new_token() -> str:
    return secrets.token_urlsafe(32)


def check_token(token: str) -> None:
    """Refuses a given token easy to guess, in one line that does not repeat it."""
    if len(token) < MIN_TOKEN_CHARS:
        why = f"has {len(token)} characters; it needs at least {MIN_TOKEN_CHARS}"
    elif len(set(token)) < MIN_TOKEN_DISTINCT:
        why = f"uses only {len(set(token))} different characters; it needs at least {MIN_TOKEN_DISTINCT}"
    else:
        return
    raise InputError(f"the dashboard token (--token or CCRP_DASHBOARD_TOKEN) {why}",
                     hint="leave --token out and CCRP_DASHBOARD_TOKEN unset: ccrp then makes a random "
                          "256-bit token and prints it in the URL to open")


@dataclass
class Session:
    opened: float  # times on Auth.clock
    used: float
    csrf: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    ended: bool = False


class Auth:
    """The token, the sessions it opened, and the Hosts this server answers to (None: any).
    `clock` is monotonic: a wall clock set back would stretch the sessions' lifetimes."""

    def __init__(self, token: str, port: int, allowed_hosts: set[str] | None, clock=time.monotonic) -> None:
        check_token(token)
        self._token = token.encode()
        self.port = port
        self.allowed_hosts = allowed_hosts
        self.cookie = f"ccrp_dashboard_{port}"  # cookies are not kept apart by port: the name is
        self._sessions: OrderedDict[str, Session] = OrderedDict()
        self._failures: OrderedDict[str, list[float]] = OrderedDict()  # client -> its wrong tokens' times
        self.clock = clock

    def token_ok(self, presented: str) -> bool:
        return hmac.compare_digest(presented.encode(), self._token)

    def token_wait(self, client: str) -> int:
        """Seconds before `client` may present a token again; 0: now."""
        now = self.clock()
        recent = [t for t in self._failures.get(client, ()) if now - t < TOKEN_FAILURE_WINDOW_S]
        if len(recent) < TOKEN_FAILURES_ALLOWED:
            return 0
        return max(1, math.ceil(recent[-TOKEN_FAILURES_ALLOWED] + TOKEN_FAILURE_WINDOW_S - now))

    def token_failed(self, client: str) -> int:
        """Counts a wrong token from `client`; returns its wrong tokens within the window."""
        now = self.clock()
        recent = [t for t in self._failures.pop(client, ()) if now - t < TOKEN_FAILURE_WINDOW_S] + [now]
        self._failures[client] = recent  # the most recent failure last: the first one dropped
        while len(self._failures) > MAX_CLIENTS_KEPT:
            self._failures.popitem(last=False)
        return len(recent)

    def open_session(self) -> str:
        now = self.clock()
        self._drop_expired(now)
        sid = secrets.token_urlsafe(32)
        self._sessions[sid] = Session(opened=now, used=now)
        while len(self._sessions) > MAX_SESSIONS:
            self._sessions.popitem(last=False)[1].ended = True
        return sid

    def session(self, sid: str | None) -> Session | None:
        """The open session of this id, its idle time started again; None: unknown or expired."""
        if not sid:
            return None
        now = self.clock()
        self._drop_expired(now)
        for known, session in self._sessions.items():  # constant time per comparison
            if hmac.compare_digest(known.encode(), sid.encode()):
                session.used = now
                return session
        return None

    def end(self, session: Session) -> None:
        """Logout: the session is forgotten, so its cookie is worth nothing, and its streams end."""
        session.ended = True
        for sid, known in list(self._sessions.items()):
            if known is session:
                del self._sessions[sid]

    def alive(self, session: Session) -> bool:
        """Whether a session is still open; asking is no use of it (an event stream asks)."""
        return not session.ended and not self._expired(session, self.clock())

    @staticmethod
    def _expired(session: Session, now: float) -> bool:
        return now - session.used >= SESSION_IDLE_S or now - session.opened >= SESSION_MAX_S

    def _drop_expired(self, now: float) -> None:
        for sid, session in list(self._sessions.items()):
            if self._expired(session, now):
                session.ended = True
                del self._sessions[sid]

    def host_ok(self, host: str) -> bool:
        return self.allowed_hosts is None or host.lower() in self.allowed_hosts


def allowed_hosts(host: str, port: int) -> set[str] | None:
    """The Host headers a server bound to host:port answers to: its own address, and the loopback
    names when it is bound to loopback. Bound to every address (0.0.0.0, ::), any Host."""
    if host in ("0.0.0.0", "::", ""):
        return None
    shown = f"[{host}]" if ":" in host else host
    hosts = {f"{shown}:{port}"}
    if host in ("127.0.0.1", "::1", "localhost"):
        hosts |= {f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}"}
    return hosts


def _headers(scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}


class Guard:
    """ASGI middleware: the checks above, then the app with scope["ccrp_session"] set."""

    def __init__(self, app, auth: Auth) -> None:
        self.app = app
        self.auth = auth

    async def __call__(self, scope, receive, send):
        if scope["type"] == "lifespan":  # the server's start and stop: no client in it
            return await self.app(scope, receive, send)
        if scope["type"] != "http":
            return await self.refuse(scope, send)
        method, path = scope["method"], scope["path"]
        status_seen = {}

        async def send_secured(message):
            if message["type"] == "http.response.start":
                status_seen["status"] = message["status"]
                names = {k.lower() for k, _ in message.get("headers", [])}
                message = dict(message)
                message["headers"] = list(message.get("headers", [])) + [
                    (k, v) for k, v in SECURITY_HEADERS if k not in names]
            await send(message)

        try:
            refusal = self.check(scope, method, path)
            if refusal is not None:
                await refusal(send_secured)
            else:
                await self.app(scope, receive, send_secured)
        finally:
            client = (scope.get("client") or ("?", 0))[0]
            # The path only: the query string may hold the token.
            log.info('%s "%s %s" %s', client, method, path, status_seen.get("status", "-"))

    async def refuse(self, scope, send) -> None:
        """Any other scope (a websocket) never reaches the app: the checks below are HTTP's, and
        the dashboard has no websocket route, so none is accepted rather than one half-checked."""
        client = (scope.get("client") or ("?", 0))[0]
        log.info('%s "%s %s" refused', client, scope["type"].upper(), scope.get("path", "-"))
        if scope["type"] == "websocket":
            # Closed before it is accepted: the client gets a 403; 1008 is "policy violation".
            await send({"type": "websocket.close", "code": 1008})

    def check(self, scope, method: str, path: str):
        headers = _headers(scope)
        host = headers.get("host", "")
        if not self.auth.host_ok(host):
            return _plain(403, "unknown Host")
        if method not in ("GET", "HEAD", "POST"):
            return _plain(405, "method not allowed")
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        if method == "GET" and "token" in query:
            client = (scope.get("client") or ("?",))[0]
            wait = self.auth.token_wait(client)
            if wait:  # refused before the token is compared, the right one too
                return _plain(429, f"too many wrong tokens: try again in {wait} s",
                              headers=[(b"retry-after", str(wait).encode())])
            if not self.auth.token_ok(query["token"][0]):
                failures = self.auth.token_failed(client)
                if failures == TOKEN_FAILURES_ALLOWED:
                    log.warning("%s sent %d wrong tokens within %d s: its next ones wait", client, failures,
                                TOKEN_FAILURE_WINDOW_S)
                return _plain(401, "wrong token", html=LOGIN_PAGE)
            sid = self.auth.open_session()
            log.info("session opened from %s", client)
            cookie = f"{self.auth.cookie}={sid}; HttpOnly; SameSite=Strict; Path=/"
            return _redirect("/", cookie)  # always the page: a path of the request's could be //elsewhere
        cookies = SimpleCookie()
        try:
            cookies.load(headers.get("cookie", ""))
        except Exception:  # noqa: BLE001 - a malformed cookie header is no session
            cookies = SimpleCookie()
        morsel = cookies.get(self.auth.cookie)
        session = self.auth.session(morsel.value if morsel else None)
        if session is None:
            return _plain(401, "no session: open the URL ccrp dashboard printed", html=LOGIN_PAGE)
        scope["ccrp_session"] = session
        if method == "POST":
            origin = headers.get("origin")
            if origin is None and headers.get("referer"):
                parts = urlsplit(headers["referer"])
                origin = f"{parts.scheme}://{parts.netloc}"
            if origin != f"http://{host}":
                return _plain(403, "cross-site request refused (Origin)")
            if not hmac.compare_digest(headers.get(CSRF_HEADER, "").encode(), session.csrf.encode()):
                return _plain(403, "cross-site request refused (CSRF token)")
        return None


def _plain(status: int, text: str, html: bytes | None = None, headers: list | None = None):
    body = html if html is not None else text.encode() + b"\n"
    kind = b"text/html; charset=utf-8" if html is not None else b"text/plain; charset=utf-8"

    async def respond(send):
        await send({"type": "http.response.start", "status": status,
                    "headers": [(b"content-type", kind), (b"content-length", str(len(body)).encode()),
                                *(headers or [])]})
        await send({"type": "http.response.body", "body": body})
    return respond


def _redirect(path: str, cookie: str):
    async def respond(send):
        await send({"type": "http.response.start", "status": 303,
                    "headers": [(b"location", path.encode()), (b"set-cookie", cookie.encode()),
                                (b"content-length", b"0")]})
        await send({"type": "http.response.body", "body": b""})
    return respond
