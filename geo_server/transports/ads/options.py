"""How the ADS interface listens and what it counts (docs/design.md §9): `AdsOptions`
(every limit a client meets, docs/limits.md) and `AdsStats`."""

from __future__ import annotations

from dataclasses import dataclass, field

import geo_server
from geo_server.dictionary import AMS_PORTS
from geo_server.transports.ads import codec
from geo_server.transports.ads.notifications import MAX_FLEET, MAX_PER_OWNER, MAX_TOTAL

#: Snapshots handed from the cycle to the event loop and not sampled yet; beyond, the
#: oldest go (their samples are delayed to a later cycle, never lost). The exact engine
#: stops handing them over earlier, at `AdsOptions.sample_backlog`.
HANDOFF_MAX = 2000
#: a machine's status entry of its ADS notifications (`sampling.Sampler.update_status`)
NOTIFICATIONS_STATUS = "ads_notifications"


@dataclass
class AdsOptions:
    """How the ADS interface listens (docs/design.md §9)."""

    host: str = "127.0.0.1"
    port: int = 48898  # 0 = ephemeral (tests); the bound port is `AdsServer.port`
    netid: str = "127.0.0.1.1.1"  # own AMS NetId
    ams_ports: tuple[int, ...] = AMS_PORTS
    read_only: bool = False  # every write answers 0x704
    #: Reject requests addressed to another NetId with AMS error 0x7 (target machine not
    #: found). Off by default: a stand-alone server answers whatever NetId the client
    #: routed to it, and notifications echo that NetId so AdsLib dispatches them.
    strict_netid: bool = False
    #: Largest AMS/TCP length accepted: what the largest legal request needs (a sum
    #: command of 500 sub-requests each carrying the largest object, see
    #: `codec.MAX_REQUEST_FRAME`). A frame header announcing more closes the connection
    #: before its data is buffered. Answers are held to the same size.
    max_frame: int = codec.MAX_REQUEST_FRAME
    #: Largest answer payload (the client's read length bounds each one): room for the
    #: symbol upload of a machine with 128 axes (about 480 kB)
    max_answer: int = 1 << 20
    #: waiting for a write to be applied, running cycles (None: the service's
    #: `ServiceLimits.write_timeout`)
    write_timeout: float | None = None
    #: Notifications one connection may register (0x716 NOMOREHDLS beyond): half of
    #: `max_notifications_total`, so one client cannot take every handle.
    max_notifications: int = MAX_PER_OWNER
    #: Notifications all connections together may register (0x716 beyond): 550, Beckhoff's
    #: recommended maximum per ADS device. Sampling runs on the event loop that answers
    #: every transport, and this is about what it sustains at a 1 ms GEO cycle. Measured
    #: on 2 cores (bench/ads_abuse.py and a sampling micro-benchmark), with every
    #: registration due every cycle at distinct addresses: on change (the pyads default)
    #: 0.3 ms of sampling per cycle alone and about 0.5 ms inside the running server,
    #: i.e. half the loop, while Modbus, Zenoh and ADS reads stay within a few ms at p99;
    #: cyclic, every one sending every cycle, 0.65 ms alone. Twice as many (1100) took
    #: 0.45 / 0.7 ms on change and 1.2 ms cyclic: the loop no longer sampled every cycle.
    max_notifications_total: int = MAX_TOTAL
    #: Notifications the machines behind one port (a fleet) may register together (0x716
    #: beyond): 1100, twice one machine's. What a registration costs follows what it
    #: samples (an on-change check of a value that cannot change at rest costs nothing
    #: while the machine rests; docs/design.md §13), and sampling is shared fairly
    #: between machines, so a fleet of 100 holding this many still answers every machine
    #: (bench/fleet_isolation.py). Read from the server that listens.
    max_notifications_fleet: int = MAX_FLEET
    #: Snapshots waiting to be sampled at the machines behind the port together (read
    #: from the server that listens), shared evenly (at least 16 each): 2000 cycles for
    #: one machine, 20 each for 100. Beyond its share a machine's exact engine publishes
    #: no more cycles for sampling until the loop caught up — those samples come later,
    #: from a later cycle, and are counted (`status()["ads_notifications"]`) — so a loop
    #: that cannot keep up sheds sampling work instead of piling it up.
    sample_backlog: int = HANDOFF_MAX
    #: With running cycles, sampling is at most this much work behind (seconds): when
    #: working through every snapshot waiting would take longer (at what a pass has cost
    #: lately), those handed over longer ago than this are skipped (counted,
    #: `cycles_shed`) and what was due in them is sampled from the next one, late. A loop
    #: that cannot sample every cycle (many registrations on a busy host) then answers a
    #: new registration within about this time, not after working through
    #: `sample_backlog` cycles of the past one by one; a loop that was only held a while,
    #: with passes that cost little, catches up every cycle (no gap in a cyclic stream).
    #: 0.25 s: on a loaded 2-core host the loop is held for hundreds of milliseconds at
    #: times, and a few registrations then owe tens of milliseconds of sampling (50 ms
    #: left gaps in cyclic streams there); hundreds of registrations still shed.
    sample_lag: float = 0.25
    #: Longest stretch of notification sampling in one event-loop callback (seconds);
    #: a longer pass continues in a later loop iteration, so requests of every transport
    #: are answered in between. A late slice still sends the values and timestamp of the
    #: cycle its samples were due at.
    sample_budget: float = 0.002
    #: Simultaneous ADS connections to one machine; one beyond is closed at once
    #: (counted in `AdsStats.refused_connections`). With `max_frame` it bounds the memory
    #: clients can make the server hold for unfinished frames to about 17 MiB. Behind one
    #: port with several machines (a fleet) a connection counts at each machine it sends
    #: a request to, and a request to a machine that has this many answers 0x716: one
    #: machine's clients cannot take the port from the others'.
    max_connections: int = 128
    #: Simultaneous connections to the port when it serves several machines (a fleet;
    #: read from the server that listens): one beyond is closed at once.
    max_connections_fleet: int = 512
    #: Answers one connection may have outstanding (writes waiting for their cycle,
    #: injected delays): beyond, the server stops reading that connection until half
    #: of them are sent, so a client pipelining requests cannot queue unbounded work.
    max_pending: int = 256
    #: Requests one machine serves in one event-loop step (read from the server that
    #: listens); the rest wait for the next step, their connections' reading paused:
    #: a client flooding one machine delays that machine's answers, not the others'.
    requests_per_step: int = 16
    #: A frame still unfinished this many seconds after its first byte arrived closes the
    #: connection (counted in `AdsStats.closed_incomplete`): a client that stopped in the
    #: middle of a frame must not keep its buffer alive. 0 disables the check.
    incomplete_frame_timeout: float = 5.0
    #: Notification frames are dropped (and counted) for a client whose unsent data
    #: exceeds this: a stalled client must not make the server buffer without bound.
    notification_backlog: int = 4 * 1024 * 1024
    device_name: str = "geo-server"
    #: ReadDeviceInfo of the system service (AMS port 10000; 15 characters at most)
    system_name: str = "geo-server sys"
    #: UDP port of discovery and add-route (48899 for real tools), on `host`; None: off
    udp_port: int | None = None
    #: host name the discovery answer gives
    host_name: str = "geo-server"
    #: The credentials an add-route request on `udp_port` must carry (`geo-server run
    #: --ads-route-user/--ads-route-password`); None: every add-route is refused with
    #: 0x704, as TwinCAT refuses wrong credentials (discovery.py).
    route_user: str | None = field(default=None, repr=False)
    route_password: str | None = field(default=None, repr=False)
    #: Symbol handles one connection may hold (0x716 beyond; TwinCAT has no documented
    #: limit, but a client that never releases must not grow the server without bound).
    max_handles: int = 10_000
    #: Symbol handles all connections together may hold at one machine (0x716 beyond).
    max_handles_machine: int = 50_000
    #: Symbol handles at every machine behind one port together (a fleet; 0x716 beyond;
    #: read from the server that listens). About 60 bytes each: 12 MiB at most.
    max_handles_fleet: int = 200_000
    #: With running cycles, no notification sample earlier than this many seconds after
    #: its registration (AdsLib drops samples that overtake its own bookkeeping).
    first_sample_hold: float = 0.005

    def __post_init__(self) -> None:
        codec.netid_to_bytes(self.netid)  # ValueError early for a malformed NetId


@dataclass
class AdsStats:
    requests: int = 0
    errors: int = 0  # responses with a non-zero result
    dropped_frames: int = 0
    faulted: int = 0  # requests an injected fault dropped, answered, delayed or cut off
    closed_for_framing: int = 0
    notifications_sent: int = 0
    notifications_dropped: int = 0
    connections: int = 0  # accepted
    refused_connections: int = 0  # closed at once: `max_connections` were open
    closed_incomplete: int = 0  # a frame stayed unfinished past `incomplete_frame_timeout`
    router_commands: int = 0  # AMS/TCP port connect, port close, get NetId answered
    udp_answered: int = 0  # discovery and add-route datagrams answered
    udp_dropped: int = 0  # datagrams that were not ADS UDP requests
    sampling_passes: int = 0  # notification sampling passes begun
    sampling_slices: int = 0  # passes continued in a later loop iteration (over budget)
    #: cycles the engine would have published for sampling but the loop was behind
    #: (`sample_backlog` snapshots waiting): their samples come from a later cycle
    samples_refused: int = 0
    #: cycles handed over for sampling but skipped, older than `sample_lag` when the
    #: loop got to them: their samples come from a later cycle
    cycles_shed: int = 0
    refused_requests: int = 0  # answered 0x716: `max_connections` at this machine
    deferred_requests: int = 0  # waited for a later loop step (`requests_per_step`)
    held_requests: int = 0  # waited for the machine's share of the loop (a fleet)
    repeated_reads: int = 0  # Reads answered from what their connection kept (`repeats`)


def server_version() -> tuple[int, int, int]:
    """(major, minor, build) of ReadDeviceInfo and discovery: the package version."""
    parts = [*geo_server.__version__.split("."), "0", "0"]
    nums = []
    for p in parts[:3]:
        digits = "".join(ch for ch in p if ch.isdigit())
        nums.append(int(digits) if digits else 0)
    return nums[0], nums[1], nums[2]
