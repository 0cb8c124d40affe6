"""``Announcer``: the web controller's start-up message, the drive URLs (and a QR code of the first) it prints.

Its own object because it is the one part of the controller that writes to a terminal, and the part tests vary
most: where it prints (``announce``), whether a QR code is drawn, and which interfaces the addresses come from
(:mod:`.addresses`; tests give a fake table) can all be changed on it without touching the server.
"""

from __future__ import annotations

import logging
from typing import TextIO

from .addresses import WILDCARD_VERSIONS, DriveUrl, InterfaceTable, drive_urls, loopback_url, system_interfaces
from .auth import TOKEN_PARAM

__all__ = ["Announcer"]

logger = logging.getLogger("asyncdonkey.parts.web.controller")


class Announcer:
    """Prints where to drive from.

    Args:
        out: where the drive URLs (and QR code) are printed; ``None``: only logged.
        qr: draw a QR code of the first URL (``None``: when ``out`` is a terminal).
    """

    __slots__ = ("interfaces", "out", "qr")

    def __init__(self, out: TextIO | None, qr: bool | None) -> None:
        self.out = out
        self.qr = qr
        #: lists the interfaces whose addresses are printed (tests give a fake table)
        self.interfaces: InterfaceTable = system_interfaces

    def urls(self, host: str, port: int, token: str | None, *, secure: bool) -> list[DriveUrl]:
        """The drive URLs to print, the one for the QR code first (:mod:`.addresses`); a server listening on every
        interface listens on loopback too, so its ``127.0.0.1`` URL comes last, for a browser on this computer."""
        scheme = "https" if secure else "http"
        query = f"?{TOKEN_PARAM}={token}" if token else ""
        if host in WILDCARD_VERSIONS:
            versions = WILDCARD_VERSIONS[host]
            found = drive_urls(scheme, port, f"/drive{query}", self.interfaces, None, versions)
            return [*found, loopback_url(scheme, port, f"/drive{query}", versions)]
        bracketed = f"[{host}]" if ":" in host else host
        return [DriveUrl(f"{scheme}://{bracketed}:{port}/drive{query}")]

    def announce(self, host: str, port: int, urls: list[DriveUrl], *, token: bool, fresh_token: bool) -> None:
        """Log where the server listens, and print the URLs (with a word on the token) to :attr:`out`."""
        logger.info("web controller listening on %s:%d", host, port)
        out = self.out
        if out is None:
            return
        lines = ["Drive from a browser (phone on the car's network):"]
        lines += [f"  {u.url}" + (f"  ({u.note})" if u.note else "") for u in urls]
        if token:
            lines.append(
                "Anyone with this link can drive" + ("; the token changes at every start." if fresh_token else ".")
            )
        out.write("\n".join(lines) + "\n")
        show_qr = self.qr if self.qr is not None else bool(getattr(out, "isatty", lambda: False)())
        if show_qr:
            import segno

            segno.make(urls[0].url, error="L").terminal(out=out, compact=True)
        out.flush()
