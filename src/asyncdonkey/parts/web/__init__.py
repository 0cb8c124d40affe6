"""Drive from a browser: :class:`WebController`, Donkeycar's web controller on the drive loop (``docs/web.md``)."""

from .auth import WebConfigError
from .config import WebConfig
from .controller import NEW_TOKEN, WEB_INPUTS, WEB_OUTPUTS, WebController

__all__ = ["NEW_TOKEN", "WEB_INPUTS", "WEB_OUTPUTS", "WebConfig", "WebConfigError", "WebController"]
