"""``asyncdonkey zenoh-pair``: the certificates and the two Zenoh configs that let one pilot host drive one car.

On a shared network anyone who can reach a car's Zenoh port could publish ``pilot/throttle``. The configs
written here close that:

* **Mutual TLS.** The car listens only on a ``tls/`` endpoint with ``enable_mtls``: a session without a
  certificate signed by this pair's own CA cannot even connect (no plain ``tcp/`` listener is opened).
* **Access control on the car**, by the certificate's common name, default *deny*:

  - the pilot host (``CN=<pilot>``) may ``put``/``delete`` exactly the command keys
    (``<prefix>/pilot/command``, the one-sample command, and ``<prefix>/pilot/angle``,
    ``<prefix>/pilot/throttle`` by default) and the link's round-trip keys;
  - every authenticated session (the pilot, a fleet view given a certificate with ``--view``) may declare
    subscribers and receive what the car publishes (telemetry, camera, status);
  - nothing else comes in: a fleet view's put on a command key is dropped by the car's Zenoh runtime before it
    reaches the process.

* The pilot config connects to the car (peer mode, no listener, retrying while the car is away) and checks the
  car's certificate against the pair's CA and the car's host name.

The CA's private key is written to ``<out>/ca/`` and is needed only to issue more certificates: keep it on
neither machine. Private keys are written with mode 0600.

**A fleet on one pilot server** (:func:`make_fleet`, ``asyncdonkey zenoh-pair --fleet``): one CA, a certificate
per car and one for the server. The server listens (mutual TLS) in router mode and every car connects to it,
so the server is each car's only neighbour. A car is a Zenoh peer with no listener and the server as its only
endpoint: it starts, and keeps retrying, while the server is away (it stops by its failsafe meanwhile). A view
is a Zenoh client of the server (a client gets what its router forwards from every car; start it once the
server is up). Two layers of rules:

* each car's own rules are the single car's above with the server as its pilot: command keys only from
  ``CN=<server>``;
* the server's rules, by certificate, default deny: car ``X`` may put, delete and subscribe only under
  ``cars/X/**`` and receives only ``cars/X/**``, so no car can command, or watch, another through the
  server; a fleet view (``--view``) may subscribe to everything and put nothing.

**Nothing is overwritten by accident.** A pairing replaces the CA: every certificate issued before (a fleet
view's, a car's) stops being accepted. :func:`make_pair` and :func:`make_fleet` refuse (:class:`PairExists`,
naming the files) to write over files that exist unless given ``force=True``.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ...errors import AsyncdonkeyError

__all__ = [
    "COMMAND_CHANNELS",
    "DEFAULT_COMMANDS",
    "PILOT_COMMAND",
    "FleetFiles",
    "PairExists",
    "PairFiles",
    "car_acl",
    "make_fleet",
    "make_pair",
    "server_acl",
]

#: the key of the remote pilot's command: angle and throttle in one sample (``ZenohPublisher(..., group=)``)
PILOT_COMMAND = "pilot/command"
#: the channels that move a Donkeycar car (and the pilot's one-sample command): a subscriber that takes any of
#: them from the network needs a session only the intended pilot can publish to (``ZenohLink.guard_commands``)
COMMAND_CHANNELS = frozenset(
    {
        "user/angle",
        "user/throttle",
        "pilot/angle",
        "pilot/throttle",
        "angle",
        "throttle",
        "user/mode",
        "recording",
        PILOT_COMMAND,
    }
)
#: the keys the paired pilot may put by default: the one-sample command, and the two channels it replaces
DEFAULT_COMMANDS = (PILOT_COMMAND, "pilot/angle", "pilot/throttle")


class PairExists(AsyncdonkeyError, ValueError):
    """A pairing would write over existing files (the message names them): a new CA would silently cut off
    every identity issued by the old one."""

    def __init__(self, paths: Sequence[Path]) -> None:
        shown = ", ".join(str(p) for p in paths[:6]) + (f" and {len(paths) - 6} more" if len(paths) > 6 else "")
        super().__init__(
            f"zenoh-pair: refusing to overwrite {len(paths)} existing file{'s' if len(paths) != 1 else ''}: {shown}."
            " A new pairing makes a new CA, and every certificate issued before (cars, views) stops being"
            " accepted. Write elsewhere, or pass --force (force=True) to replace them."
        )
        self.paths = list(paths)


def _refuse_overwrite(paths: Sequence[Path], force: bool) -> None:
    existing = [p for p in paths if p.exists()]
    if existing and not force:
        raise PairExists(existing)


def _check_names(names: Sequence[str], what: str) -> None:
    for name in names:
        if not name or not all(c.isalnum() or c in "-_." for c in name):
            raise ValueError(f"zenoh-pair: names are letters, digits, '-', '_' or '.', got {name!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"zenoh-pair: {what} names must differ, got {list(names)}")


@dataclass
class PairFiles:
    """What :func:`make_pair` wrote: the config file of each side and the directories to copy."""

    car_config: Path
    pilot_config: Path
    car_dir: Path
    pilot_dir: Path
    ca_key: Path
    view_configs: dict[str, Path] = field(default_factory=dict)
    #: when the certificates become valid and when they expire (UTC): every machine's clock must be inside
    valid: tuple[datetime.datetime, datetime.datetime] | None = None


def car_acl(prefix: str, pilot_cn: str | Sequence[str], commands: Sequence[str] = DEFAULT_COMMANDS) -> dict:
    """The car's ``access_control`` section: commands only from ``pilot_cn`` (one name, or the names of a
    primary server and its standby), reading for every authenticated peer."""
    pilots = [pilot_cn] if isinstance(pilot_cn, str) else list(pilot_cn)
    prefix = prefix.strip("/")
    command_keys = [f"{prefix}/{c.strip('/')}" for c in commands]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": [
            {
                "id": "pilot-commands",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put", "delete"],
                "key_exprs": [*command_keys, f"{prefix}/_rtt/ping", f"{prefix}/_rtt/pong/**"],
            },
            {
                "id": "publish-telemetry",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put"],
                "key_exprs": ["**"],
            },
            {
                "id": "subscriptions",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": ["declare_subscriber"],
                "key_exprs": ["**"],
            },
        ],
        "subjects": [
            {"id": "pilot-host", "cert_common_names": pilots},
            {"id": "authenticated"},  # with mTLS, every connected session holds a certificate of this CA
        ],
        "policies": [
            {"rules": ["pilot-commands"], "subjects": ["pilot-host"]},
            {"rules": ["publish-telemetry", "subscriptions"], "subjects": ["authenticated"]},
        ],
    }


def make_pair(
    out: str | Path,
    *,
    car: str = "car1",
    pilot: str = "pilot",
    car_hosts: Sequence[str] = ("localhost",),
    port: int = 7447,
    listen_host: str = "0.0.0.0",
    prefix: str | None = None,
    commands: Sequence[str] = DEFAULT_COMMANDS,
    views: Sequence[str] = (),
    car_dir: str | Path | None = None,
    pilot_dir: str | Path | None = None,
    days: int = 825,
    force: bool = False,
    not_before: datetime.datetime | None = None,
) -> PairFiles:
    """Write a CA, the car's and the pilot's certificates and Zenoh configs (and one per fleet ``views``).

    ``car_hosts``: the names and addresses the pilot will reach the car by (put in the car certificate's
    subject alternative names; the first is the pilot's connect endpoint). ``car_dir``/``pilot_dir``: where
    each side's folder will live on its machine (the configs name the certificate files by absolute path);
    default: where they are written. ``force``: write over existing files (otherwise :class:`PairExists`).
    ``not_before``: when the certificates become valid (default: five minutes ago, for clocks a little behind);
    they stay valid ``days`` from then. Tests give a time ahead to play a car whose clock is behind.
    """
    if not car_hosts:
        raise ValueError("zenoh-pair: give at least one host name or address the pilot reaches the car by")
    _check_names([car, pilot, *views], "car, pilot and view")
    prefix = (prefix or f"cars/{car}").strip("/")
    out = Path(out).resolve()
    dirs = {"ca": out / "ca", "car": out / "car", "pilot": out / "pilot"}
    _refuse_overwrite(
        [
            *_ca_paths(dirs["ca"]),
            *_identity_paths(dirs["car"], car, "car.json5"),
            *_identity_paths(dirs["pilot"], pilot, "pilot.json5"),
            *(p for view in views for p in _identity_paths(out / view, view, f"{view}.json5")),
        ],
        force,
    )
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    issue = _Issuer(dirs["ca"], f"asyncdonkey pair {car}/{pilot}", days, not_before)
    issue(dirs["car"], car, car_hosts)
    issue(dirs["pilot"], pilot, [pilot])
    at_car = Path(car_dir) if car_dir else dirs["car"]
    at_pilot = Path(pilot_dir) if pilot_dir else dirs["pilot"]
    endpoint_host = car_hosts[0] if ":" not in car_hosts[0] else f"[{car_hosts[0]}]"
    listen = listen_host if ":" not in listen_host else f"[{listen_host}]"
    car_cfg = {
        "mode": "peer",
        "listen": {"endpoints": [f"tls/{listen}:{port}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": _tls(at_car, car, listen_side=True)}},
        "access_control": car_acl(prefix, pilot, commands),
    }
    files = PairFiles(
        car_config=dirs["car"] / "car.json5",
        pilot_config=dirs["pilot"] / "pilot.json5",
        car_dir=dirs["car"],
        pilot_dir=dirs["pilot"],
        ca_key=dirs["ca"] / "ca-key.pem",
        valid=issue.validity,
    )
    header = "// written by asyncdonkey zenoh-pair for car {car!r} (keys {prefix}/**) and pilot host {pilot!r}\n"
    files.car_config.write_text(
        header.format(car=car, prefix=prefix, pilot=pilot) + json.dumps(car_cfg, indent=2) + "\n"
    )
    files.pilot_config.write_text(
        header.format(car=car, prefix=prefix, pilot=pilot)
        + json.dumps(_connector(at_pilot, pilot, endpoint_host, port), indent=2)
        + "\n"
    )
    for view in views:
        d = out / view
        issue(d, view, [view])
        cfg = d / f"{view}.json5"
        cfg.write_text(
            f"// fleet view {view!r}: may read what car {car!r} publishes, may not command it\n"
            + json.dumps(_connector(d, view, endpoint_host, port), indent=2)
            + "\n"
        )
        files.view_configs[view] = cfg
    return files


class _Issuer:
    """A new CA written to ``ca_dir`` (``ca-key.pem`` 0600, ``ca.pem``), and ``issue(dir, cn, sans)``: a key and
    certificate for ``cn`` in ``dir``, with the CA's certificate beside them."""

    def __init__(self, ca_dir: Path, name: str, days: int, not_before: datetime.datetime | None = None) -> None:
        from cryptography.hazmat.primitives import serialization

        self.validity = _validity(days, not_before)
        self.key, self.cert = _ca(name, self.validity)
        _write_key(ca_dir / "ca-key.pem", self.key)
        self.pem = self.cert.public_bytes(serialization.Encoding.PEM)
        (ca_dir / "ca.pem").write_bytes(self.pem)

    def __call__(self, role_dir: Path, cn: str, sans: Sequence[str]) -> None:
        from cryptography.hazmat.primitives import serialization

        role_dir.mkdir(parents=True, exist_ok=True)
        key, cert = _leaf(self.key, self.cert, cn, sans, self.validity)
        _write_key(role_dir / f"{cn}-key.pem", key)
        (role_dir / f"{cn}-cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        (role_dir / "ca.pem").write_bytes(self.pem)


def _ca_paths(ca_dir: Path) -> list[Path]:
    return [ca_dir / "ca-key.pem", ca_dir / "ca.pem"]


def _identity_paths(role_dir: Path, cn: str, config: str) -> list[Path]:
    return [role_dir / f"{cn}-key.pem", role_dir / f"{cn}-cert.pem", role_dir / "ca.pem", role_dir / config]


@dataclass
class FleetFiles:
    """What :func:`make_fleet` wrote: the server's config and directory, each car's, each view's, the CA key."""

    server_config: Path
    server_dir: Path
    car_configs: dict[str, Path]
    car_dirs: dict[str, Path]
    ca_key: Path
    view_configs: dict[str, Path] = field(default_factory=dict)
    #: when the certificates become valid and when they expire (UTC): every machine's clock must be inside
    valid: tuple[datetime.datetime, datetime.datetime] | None = None
    #: the standby server's config and directory (``standby=``), or ``None``
    standby_config: Path | None = None
    standby_dir: Path | None = None


#: the subjects' ids naming the other server of a pair in a server's rules (read back by
#: :func:`.standby.role_from_config`: a server learns its role from its config)
PAIR_SUBJECTS = {"primary": "pair-standby", "standby": "pair-primary"}
#: a server of a pair is declared gone by the other (and by the cars) after this long without a word from it
#: when its connections are not closed (power cut, cable); a killed process's are closed by its OS at once
PAIR_LEASE_MS = 1000


def server_acl(
    cars: Sequence[str],
    views: Sequence[str] = (),
    prefix: str = "cars/{car}",
    pair: tuple[str, str] | None = None,
    this: str = "primary",
) -> dict:
    """The pilot server's ``access_control`` section (it routes for the fleet; see the module docstring).

    Per car ``X`` (certificate ``CN=X``): put, delete and subscribe only under ``cars/X/**``, receive only
    ``cars/X/**``. Views: subscribe to anything, receive anything, put nothing. Every session may learn of the
    others' subscriptions (``declare_subscriber`` out), which carries no data: that is how a car learns the
    server wants its frames.

    ``pair=(primary, standby)``: this server (``this``: ``"primary"`` or ``"standby"``) and the other may
    exchange liveliness tokens, liveliness subscriptions and queries on ``pilot-servers/<primary>/**`` only
    (:mod:`.standby`): no car's data passes between them, and neither learns the other's subscriptions.
    """
    rules: list[dict] = []
    subjects: list[dict] = []
    policies: list[dict] = []
    for car in cars:
        keys = [f"{prefix.format(car=car).strip('/')}/**"]
        rules.append(
            {
                "id": f"{car}-in",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["put", "delete", "declare_subscriber"],
                "key_exprs": keys,
            }
        )
        rules.append(
            {
                "id": f"{car}-out",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put", "delete"],
                "key_exprs": keys,
            }
        )
        subjects.append({"id": f"car-{car}", "cert_common_names": [car]})
        policies.append({"rules": [f"{car}-in", f"{car}-out"], "subjects": [f"car-{car}"]})
    rules.append(
        {
            "id": "declarations-out",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["declare_subscriber"],
            "key_exprs": ["**"],
        }
    )
    if pair is None:
        subjects.append({"id": "authenticated"})
        policies.append({"rules": ["declarations-out"], "subjects": ["authenticated"]})
    else:
        primary, standby = pair
        other = standby if this == "primary" else primary
        subjects.append({"id": "fleet", "cert_common_names": [*cars, *views]})
        policies.append({"rules": ["declarations-out"], "subjects": ["fleet"]})
        rules.append(
            {
                "id": "pair-liveliness",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query", "reply"],
                "key_exprs": [f"pilot-servers/{primary}/**"],
            }
        )
        subjects.append({"id": PAIR_SUBJECTS[this], "cert_common_names": [other]})
        policies.append({"rules": ["pair-liveliness"], "subjects": [PAIR_SUBJECTS[this]]})
    if views:
        # a view receives everything (egress puts to it) and may subscribe (ingress declarations); its own puts
        # are ingress puts, and no rule allows them
        rules.append(
            {
                "id": "views-read",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["put", "delete"],
                "key_exprs": ["**"],
            }
        )
        rules.append(
            {
                "id": "views-subscribe",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["declare_subscriber"],
                "key_exprs": ["**"],
            }
        )
        subjects.append({"id": "views", "cert_common_names": list(views)})
        policies.append({"rules": ["views-read", "views-subscribe"], "subjects": ["views"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def make_fleet(
    out: str | Path,
    *,
    cars: Sequence[str],
    server: str,
    server_hosts: Sequence[str] = ("localhost",),
    port: int = 7447,
    listen_host: str = "0.0.0.0",
    views: Sequence[str] = (),
    commands: Sequence[str] = DEFAULT_COMMANDS,
    days: int = 825,
    force: bool = False,
    not_before: datetime.datetime | None = None,
    standby: str | None = None,
    standby_hosts: Sequence[str] = ("localhost",),
    standby_port: int | None = None,
) -> FleetFiles:
    """Write one CA, the pilot server's certificate and config, and one certificate and config per car (and
    per fleet view): see the module docstring. Cars and views connect to the server at ``server_hosts[0]``
    (all of ``server_hosts`` go into its certificate); the server listens on ``listen_host:port``.
    ``force``: write over existing files (otherwise :class:`PairExists`). ``not_before``: as for
    :func:`make_pair`.

    ``standby``: the name of a standby server for the same cars (written to ``<out>/standby/``), reached at
    ``standby_hosts[0]:standby_port`` (default ``port``) and listening on ``listen_host:standby_port``. Every
    car then connects to both servers and takes commands from either certificate; the two servers dial each
    other and their rules let them exchange liveliness tokens on ``pilot-servers/<server>/**`` and nothing
    else (:mod:`.standby` decides which one answers).
    """
    cars = list(cars)
    if not cars:
        raise ValueError("zenoh-pair --fleet: name at least one car (--cars car1 car2 ...)")
    if not server_hosts:
        raise ValueError("zenoh-pair --fleet: give at least one host name or address the cars reach the server by")
    _check_names([*cars, server, *views, *([standby] if standby else [])], "car, server, standby and view")
    if standby is not None and not standby_hosts:
        raise ValueError("zenoh-pair --fleet: give at least one host name or address the standby is reached by")
    s_port = port if standby_port is None else standby_port
    out = Path(out).resolve()
    ca_dir, server_dir, standby_dir = out / "ca", out / "server", out / "standby"
    if standby is not None and s_port == port and list(standby_hosts)[:1] == list(server_hosts)[:1]:
        raise ValueError(
            f"zenoh-pair --fleet: the standby {standby!r} would be reached at the server's own address"
            f" ({server_hosts[0]}:{port}): give it another host (--standby-host) or port (--standby-port)"
        )
    _refuse_overwrite(
        [
            *_ca_paths(ca_dir),
            *_identity_paths(server_dir, server, "server.json5"),
            *(_identity_paths(standby_dir, standby, "server.json5") if standby else []),
            *(p for car in cars for p in _identity_paths(out / car, car, "car.json5")),
            *(p for view in views for p in _identity_paths(out / view, view, f"{view}.json5")),
        ],
        force,
    )
    ca_dir.mkdir(parents=True, exist_ok=True)
    issue = _Issuer(ca_dir, f"asyncdonkey fleet {server}", days, not_before)
    issue(server_dir, server, server_hosts)
    host = _bracket(server_hosts[0])
    listen = _bracket(listen_host)
    endpoints = [f"tls/{host}:{port}"]
    server_cfg = _server_config(server_dir, server, f"tls/{listen}:{port}", server_acl(cars, views))
    if standby is not None:
        issue(standby_dir, standby, standby_hosts)
        endpoints.append(f"tls/{_bracket(standby_hosts[0])}:{s_port}")
        pair = (server, standby)
        server_cfg = _server_config(
            server_dir, server, f"tls/{listen}:{port}", server_acl(cars, views, pair=pair), dial=endpoints[1]
        )
        standby_cfg = _server_config(
            standby_dir,
            standby,
            f"tls/{listen}:{s_port}",
            server_acl(cars, views, pair=pair, this="standby"),
            dial=endpoints[0],
        )
    files = FleetFiles(
        server_config=server_dir / "server.json5",
        server_dir=server_dir,
        car_configs={},
        car_dirs={},
        ca_key=ca_dir / "ca-key.pem",
        valid=issue.validity,
    )
    role = f" (primary; standby {standby!r})" if standby else ""
    files.server_config.write_text(
        f"// written by asyncdonkey zenoh-pair --fleet: pilot server {server!r}{role} for cars {', '.join(cars)}\n"
        + json.dumps(server_cfg, indent=2)
        + "\n"
    )
    if standby is not None:
        files.standby_config, files.standby_dir = standby_dir / "server.json5", standby_dir
        files.standby_config.write_text(
            f"// written by asyncdonkey zenoh-pair --fleet: pilot server {standby!r}, standby of {server!r}, for"
            f" cars {', '.join(cars)}: it answers while {server!r} is not alive\n"
            + json.dumps(standby_cfg, indent=2)
            + "\n"
        )
    servers = [server, *([standby] if standby else [])]
    for car in cars:
        d = out / car
        issue(d, car, [car])
        cfg = _connector(d, car, endpoints)  # a peer: it starts (and stops, failsafe) before the server is up
        cfg["access_control"] = car_acl(f"cars/{car}", servers, commands)
        path = d / "car.json5"
        path.write_text(
            f"// car {car!r} (keys cars/{car}/**): connects to pilot server {' and '.join(map(repr, servers))},"
            " takes commands only from it\n" + json.dumps(cfg, indent=2) + "\n"
        )
        files.car_configs[car] = path
        files.car_dirs[car] = d
    for view in views:
        d = out / view
        issue(d, view, [view])
        path = d / f"{view}.json5"
        path.write_text(
            f"// fleet view {view!r}: reads every car through pilot server {server!r}, commands none\n"
            + json.dumps(_connector(d, view, endpoints, mode="client"), indent=2)
            + "\n"
        )
        files.view_configs[view] = path
    return files


def _bracket(host: str) -> str:
    """An address as an endpoint writes it (an IPv6 address in brackets)."""
    return host if ":" not in host else f"[{host}]"


def _server_config(cert_dir: Path, cn: str, listen: str, acl: dict, dial: str | None = None) -> dict:
    """A pilot server's config: a router listening on mutual TLS with its rules; a server of a pair also dials
    the other (both do, so whichever starts second reaches the first at once) with a short lease."""
    cfg: dict = {
        "mode": "router",  # it forwards each car's keys between that car, itself and the fleet views
        "listen": {"endpoints": [listen]},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": _tls(cert_dir, cn, listen_side=True)}},
        "access_control": acl,
    }
    if dial is not None:
        cfg["connect"] = {
            "endpoints": [dial],
            "exit_on_failure": False,
            "retry": {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2},
        }
        cfg["transport"]["link"]["tx"] = {"lease": PAIR_LEASE_MS, "keep_alive": 4}
    return cfg


def _connector(
    cert_dir: Path, cn: str, endpoints: str | Sequence[str], port: int | None = None, mode: str = "peer"
) -> dict:
    if isinstance(endpoints, str):  # a host and a port
        endpoints = [f"tls/{endpoints}:{port}"]
    return {
        "mode": mode,
        "listen": {"endpoints": []},  # reachable only through the connection it opens
        "connect": {
            "endpoints": list(endpoints),
            "exit_on_failure": False,  # start before the car, keep retrying while it is away
            "retry": {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2},
        },
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": _tls(cert_dir, cn, listen_side=False)}},
    }


def _tls(cert_dir: Path, cn: str, *, listen_side: bool) -> dict:
    tls = {
        "root_ca_certificate": str(cert_dir / "ca.pem"),
        "enable_mtls": True,
        "connect_private_key": str(cert_dir / f"{cn}-key.pem"),
        "connect_certificate": str(cert_dir / f"{cn}-cert.pem"),
        "verify_name_on_connect": True,
    }
    if listen_side:
        tls["listen_private_key"] = str(cert_dir / f"{cn}-key.pem")
        tls["listen_certificate"] = str(cert_dir / f"{cn}-cert.pem")
    return tls


def _write_key(path: Path, key) -> None:
    from cryptography.hazmat.primitives import serialization

    data = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _validity(days: int, not_before: datetime.datetime | None = None) -> tuple[datetime.datetime, datetime.datetime]:
    """The certificates' window: from ``not_before`` (default five minutes ago) for ``days`` days."""
    start = not_before or datetime.datetime.now(datetime.UTC) - datetime.timedelta(minutes=5)
    return start, start + datetime.timedelta(days=days, minutes=5)


def _ca(name: str, validity: tuple[datetime.datetime, datetime.datetime]):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    start, end = validity
    usage = x509.KeyUsage(
        digital_signature=True,
        key_cert_sign=True,
        crl_sign=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        encipher_only=False,
        decipher_only=False,
    )
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(usage, critical=True)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def _leaf(ca_key, ca_cert, cn: str, sans: Sequence[str], validity: tuple[datetime.datetime, datetime.datetime]):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    alt: list[x509.GeneralName] = []
    for name in sans:
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(name)))
        except ValueError:
            alt.append(x509.DNSName(name))
    key = ec.generate_private_key(ec.SECP256R1())
    start, end = validity
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(end)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert
