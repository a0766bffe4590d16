"""Generated documentation: every table comes from the code, never typed.

`python -m geo_server.docs` writes the reference pages under docs/ (`PAGES`: the
objects, the Modbus map, the list checks, the ADS symbols and the *Limits* table, whose
values are the defaults of the option classes), and rewrites every
`<!-- BEGIN name -->` … `<!-- END name -->` block of README.md (`README_BLOCKS`).
`tests/test_docs.py` fails when any of them is out of date.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import Any

from geo_server.dictionary import ATTRIBUTES, GROUPS, dictionary_markdown

ROOT = Path(__file__).resolve().parent.parent


def objects_page() -> str:
    attributes = ", ".join(f"`0x{offset:X}` ({kind})" for offset, kind in ATTRIBUTES.items())
    return (
        "# Objects\n\n"
        "Generated from `objects/objects.toml` by `python -m geo_server.docs`.\n\n"
        f"Index group `0x{GROUPS['geo']:X}` (GEO) and `0x{GROUPS['sim']:X}` (emulator "
        "extension); index offset `(axis << 16) | id`, machine-wide objects with axis 0. "
        f"Attribute groups at group + {attributes}. Sources cite the manuals by number and "
        "page (see the legend in [design.md](design.md)).\n\n" + dictionary_markdown()
    )


def modbus_page() -> str:
    from geo_server.transports.modbus.regmap import modbus_map

    return (
        "# Modbus register map\n\n"
        "Generated from the object dictionary by `python -m geo_server.docs` (also "
        "`geo-server modbus-map`). Unit id = logical axis number, unit 0 (or 255) = the "
        "machine-wide objects; addresses are PDU addresses (0-based).\n\n" + modbus_map("md")
    )


def checks_page() -> str:
    from geo_server.listfile.checks import checks_markdown

    return checks_markdown()


#: Pages under docs/ and what writes them.
def symbols_page() -> str:
    """Every ADS symbol pattern, from the dictionary (`transports/ads/symbols.py`)."""
    from geo_server.dictionary import COM_AMS_PORT, load_dictionary
    from geo_server.transports.ads.symbols import has_symbol, symbol_name

    rows = [
        "| symbol | TwinCAT type | size | ADST | index group | index offset | access | object |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for obj in filter(has_symbol, load_dictionary().objects):
        axis = obj.scope == "axis"
        name = symbol_name(obj, "<axis>" if axis else None)
        offset = f"(axis << 16) \\| 0x{obj.id:04X}" if axis else f"0x{obj.id:X}"
        access = (
            "read"
            if "w" not in obj.access
            else ("write" if "r" not in obj.access else "read/write")
        )
        rows.append(
            f"| `{name}` | {obj.type.tc_type} | {obj.type.size} | {obj.type.ads_type} | "
            f"0x{GROUPS[obj.group]:X} | {offset} | {access} | {obj.name} |"
        )
    return (
        "# ADS symbols\n\n"
        "Generated from `objects/objects.toml` by `python -m geo_server.docs`. One symbol per "
        "object and axis of the machine (`<axis>` is the axis name of its axis list, e.g. "
        "`GEO.X.TEMPC.coefficient`), machine-wide objects once; names are case-insensitive. "
        "Served on AMS port 551: handles (0xF003/0xF005/0xF006), info by name (0xF009), "
        "uploads (0xF00B/0xF00C/0xF00E/0xF00F) — see [design.md](design.md) §9. The COM "
        f"task's objects (AMS port {COM_AMS_PORT}, index group 0x{GROUPS['com']:X}) have no "
        "symbols: address them "
        "by index group and offset ([volumetric.md](volumetric.md)).\n\n" + "\n".join(rows) + "\n"
    )


# ---------------------------------------------------------------------- limits

#: (option class, field) -> (what, what happens past it). The value is the field's
#: default, read from the class.
_LIMITS: list[tuple[str, str, str, str, str]] = [
    (
        "service",
        "write_timeout",
        "s",
        "a write waits for the cycle that applies it",
        "withdrawn, never applied; ADS 0x719, Modbus exception 6, Zenoh reply_err 0x719",
    ),
    (
        "service",
        "swap_timeout",
        "s",
        "a reload waits for the cycle that swaps the tables",
        "withdrawn, machine unchanged; 0x719",
    ),
    (
        "service",
        "command_wait",
        "s",
        "a reload/save waits for another one to finish",
        "refused: 0x708 (busy), Modbus exception 6",
    ),
    (
        "service",
        "stall_after",
        "s",
        "no new cycle while cycles should run",
        "stalled: reads 0x707 / exception 6 / reply_err, writes refused, status says so",
    ),
    ("service", "nc_max_bytes", "bytes", "NC text in one request", "refused: 0x705"),
    ("service", "nc_max_lines", "lines", "NC text in one request", "refused: 0x705"),
    (
        "service",
        "measure_deadline",
        "s",
        "a measurement (`cmd/measure`) holds a running machine",
        "ended: reply_err 0x708; one at a time (0x708)",
    ),
    (
        "ads",
        "max_connections",
        "",
        "ADS connections to one machine",
        "the new one is closed at once; in a fleet, its request to that machine answers 0x716",
    ),
    (
        "ads",
        "max_connections_fleet",
        "",
        "ADS connections to the port of a fleet",
        "the new one is closed at once",
    ),
    (
        "ads",
        "max_pending",
        "",
        "answers one ADS connection has outstanding",
        "the server stops reading that connection until half are sent",
    ),
    (
        "ads",
        "requests_per_step",
        "",
        "ADS requests one machine serves in one event-loop step",
        "the rest wait for the next step (their connections' reading paused)",
    ),
    ("ads", "max_handles", "", "symbol handles of one connection at one machine", "0x716"),
    ("ads", "max_handles_machine", "", "symbol handles at one machine", "0x716"),
    ("ads", "max_handles_fleet", "", "symbol handles at every machine of a fleet", "0x716"),
    (
        "ads",
        "max_frame",
        "bytes",
        "one AMS/TCP frame (the largest legal request)",
        "connection closed before the data is read",
    ),
    ("ads", "incomplete_frame_timeout", "s", "a frame may stay unfinished", "connection closed"),
    ("ads", "max_notifications", "", "notifications per connection", "0x716"),
    ("ads", "max_notifications_total", "", "notifications at one machine", "0x716"),
    ("ads", "max_notifications_fleet", "", "notifications at every machine of a fleet", "0x716"),
    (
        "ads",
        "sample_backlog",
        "cycles",
        "snapshots waiting to be sampled, all machines together (shared evenly, ≥ 16 each)",
        "the engine publishes no more for sampling; those samples come from a later cycle "
        "(counted: `samples_late`)",
    ),
    (
        "ads",
        "sample_lag",
        "s",
        "sampling work owed, with running cycles (at what a pass costs lately)",
        "older snapshots are skipped; those samples come from a later cycle (counted: "
        "`cycles_shed`)",
    ),
    (
        "ads",
        "notification_backlog",
        "bytes",
        "unsent data of a client that does not read",
        "its notification samples are dropped (counted)",
    ),
    (
        "ads",
        "sample_budget",
        "s",
        "notification sampling in one event-loop step",
        "continued in the next step (other requests answered in between)",
    ),
    ("modbus", "max_connections", "", "Modbus connections", "the new one is closed at once"),
    (
        "modbus",
        "max_pipeline",
        "",
        "requests queued on one connection",
        "the server stops reading that connection until it has answered",
    ),
    ("modbus", "incomplete_frame_timeout", "s", "a frame may stay unfinished", "connection closed"),
    ("zenoh", "max_sessions", "", "Zenoh sessions", "new sessions refused by Zenoh"),
    (
        "zenoh",
        "accept_timeout_ms",
        "ms",
        "a TCP connection may take to open a session",
        "dropped by Zenoh (idle sockets cannot lock sessions out)",
    ),
    ("zenoh", "accept_pending", "", "connections opening a session at once", "further ones wait"),
    ("zenoh", "max_nc_bytes", "bytes", "NC text on `cnc/<m>/nc`", "reply_err 0x705"),
    (
        "zenoh",
        "max_pending",
        "",
        "gets and puts waiting on the event loop, all sessions together",
        "a get: reply_err 0x716 at once; a put: dropped (counted, logged)",
    ),
    (
        "files",
        "volc_list_bytes",
        "bytes",
        "a VOLC list (start-up, reload, 0x27C, `#VOLCOMP UPDATE`)",
        "refused unread past the bound: compensation unavailable / update 0x70D",
    ),
    (
        "files",
        "correction_file_bytes",
        "bytes",
        "a correction file `file[j]` of a VOLC list",
        "refused unread past the bound: compensation unavailable / update 0x70D",
    ),
    (
        "http",
        "max_connections",
        "",
        "HTTP connections (open pages included); shrunk at start to fit the descriptor limit",
        "the new one is closed at once",
    ),
    (
        "http",
        "keepalive_timeout",
        "s",
        "an HTTP connection without a complete request head (from its opening, after each answer)",
        "connection closed",
    ),
    ("http", "body_timeout", "s", "an HTTP request body may take to arrive", "408"),
    ("http", "max_line_size", "bytes", "one HTTP request or header line", "400/431"),
    ("http", "max_headers", "", "HTTP header lines of one request", "400/431"),
    ("http", "max_body", "bytes", "an HTTP request body (a write is under 200)", "413"),
    (
        "http",
        "max_pages",
        "",
        "open pages (WebSockets) of one machine",
        "503 with a message; a closed page frees its place",
    ),
    (
        "http",
        "ws_max_message",
        "bytes",
        "a WebSocket message from a page (the page sends none)",
        "socket closed: 1009 at the frame's header, unread; any message 1008",
    ),
    (
        "http",
        "ws_ping_burst",
        "",
        "WebSocket pings from a peer in a burst (one more a second)",
        "socket closed: 1008",
    ),
    (
        "http",
        "ws_backlog",
        "bytes",
        "pushes a page leaves unread",
        "the page is dropped (it reconnects), the others are not held up",
    ),
    ("http", "ws_send_timeout", "s", "one push to one page", "the page is dropped"),
    (
        "recorder",
        "max_samples",
        "rows",
        "a recording without a trigger (`samples`), and after one (`post`)",
        "refused: 0x70B naming the setting and its range",
    ),
    ("recorder", "max_pre", "rows", "samples kept before the trigger (`pre`)", "refused: 0x70B"),
    ("recorder", "max_every", "cycles", "between two samples (`every`)", "refused: 0x70B"),
    ("recorder", "max_selectors", "", "selectors of one recording (`objects`)", "refused: 0x70B"),
    (
        "recorder",
        "max_text",
        "characters",
        "one selector, the trigger, the file name",
        "refused: 0x70B",
    ),
    (
        "recorder",
        "buffer_bytes",
        "bytes",
        "the ring of a recording to a file (the `pre` samples and rows not yet written)",
        "a wider `pre` refused (0x70B); a real-time machine whose writer is a ring behind "
        "drops samples (counted: `dropped`), a stepped one waits",
    ),
    (
        "recorder",
        "input_buffer_bytes",
        "bytes",
        "the machine's inputs held by a recording (awaiting its trigger, or not yet written)",
        "the oldest go (counted: `inputs_dropped`)",
    ),
    ("opcua", "max_connections", "", "OPC UA connections", "closed at once"),
    (
        "opcua",
        "max_monitored_items_per_session",
        "",
        "monitored items in one session (of any node)",
        "BadTooManyMonitoredItems",
    ),
    (
        "opcua",
        "max_monitored_items",
        "",
        "monitored items in all sessions (of any node)",
        "BadTooManyMonitoredItems",
    ),
    ("opcua", "max_subscriptions", "", "subscriptions in all sessions", "BadTooManySubscriptions"),
    (
        "opcua",
        "loop_share",
        "s per s",
        "processor time OPC UA's requests take on its thread, and as much again its "
        "notifications (`loop_burst_s` in a row after a quiet spell)",
        "requests wait, their connections' reading paused; notifications are sampled "
        "less often (`samples_skipped` of the machine's `opcua_items` status); a "
        "subscription's publishing waits, for at most "
        "`guard.PUBLISH_HOLD_MAX` (0.5 s) after its last publish",
    ),
]


def _option_classes() -> dict[str, Any]:
    from geo_server.recorder.recorder import RecorderLimits
    from geo_server.safefile import FileLimits
    from geo_server.service import ServiceLimits
    from geo_server.transports.interface import plugs

    return {
        **{plug.name: plug.limits() for plug in plugs()},
        "service": ServiceLimits,
        "files": FileLimits,
        "recorder": RecorderLimits,
    }


def _fault_and_descriptor_rows() -> list[str]:
    """Bounds that are constants, not options: faults (docs/faults.md) and the
    descriptors kept beside the connection caps (geo_server/descriptors.py)."""
    from geo_server.descriptors import RESERVE
    from geo_server.faults import MAX_FAULTS, MAX_PATTERN, MAX_TEXT
    from geo_server.fleetfile import MAX_FLEET_SIZE
    from geo_server.transports.ads.codec import MAX_ADDRESSES
    from geo_server.transports.ads.repeats import MAX_REPEAT_SIZE, MAX_REPEATS
    from geo_server.transports.modbus.plug import FLEET_BACKLOG
    from geo_server.transports.tcp import BACKLOG

    return [
        f"| faults | faults active on one machine | {MAX_FAULTS} | `faults.MAX_FAULTS` | "
        "refused: 0x70B |",
        f"| faults | one fault's text | {MAX_TEXT} characters | `faults.MAX_TEXT` | "
        "refused: 0x70B |",
        f"| faults | one `objects=` pattern (one per fault) | {MAX_PATTERN} characters | "
        "`faults.MAX_PATTERN` | refused: 0x70B |",
        f"| all | accept queue of each TCP listener | {BACKLOG} | `tcp.BACKLOG` | "
        "counted in the descriptor budget |",
        f"| Modbus | accept queue of each machine's port in a fleet | {FLEET_BACKLOG} | "
        "`modbus.plug.FLEET_BACKLOG` | counted in the descriptor budget; each port keeps at least "
        "4 connections, or the fleet does not start |",
        f"| fleet | machines of one fleet (`--fleet-size`, a fleet file) | {MAX_FLEET_SIZE} | "
        "`fleetfile.MAX_FLEET_SIZE` | refused at start |",
        f"| ADS | AMS addresses remembered from request headers (each decoded once) | "
        f"{MAX_ADDRESSES} | `codec.MAX_ADDRESSES` | forgotten all at once, decoded again |",
        f"| ADS | answers one connection keeps for Reads sent again | {MAX_REPEATS} | "
        "`repeats.MAX_REPEATS` | forgotten all at once, read again |",
        f"| ADS | one answer kept for a Read sent again | {MAX_REPEAT_SIZE} bytes | "
        "`repeats.MAX_REPEAT_SIZE` | not kept: read again each time |",
        f"| all | descriptors kept for files and the runtime | {RESERVE} | "
        "`descriptors.RESERVE` | the caps are shrunk to fit; too few: the server does not start |",
        *_opcua_guard_rows(),
    ]


def _opcua_guard_rows() -> list[str]:
    """The OPC UA guard's bounds (geo_server/transports/opcua/guard.py, logins.py)."""
    from geo_server.transports.opcua import apart, guard, logins, operations
    from geo_server.transports.opcua.guard import MAX_REQUEST, MIN_BUFFER, SESSIONS_PER_CONNECTION

    per_request = [
        f"| OPC UA | operations of one request: {name} | {most} | "
        "`operations.OPERATION_LIMITS` (advertised in ServerCapabilities/OperationLimits) | "
        "BadTooManyOperations, counted before the request is decoded |"
        for name, most in operations.OPERATION_LIMITS.items()
    ]
    return [
        *per_request,
        f"| OPC UA | RelativePath elements of one TranslateBrowsePathsToNodeIds | "
        f"{operations.MAX_PATH_ELEMENTS} | `operations.MAX_PATH_ELEMENTS` | BadTooManyOperations |",
        f"| OPC UA | subscriptions of one session | {guard.SUBSCRIPTIONS_PER_SESSION} | "
        "`guard.SUBSCRIPTIONS_PER_SESSION` | BadTooManySubscriptions |",
        f"| OPC UA | a monitored item's queue | {guard.MAX_QUEUE_SIZE} notifications | "
        "`guard.MAX_QUEUE_SIZE` | RevisedQueueSize (on Create and Modify; 0 or 1 asked: 1) |",
        f"| OPC UA | Publish responses not yet acknowledged, per subscription | "
        f"{guard.MAX_UNACKED} | `guard.MAX_UNACKED` | the oldest dropped (no Republish) |",
        f"| OPC UA | publishing interval, at least | {guard.MIN_PUBLISHING_MS:g} ms | "
        "`guard.MIN_PUBLISHING_MS` | RevisedPublishingInterval |",
        f"| OPC UA | one request message | {MAX_REQUEST} bytes | `guard.MAX_REQUEST` | "
        "BadRequestTooLarge; a chunk over the receive buffer (65535) is refused at its header: "
        "ERR BadTcpMessageTooLarge, closed |",
        f"| OPC UA | a Hello's receive and send buffers, at least | {MIN_BUFFER} bytes | "
        "`guard.MIN_BUFFER` (Part 6 §7.1.2.3) | ERR BadConnectionRejected, closed |",
        f"| OPC UA | sessions of one connection | {SESSIONS_PER_CONNECTION} | "
        "`guard.SESSIONS_PER_CONNECTION` | BadTooManySessions |",
        f"| OPC UA | the wait after a failed login from one address | "
        f"{logins.LOGIN_BACKOFF_FIRST_S:g} s, doubled per failure up to "
        f"{logins.LOGIN_BACKOFF_MAX_S:g} s | `logins.LOGIN_BACKOFF_*` | an attempt within it is "
        "refused unchecked (BadUserAccessDenied) |",
        f"| OPC UA | addresses whose failed logins are remembered | {logins.LOGIN_ADDRESSES} | "
        "`logins.LOGIN_ADDRESSES` | the oldest forgotten |",
        f"| OPC UA | snapshots waiting to be sent to OPC UA's process | {apart.SNAP_BACKLOG} | "
        "`apart.SNAP_BACKLOG` | the oldest dropped (counted in the machine's `opcua_items` "
        "status as `samples_late`); its monitored items skip those cycles |",
        f"| OPC UA | the wait for OPC UA's process to stop | {apart.STOP_WAIT_S:g} s | "
        "`apart.STOP_WAIT_S` | killed |",
    ]


def _default(cls: Any, name: str) -> Any:
    for f in fields(cls):
        if f.name == name:
            return f.default
    raise KeyError(f"{cls.__name__} has no field {name}")


def limits_table() -> str:
    """The *Limits* table (docs/limits.md): every bound with its default value."""
    from geo_server.listfile.syntax import MAX_LIST_BYTES
    from geo_server.transports.interface import plugs
    from geo_server.transports.modbus.codec import MAX_ADU

    classes = _option_classes()
    where = {"service": "all", "files": "files", "recorder": "recorder"}
    where |= {plug.name: plug.title for plug in plugs()}
    lines = [
        "| interface | limit | default | option | past it |",
        "|---|---|---|---|---|",
    ]
    for key, name, unit, what, past in _LIMITS:
        value = _default(classes[key], name)
        shown = f"{value:g}" if isinstance(value, float) else f"{value}"
        option = f"`{classes[key].__name__}.{name}`"
        lines.append(f"| {where[key]} | {what} | {shown} {unit} | {option} | {past} |")
    lines.append(
        f"| Modbus | one frame (MBAP + PDU) | {MAX_ADU} bytes | protocol | "
        "a header announcing more closes the connection |"
    )
    from geo_server.transports.share import FLEET_BURST, FLEET_RATE

    lines.append(
        "| ADS, Modbus | event-loop time one fleet machine's requests take (its share: "
        f"its even share, at least {FLEET_RATE:g}; at most {FLEET_BURST * 1000:g} ms at "
        f"once) | {FLEET_RATE:g} s per s (10 machines or more) | "
        "`transports.share.FLEET_RATE`, `FLEET_BURST` | its requests wait, their "
        "connections' reading paused, until the share is back (`throttled` in the "
        "fleet's status) |"
    )
    lines.append(
        f"| lists | one list file | {MAX_LIST_BYTES} bytes | `MAX_LIST_BYTES` | "
        "refused (reload rejected, machine unchanged) |"
    )
    lines.extend(_fault_and_descriptor_rows())
    from geo_server.dictionary import MAX_JSON_INT_CHARS, load_dictionary

    lines.append(
        f"| all | an object name | {load_dictionary().max_name_chars} characters | the "
        "longest name, alias or key spelling + `[65535]` (`Dictionary.max_name_chars`) | "
        "0x703 before any matching |"
    )
    lines.append(
        f"| all | a JSON integer (Zenoh payloads, web HMI bodies) | {MAX_JSON_INT_CHARS} "
        "characters | `MAX_JSON_INT_CHARS` | 0x706 before it is converted |"
    )
    return "\n".join(line.replace("  ", " ") for line in lines) + "\n"


