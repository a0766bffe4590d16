"""How the Zenoh interface joins a Zenoh network, and the limits it keeps (docs/design.md
§7, docs/limits.md)."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

import zenoh

#: `ZenohOptions` field -> Zenoh configuration key of the transport limits.
TRANSPORT_LIMITS = {
    "accept_timeout_ms": "transport/unicast/accept_timeout",
    "accept_pending": "transport/unicast/accept_pending",
    "max_sessions": "transport/unicast/max_sessions",
    "max_links": "transport/unicast/max_links",
}


@dataclass
class ZenohOptions:
    """How the server joins a Zenoh network (docs/design.md §7), and the limits it keeps."""

    machine: str = "local"
    mode: str = "peer"  # "peer" | "client"
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    config_file: str | None = None  # a Zenoh JSON5 config for anything else (TLS, ACL)
    publish_period: float = 0.05
    #: seconds between two publications of `cnc/<m>/status`; 0: none (a fleet's
    #: machines: the fleet publishes them, `ZenohInterface.publish_status`)
    status_period: float = 1.0
    read_only: bool = False
    #: Milliseconds a new connection has to complete the Zenoh handshake before it is
    #: closed (Zenoh's own default: 10000). A connection that connects and never speaks
    #: holds one of the `accept_pending` slots that long; once they are all taken, every
    #: new session is turned away, so this bounds how long idle sockets lock clients out.
    #: A handshake is a few round trips (a few more with TLS): milliseconds on a LAN;
    #: 2 s leaves room for a slow link.
    accept_timeout_ms: int = 2000
    #: Connections in the handshake at once; more are closed at once (Zenoh's default).
    accept_pending: int = 100
    #: Sessions connected at once (Zenoh's default: 1000). A CNC cell has a few HMIs, PLC
    #: programs and test tools; 64 is far above that and bounds the memory and threads
    #: the Zenoh transport may take next to the GEO cycle.
    max_sessions: int = 64
    #: Links per session (Zenoh's default: no multilink).
    max_links: int = 1
    #: Largest NC text in one `cnc/<m>/nc` request, in bytes (UTF-8); larger -> 0x705.
    #: MDI lines and the manuals' test programs are well under 1 kB; a long program
    #: belongs in a file (`geo-server run --program`), not in one request that parses
    #: while the GEO cycle waits for the interpreter.
    max_nc_bytes: int = 16 * 1024
    #: Gets and puts handed to the event loop and not finished yet, for all sessions
    #: together (a get answered on Zenoh's thread at once is not counted). Beyond, a
    #: get is answered at once with 0x716 and a put is dropped (both counted in the
    #: status as `zenoh_busy`; a dropped put logged at most every 10 s): a session
    #: sending faster than the machine answers cannot make the server hold unbounded
    #: work.
    max_pending: int = 1024
    #: Seconds between two looks for another session answering for this machine (also
    #: done at once when Zenoh reports a matching queryable or a liveliness change).
    rival_check_period: float = 5.0
    #: Seconds between two looks whether anybody subscribes to this machine, while
    #: nobody does (Zenoh's matching listener reports it at once; this is in case it
    #: did not). A look asks Zenoh and takes milliseconds one time in ten when the
    #: interpreter lock is busy: a fleet looks less often per machine (`plug`).
    watch_recheck: float = 1.0
    #: How far (a fraction of their periods, 0 to 1) this machine's periodic looks —
    #: rival probes, the publish loop's check for subscribers — are shifted after the
    #: first: the machines of a fleet start together, and a hundred probes or checks at
    #: once kept the event loop that answers every machine busy for milliseconds to tens
    #: of milliseconds (docs/design.md §13.1). The plug spreads a fleet evenly.
    spread: float = 0.0

    def shrink_to(self, connections: int) -> None:
        """Fit sessions and handshakes under way into `connections` descriptors, in
        proportion (the descriptor plan of geo_server/descriptors.py)."""
        total = self.max_sessions + self.accept_pending
        if connections >= total:
            return
        self.max_sessions = max(1, connections * self.max_sessions // total)
        self.accept_pending = max(1, connections - self.max_sessions)

    def zenoh_config(self) -> zenoh.Config:
        """The Zenoh configuration: the config file (if any), then our options.

        Mode, endpoints and scouting are always set from the options. The transport
        limits (`TRANSPORT_LIMITS`) are set from the options unless the config file sets
        that key to something other than Zenoh's own default: a limit written in the
        config file wins over the option's default.
        """
        cfg = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
        zenoh_defaults = zenoh.Config()
        for name, key in TRANSPORT_LIMITS.items():
            value = getattr(self, name)
            # Zenoh takes -1 for a millisecond count without complaint (as 0): check here
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ZenohOptions.{name} must be a positive integer, not {value!r}")
            if cfg.get_json(key) == zenoh_defaults.get_json(key):
                cfg.insert_json5(key, json.dumps(value))
        return cfg
