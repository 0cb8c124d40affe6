"""Who may use the web controller: a random token per start (as Jupyter does), a cookie, and origin checks.

A car on a shared Wi-Fi is reachable by everyone on it, and Donkeycar's web controller lets any of them drive.
Here every request needs the access token made when the server starts:

* the URL printed at start-up carries it (``/drive?token=...``); a browser opening it (a request that accepts
  ``text/html``) gets the token stored in a cookie (``HttpOnly``, ``SameSite=Strict``) and is redirected to the
  same page without it, so the token does not stay in the address bar or the history;
* scripts send it as ``?token=...`` on any request (answered directly: a script keeps no cookie, so a redirect
  would lose the token) or as an ``Authorization: Token ...`` (or ``Bearer``) header;
* anything else gets ``401``, and its connection is closed: a client without the token cannot keep one open
  (see :mod:`.guard` for connections that never complete a request).

A browser sends the cookie with every request to the car, including requests another site's page makes it
send; ``SameSite=Strict`` keeps the cookie off those, and requests that change something (WebSockets, ``POST``)
are refused when their ``Origin`` names another site. ``token=None`` turns all this off, which is allowed only
when the server listens on loopback alone (a simulator on the laptop): nobody else can reach it then.

The token says a client may use the car, not which client it is. ``POST /drive`` clients are told apart by a
*session* (:class:`Sessions`): a cookie the server sets on their first ``POST``, so that a second script on the
driver's machine, holding the same token but not the driver's cookie, cannot take over.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import os
import secrets
import shlex
import stat
from collections.abc import Awaitable, Callable
from pathlib import Path
from urllib.parse import urlsplit

from aiohttp import web

from ...errors import AsyncdonkeyError

__all__ = [
    "TOKEN_PARAM",
    "Access",
    "Sessions",
    "WebConfigError",
    "is_loopback",
    "new_token",
    "origin_allowed",
    "token_from_file",
]

TOKEN_PARAM = "token"

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class WebConfigError(AsyncdonkeyError, ValueError):
    """The web controller was configured in a way that is unsafe or cannot work (the message says which)."""


def new_token() -> str:
    """A fresh random access token (128 bits, URL-safe)."""
    return secrets.token_urlsafe(16)


#: The most a token file may hold: a token is a line; a larger file is not a token file.
_TOKEN_FILE_MAX = 4096


def token_from_file(path: str | os.PathLike[str]) -> str:
    """The token kept in ``path``, made (128 random bits, readable by its owner only) when the file does not exist.

    A car started at boot by a service would otherwise have a new token at every start, and the phone that
    drives it a dead bookmark after each reboot. The file holds the token alone; deleting it makes a new one at
    the next start (which locks out every phone that had the old one). A file that exists but holds no usable
    token is an error, never silently replaced: the user may be pointing at the wrong file.

    The token is a password, so the file must be private: a regular file owned by the user running the car, with
    no group or other permission bits (``chmod 600``), opened without following a symbolic link (a link would
    make any readable file of the machine, ``/etc/machine-id`` say, the token). The checks are made on the opened
    file (``fstat``), so the file cannot be swapped between check and read. A new file is created ``0600`` with
    ``O_EXCL | O_NOFOLLOW``: never through a link, never over a file someone else put there first.
    """
    p = Path(path)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(p, flags, 0o600)
    except FileExistsError:  # also a symbolic link, dangling or not: O_EXCL never follows one
        return _read_token_file(p)
    except FileNotFoundError:
        raise WebConfigError(f"web token file {str(p)!r}: its folder {str(p.parent)!r} does not exist") from None
    token = new_token()
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        os.fchmod(f.fileno(), 0o600)  # the umask can only have taken bits away; make it exactly owner-only
        f.write(token + "\n")
    return token


def _read_token_file(p: Path) -> str:
    """The token of an existing file, refused (one line: the file, what is wrong, the fix) unless it is private."""
    try:
        # O_NONBLOCK: a FIFO put there must not hang the start; it is refused below as not a regular file
        fd = os.open(p, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise WebConfigError(
                f"web token file {str(p)!r} is a symbolic link, which is not followed (it could make any file the "
                "token); give the path of the token file itself"
            ) from None
        raise WebConfigError(f"web token file {str(p)!r} cannot be opened: {exc.strerror}") from None
    try:
        problem = _private_file_problem(os.fstat(fd), p)
        if problem is not None:
            raise WebConfigError(f"web token file {str(p)!r} {problem}")
        data = os.read(fd, _TOKEN_FILE_MAX + 1)
    finally:
        os.close(fd)
    try:
        token = data.decode("utf-8").strip()
    except UnicodeDecodeError:
        token = ""  # not text: refused below, as any file that holds no token
    if len(data) > _TOKEN_FILE_MAX or len(token) < 8 or any(c.isspace() for c in token) or not token.isprintable():
        raise WebConfigError(
            f"web token file {str(p)!r}: expected one token of at least 8 printable characters without spaces"
            " (delete the file to have a new one made)"
        )
    return token


def _private_file_problem(st: os.stat_result, p: Path) -> str | None:
    """What keeps the opened file from being a private token file, with how to fix it; ``None`` if nothing."""
    if stat.S_ISDIR(st.st_mode):
        return "is a directory; give the path of a file (a new one is made there if it does not exist)"
    if not stat.S_ISREG(st.st_mode):
        return "is not a regular file; give the path of a file (a new one is made there if it does not exist)"
    uid = os.geteuid()
    if st.st_uid != uid:
        return (
            f"is owned by uid {st.st_uid}, not by the user running the car (uid {uid}), who alone may hold the "
            f"token: chown {uid} {shlex.quote(str(p))} (or delete it to have a new one made)"
        )
    mode = stat.S_IMODE(st.st_mode)
    if mode & 0o077:
        return (
            f"has mode {mode:04o}: its group or others can read the token; make it private: "
            f"chmod 600 {shlex.quote(str(p))}"
        )
    return None


def is_loopback(host: str) -> bool:
    """True when ``host`` is a loopback name or address (``localhost``, ``127.x.x.x``, ``::1``)."""
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def origin_allowed(request: web.Request) -> bool:
    """A request's ``Origin`` (if any) must be the car's own address: the page the car served, not another site.

    No ``Origin`` header means the client is not a browser page (a script, a command-line tool), which the token
    alone governs.
    """
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    parts = urlsplit(origin)
    return bool(parts.netloc) and parts.netloc.lower() == (request.host or "").lower()


class Access:
    """The token check as aiohttp middleware, with the cookie named after the port (two cars on one host).

    Args:
        token: the access token, or ``None`` for no check (loopback only; the caller enforces that).
        port: the server's port, part of the cookie's name.
        on_admit: called with every request that passes the check, before its handler (the connection guard
            then knows the connection is the car's user's, never to be shed).
    """

    def __init__(self, token: str | None, port: int, on_admit: Callable[[web.Request], None] | None = None) -> None:
        self.token = token
        self.cookie = f"asyncdonkey-token-{port}"
        self.refused = 0
        self._on_admit = on_admit

    def matches(self, candidate: str | None) -> bool:
        if self.token is None:
            return True
        return candidate is not None and hmac.compare_digest(candidate.encode(), self.token.encode())

    def presented(self, request: web.Request) -> str | None:
        """The token a request carries: query, then header, then cookie."""
        q = request.query.get(TOKEN_PARAM)
        if q is not None:
            return q
        auth = request.headers.get("Authorization", "")
        scheme, _, value = auth.partition(" ")
        if scheme.lower() in ("token", "bearer") and value:
            return value.strip()
        return request.cookies.get(self.cookie)

    @web.middleware
    async def middleware(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        if self.token is not None and not self.matches(self.presented(request)):
            self.refused += 1
            resp = web.Response(
                status=401,
                text="asyncdonkey: this car needs its access token. Open the URL it printed when it started "
                "(.../drive?token=...), or send the token as ?token=... or an 'Authorization: Token ...' header.\n",
                headers={"WWW-Authenticate": 'Token realm="asyncdonkey"'},
            )
            resp.force_close()  # no keep-alive: the descriptor is the car's, not the stranger's
            return resp
        if self._on_admit is not None:
            self._on_admit(request)
        if self.token is None:
            return await handler(request)
        if TOKEN_PARAM in request.query and _is_page_navigation(request):
            # a browser opening the printed URL: keep the token in a cookie, drop it from the address bar
            query = {k: v for k, v in request.query.items() if k != TOKEN_PARAM}
            target = request.rel_url.with_query(query)
            resp = web.Response(status=302, headers={"Location": str(target), "Cache-Control": "no-store"})
            resp.set_cookie(self.cookie, self.token, httponly=True, samesite="Strict", path="/")
            return resp
        return await handler(request)


def _is_websocket(request: web.Request) -> bool:
    return request.headers.get("Upgrade", "").lower() == "websocket"


def _is_page_navigation(request: web.Request) -> bool:
    """A browser opening a page: a ``GET`` that accepts HTML (browsers send ``Accept: text/html,...`` when they
    navigate; ``curl``, ``requests`` and ``aiohttp`` send ``*/*``). ``Sec-Fetch-Mode`` would say it better, but
    browsers send it only to HTTPS and localhost, and a car is mostly reached over plain HTTP."""
    if request.method != "GET" or _is_websocket(request):
        return False
    return request.headers.get("Sec-Fetch-Mode") == "navigate" or "text/html" in request.headers.get("Accept", "")


class Sessions:
    """Session cookies for ``POST`` clients: a random id signed with a key made at each start.

    Signed, not stored: the server keeps nothing per session (a client that drops cookies would make one per
    request), and an id it did not issue (or issued before a restart) is no session at all.

    Args:
        port: the server's port, part of the cookie's name (two cars on one host).
        secure: mark the cookie ``Secure`` (the server speaks HTTPS).
    """

    def __init__(self, port: int, *, secure: bool = False) -> None:
        self.cookie = f"asyncdonkey-session-{port}"
        self.secure = secure
        self._key = secrets.token_bytes(32)

    def _sign(self, raw: str) -> str:
        return hmac.new(self._key, raw.encode(), "sha256").hexdigest()[:32]

    def of(self, request: web.Request) -> str | None:
        """The session id a request carries, if the server issued it; else ``None``."""
        value = request.cookies.get(self.cookie)
        if not value or len(value) > 80:
            return None
        raw, _, mac = value.partition(".")
        return value if raw and hmac.compare_digest(mac.encode(), self._sign(raw).encode()) else None

    def issue(self, response: web.StreamResponse) -> str:
        """Give the client of ``response`` a new session (``HttpOnly``, ``SameSite=Strict``); returns its id."""
        raw = secrets.token_urlsafe(16)
        value = f"{raw}.{self._sign(raw)}"
        response.set_cookie(self.cookie, value, httponly=True, samesite="Strict", path="/", secure=self.secure)
        return value