def limits_page() -> str:
    """docs/limits.md: the Limits table with its introduction."""
    return (
        "# Limits\n\n<!-- generated by `python -m geo_server.docs`: do not edit -->\n\n"
        "What one client can make the server hold or wait for, and what happens past each "
        "bound (generated from the option classes; every one is a field you can change). "
        "Who can reach what: [security.md](security.md).\n\n" + limits_table()
    )


#: The generated pages under docs/ and what writes them.
PAGES: dict[str, Callable[[], str]] = {
    "objects.md": objects_page,
    "modbus-map.md": modbus_page,
    "list_checks.md": checks_page,
    "ads-symbols.md": symbols_page,
    "limits.md": limits_page,
}


#: README blocks and what writes them.
README_BLOCKS: dict[str, Callable[[], str]] = {"limits": limits_table}

_BLOCK = re.compile(
    r"(<!-- BEGIN (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- END (?P=name) -->)", re.S
)


def render(text: str) -> str:
    """README text with every generated block replaced by its current content."""

    def repl(m: re.Match[str]) -> str:
        name = m.group("name")
        if name not in README_BLOCKS:
            return m.group(0)
        return m.group(1) + README_BLOCKS[name]() + m.group(4)

    return _BLOCK.sub(repl, text)


def main(argv: list[str] | None = None) -> int:
    readme = Path(argv[0]) if argv else ROOT / "README.md"
    _update(readme, render(readme.read_text(encoding="utf-8")))
    docs = ROOT / "docs"
    if not argv and docs.is_dir():  # a source checkout, not an installed wheel
        for name, page in PAGES.items():
            _update(docs / name, page())
    return 0


def _update(path: Path, new: str) -> None:
    if not path.exists() or path.read_text(encoding="utf-8") != new:
        path.write_text(new, encoding="utf-8")
        print(f"updated {path}")


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
