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
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["COMMAND_CHANNELS", "DEFAULT_COMMANDS", "PILOT_COMMAND", "PairFiles", "car_acl", "make_pair"]

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


@dataclass
class PairFiles:
    """What :func:`make_pair` wrote: the config file of each side and the directories to copy."""

    car_config: Path
    pilot_config: Path
    car_dir: Path
    pilot_dir: Path
    ca_key: Path
    view_configs: dict[str, Path] = field(default_factory=dict)


def car_acl(prefix: str, pilot_cn: str, commands: Sequence[str] = DEFAULT_COMMANDS) -> dict:
    """The car's ``access_control`` section: commands only from ``pilot_cn``, reading for every authenticated peer."""
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
            {"id": "pilot-host", "cert_common_names": [pilot_cn]},
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
) -> PairFiles:
    """Write a CA, the car's and the pilot's certificates and Zenoh configs (and one per fleet ``views``).

    ``car_hosts``: the names and addresses the pilot will reach the car by (put in the car certificate's
    subject alternative names; the first is the pilot's connect endpoint). ``car_dir``/``pilot_dir``: where
    each side's folder will live on its machine (the configs name the certificate files by absolute path);
    default: where they are written.
    """
    from cryptography.hazmat.primitives import serialization

    if not car_hosts:
        raise ValueError("zenoh-pair: give at least one host name or address the pilot reaches the car by")
    names = [car, pilot, *views]
    for name in names:
        if not name or not all(c.isalnum() or c in "-_." for c in name):
            raise ValueError(f"zenoh-pair: names are letters, digits, '-', '_' or '.', got {name!r}")
    if len(set(names)) != len(names):
        raise ValueError(f"zenoh-pair: car, pilot and view names must differ, got {names}")
    prefix = (prefix or f"cars/{car}").strip("/")
    out = Path(out).resolve()
    dirs = {"ca": out / "ca", "car": out / "car", "pilot": out / "pilot"}
    for d in dirs.values():
        d.mkdir(parents=True, exist_ok=True)
    ca_key, ca_cert = _ca(f"asyncdonkey pair {car}/{pilot}", days)
    _write_key(dirs["ca"] / "ca-key.pem", ca_key)
    pem = ca_cert.public_bytes(serialization.Encoding.PEM)
    (dirs["ca"] / "ca.pem").write_bytes(pem)

    def issue(role_dir: Path, cn: str, sans: Sequence[str]) -> None:
        key, cert = _leaf(ca_key, ca_cert, cn, sans, days)
        _write_key(role_dir / f"{cn}-key.pem", key)
        (role_dir / f"{cn}-cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        (role_dir / "ca.pem").write_bytes(pem)

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
        d.mkdir(parents=True, exist_ok=True)
        issue(d, view, [view])
        cfg = d / f"{view}.json5"
        cfg.write_text(
            f"// fleet view {view!r}: may read what car {car!r} publishes, may not command it\n"
            + json.dumps(_connector(d, view, endpoint_host, port), indent=2)
            + "\n"
        )
        files.view_configs[view] = cfg
    return files


def _connector(cert_dir: Path, cn: str, host: str, port: int) -> dict:
    return {
        "mode": "peer",
        "listen": {"endpoints": []},  # reachable only through the connection it opens
        "connect": {
            "endpoints": [f"tls/{host}:{port}"],
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


def _validity(days: int):
    now = datetime.datetime.now(datetime.UTC)
    return now - datetime.timedelta(minutes=5), now + datetime.timedelta(days=days)


def _ca(name: str, days: int):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    start, end = _validity(days)
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


def _leaf(ca_key, ca_cert, cn: str, sans: Sequence[str], days: int):
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
    start, end = _validity(days)
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
