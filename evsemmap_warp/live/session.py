"""Opening a Zenoh session as Zenoh users describe one: endpoints to connect to and to listen on
(``tcp/HOST:7447``), a Zenoh config file (JSON5), peer or client mode, multicast scouting on or off."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from ..config import ConfigError

INSTALL_HINT = 'live mapping over Zenoh needs the eclipse-zenoh package: pip install "evsemmap_warp[live]"'


def zenoh_module():
    """The ``zenoh`` module; ConfigError with the install line when eclipse-zenoh is not installed."""
    try:
        import zenoh
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    return zenoh


@dataclass
class ZenohOptions:
    """Where the session goes: ``connect`` / ``listen`` endpoints, a ``config_file`` (its settings, then these
    on top), ``mode`` (peer or client) and multicast scouting (off unless asked: it finds peers on the whole
    network segment)."""

    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config_file: Path | None = None
    mode: str = "peer"
    multicast: bool = False

    def check(self) -> None:
        """Refuse what Zenoh would refuse less clearly: an endpoint without its protocol, an unknown mode, a missing file."""
        if self.mode not in ("peer", "client"):
            raise ConfigError(f"--mode {self.mode!r}: peer or client")
        for flag, endpoints in (("--connect", self.connect), ("--listen", self.listen)):
            for endpoint in endpoints:
                protocol, _, address = endpoint.partition("/")
                if not protocol or not address or ":" not in address:
                    raise ConfigError(f"{flag} {endpoint!r}: a Zenoh endpoint is PROTOCOL/HOST:PORT, e.g. tcp/192.168.1.10:7447")
        if self.config_file is not None and not Path(self.config_file).is_file():
            raise ConfigError(f"--zenoh-config {self.config_file}: no such file")
        if self.mode == "client" and not self.connect and self.config_file is None:
            raise ConfigError("--mode client needs --connect (the router or peer to reach)")


def open_session(options: ZenohOptions):
    """An open Zenoh session for ``options``; ConfigError naming the endpoint or file Zenoh refused."""
    zenoh = zenoh_module()
    options.check()
    try:
        config = zenoh.Config.from_file(str(options.config_file)) if options.config_file else zenoh.Config()
    except Exception as exc:  # zenoh raises its own ZError for a file it cannot parse
        raise ConfigError(f"--zenoh-config {options.config_file}: not a Zenoh config file ({exc})") from None
    settings = {"mode": options.mode, "scouting/multicast/enabled": options.multicast}
    if options.connect:
        settings["connect/endpoints"] = options.connect
    if options.listen:
        settings["listen/endpoints"] = options.listen
    for key, value in settings.items():
        config.insert_json5(key, json.dumps(value))
    try:
        return zenoh.open(config)
    except Exception as exc:  # an endpoint it cannot listen on (port taken), or cannot parse
        raise ConfigError(f"Zenoh session ({', '.join(f'{k} {v}' for k, v in settings.items())}): {exc}") from None
