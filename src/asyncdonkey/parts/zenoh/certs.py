"""Why a TLS session may never connect, said in Python: the certificates a Zenoh config names, against this clock.

Zenoh does the TLS handshake in Rust. When a certificate is outside its validity window on one side's clock
(a Raspberry Pi without a clock battery boots with the time it last saved, hours or months behind, until NTP
answers), the handshake fails there, the peer sees an alert (rustls reports a not-yet-valid certificate as
``CertificateExpired``), and neither process's Python log says anything: the car is never commanded and
stops by its failsafe, silently. So the sides check what they can themselves:

* at start (:class:`.ZenohLink`, :class:`.PilotServer`), each certificate file its config names (its own
  certificate, for connecting and for listening, and the CA's) against this machine's clock, with one line per
  problem: ``certificate <file> is not valid until <time> UTC; this machine's clock says <time> UTC: check the
  clock (NTP)``. The CA and the peers' certificates are issued together by ``zenoh-pair``, so a CA that is
  not valid yet here means the peer's certificate is not either;
* while a subscriber hears nothing (:class:`.ZenohSubscriber`, ``silent_after_s``), once per silence: what
  the session is connected to, and these checks again (the clock may have moved since the start).

A config that holds its certificates inline (``*_base64``) is not checked here. ``cryptography`` comes with
the ``zenoh`` extra; without it nothing is checked.
"""

from __future__ import annotations

import datetime
import json
import logging
from pathlib import Path
from typing import Any

__all__ = ["TLS_FILES", "certificate_files", "certificate_problems", "config_value", "log_certificate_problems"]

logger = logging.getLogger(__name__)

#: the config keys under ``transport/link/tls`` that name certificate files, and what each one is
TLS_FILES = {
    "connect_certificate": "certificate",
    "listen_certificate": "certificate",
    "root_ca_certificate": "CA certificate",
}


def config_value(cfg: Any, key: str) -> Any:
    """A setting of a ``zenoh.Config`` as a Python value; ``None`` when unset (or not a config)."""
    try:
        return json.loads(cfg.get_json(key))
    except Exception:  # unset, or not a zenoh.Config
        return None


def certificate_files(cfg: Any) -> list[tuple[str, Path]]:
    """``(what, path)`` for each certificate file the config names (each file once)."""
    seen: dict[Path, str] = {}
    for key, what in TLS_FILES.items():
        value = config_value(cfg, f"transport/link/tls/{key}")
        if isinstance(value, str) and value:
            seen.setdefault(Path(value), what)
    return [(what, path) for path, what in seen.items()]


def _utc(t: datetime.datetime) -> str:
    return t.astimezone(datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def certificate_problems(cfg: Any, now: datetime.datetime | None = None) -> list[str]:
    """One sentence per certificate (of those the config names) that this clock (or ``now``) finds outside its
    validity window, or that cannot be read. Empty when all is well, or without ``cryptography``."""
    try:
        from cryptography import x509
    except ImportError:  # pragma: no cover - the zenoh extra brings it
        return []
    now = now or datetime.datetime.now(datetime.UTC)
    problems = []
    for what, path in certificate_files(cfg):
        try:
            certs = x509.load_pem_x509_certificates(path.read_bytes())
        except (OSError, ValueError) as exc:
            problems.append(f"{what} {path} cannot be read as PEM certificates: {exc}")
            continue
        for cert in certs:
            problem = _window(what, path, cert.not_valid_before_utc, cert.not_valid_after_utc, now)
            if problem:
                problems.append(problem)
                break
    return problems


def _window(
    what: str, path: Path, start: datetime.datetime, end: datetime.datetime, now: datetime.datetime
) -> str | None:
    clock = f"this machine's clock says {_utc(now)}"
    if now < start:
        peers = " (and so, probably, are the peers' certificates issued with it)" if what == "CA certificate" else ""
        return f"{what} {path} is not valid until {_utc(start)}{peers}; {clock}: check the clock (NTP)"
    if now > end:
        return (
            f"{what} {path} expired at {_utc(end)}; {clock}: issue new certificates (asyncdonkey zenoh-pair), or"
            " check the clock (NTP)"
        )
    return None


def log_certificate_problems(cfg: Any, who: str) -> list[str]:
    """Check the config's certificates (:func:`certificate_problems`) and log each problem as one warning line
    naming ``who``, with what follows from it; returns the problems."""
    problems = certificate_problems(cfg)
    for problem in problems:
        logger.warning(
            "%s: %s. Until this is fixed, TLS peers refuse this session and it refuses them: no command or frame"
            " passes",
            who,
            problem,
        )
    return problems
