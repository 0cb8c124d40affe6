"""Donkeycar's PCA9685 pin specs: ``"PCA9685.<bus>:<hex address>.<channel>"``, e.g. ``"PCA9685.1:40.1"``.

Donkeycar's configs name PWM outputs this way (``PWM_STEERING_PIN``, ``PWM_THROTTLE_PIN``), so the same
strings work here. Parsing is strict: a typo in a pin spec would otherwise drive the wrong channel (or the
wrong chip) of a moving car, so every malformed spec fails with the spec and the expected form.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ..errors import AsyncdonkeyError

__all__ = ["PCA9685Pin", "PinSpecError", "parse_pca9685_pin"]

EXPECTED = "'PCA9685.<bus>:<hex address>.<channel>', e.g. 'PCA9685.1:40.1' (bus 1, address 0x40, channel 1)"

_SPEC = re.compile(r"^(?P<provider>[A-Za-z0-9_]+)\.(?P<bus>\d+):(?P<addr>(?:0[xX])?[0-9A-Fa-f]{1,2})\.(?P<ch>\d+)$")
_PROVIDER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class PinSpecError(AsyncdonkeyError, ValueError):
    """A pin spec that cannot be parsed or names a pin asyncdonkey cannot drive."""


@dataclass(frozen=True, slots=True)
class PCA9685Pin:
    """One PCA9685 output: I2C bus number, 7-bit chip address and channel 0..15."""

    bus: int
    address: int
    channel: int

    def __str__(self) -> str:
        return f"PCA9685.{self.bus}:{self.address:02X}.{self.channel}"


def parse_pca9685_pin(spec: str) -> PCA9685Pin:
    """Parse a Donkeycar PCA9685 pin spec; the address is hexadecimal as in Donkeycar (``40`` is 0x40).

    Raises :class:`PinSpecError` naming the spec and the expected form when it is malformed, names another
    pin provider (``RPI_GPIO``, ``PIGPIO``), or has a channel outside 0..15 or an address outside 0x03..0x77.
    """
    if not isinstance(spec, str):
        raise PinSpecError(f"pin spec must be a string of the form {EXPECTED}; got {spec!r}")
    text = spec.strip()
    m = _SPEC.match(text)
    if m is None:
        provider = text.split(".", 1)[0]
        if _PROVIDER.match(provider) and provider.upper() != "PCA9685" and "." in text:
            raise PinSpecError(
                f"pin spec {spec!r} names the {provider!r} pin provider; asyncdonkey's PWM parts drive PCA9685 "
                f"outputs, expected {EXPECTED}"
            )
        raise PinSpecError(f"malformed pin spec {spec!r}: expected {EXPECTED}")
    provider = m["provider"]
    if provider.upper() != "PCA9685":
        raise PinSpecError(
            f"pin spec {spec!r} names the {provider!r} pin provider; asyncdonkey's PWM parts drive PCA9685 "
            f"outputs, expected {EXPECTED}"
        )
    bus = int(m["bus"])
    address = int(m["addr"], 16)
    channel = int(m["ch"])
    if not 0x03 <= address <= 0x77:
        raise PinSpecError(
            f"pin spec {spec!r}: address 0x{address:02X} is not a 7-bit I2C device address (0x03..0x77); "
            f"expected {EXPECTED}"
        )
    if not 0 <= channel <= 15:
        raise PinSpecError(f"pin spec {spec!r}: channel {channel} is out of range, a PCA9685 has channels 0..15")
    return PCA9685Pin(bus, address, channel)
