"""The recorder on the command line (docs/recorder.md §7): `geo-server run --record …`,
`geo-server replay`, `geo-server compare`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from geo_server.errors import AdsError
from geo_server.recorder.compare import compare, parse_tolerances
from geo_server.recorder.inputs import load_inputs
from geo_server.recorder.paths import default_record_dir
from geo_server.recorder.recorder import RecordSpec
from geo_server.recorder.selection import SelectionError
from geo_server.recorder.trace import TraceFileError, load_trace
from geo_server.service import ObjectService


def add_spec_arguments(p: argparse.ArgumentParser, prefix: str = "") -> None:
    """The options of a recording (`--record SEL …`, `--record-every`, …)."""
    p.add_argument(
        f"--{prefix}record",
        action="append",
        metavar="SEL",
        help="record these objects (repeatable): NAME, NAME@AXIS, a wildcard TEMPC::*, or "
        "an address 0x120300:0x10043 (docs/recorder.md)",
    )
    p.add_argument(
        f"--{prefix}record-every",
        type=int,
        default=1,
        metavar="N",
        help="a sample every N cycles (default 1)",
    )
    p.add_argument(
        f"--{prefix}record-trigger",
        metavar="EXPR",
        help="start on a condition: 'SIM::program_running rising', 'X@1 > 5'",
    )
    p.add_argument(
        f"--{prefix}record-pre",
        type=int,
        default=0,
        metavar="N",
        help="samples kept before the trigger",
    )
    p.add_argument(
        f"--{prefix}record-post",
        type=int,
        default=1000,
        metavar="N",
        help="samples after the trigger (then the recording is written)",
    )


def spec_from_args(args: argparse.Namespace) -> RecordSpec:
    spec = RecordSpec(
        list(args.record),
        every=args.record_every,
        trigger=args.record_trigger,
        pre=args.record_pre,
        post=args.record_post,
    )
    spec.check()
    return spec


def add_run_arguments(r: argparse.ArgumentParser) -> None:
    g = r.add_argument_group("recording (docs/recorder.md)")
    add_spec_arguments(g)  # type: ignore[arg-type]
    g.add_argument(
        "--record-out",
        default="geo-trace.csv",
        metavar="FILE",
        help="trace file of --record (.csv or .parquet), where you say; the inputs go "
        "beside it as FILE-stem.inputs.jsonl (default geo-trace.csv)",
    )
    g.add_argument(
        "--record-dir",
        metavar="DIR",
        help="the only folder recordings asked for over an interface (Zenoh cmd/record) "
        "are written to (default: recordings/ beside the start-up list; for the shipped "
        "default machine ./recordings; a fleet: one subfolder per machine)",
    )


def record_dir(
    args: argparse.Namespace, machine: str = "", startup: Path | None = None
) -> Path | None:
    """The recordings folder of `--record-dir` (a fleet's machine: its subfolder, also
    of the default folder beside `startup`); None: the service's default."""
    if args.record_dir:
        base = Path(args.record_dir)
    elif machine and startup is not None:
        base = default_record_dir(startup)
    else:
        return None
    return base / machine if machine else base


def start_from_args(args: argparse.Namespace, service: ObjectService) -> bool:
    """`run --record`: start recording before the first cycle; False after saying why.
    Sets the recordings folder of `--record-dir` either way."""
    service.recordings.record_dir = record_dir(args)
    if not args.record:
        return True
    try:
        # the local user's own file name: written where it says (docs/recorder.md §7)
        st = service.recordings.start(
            spec_from_args(args), args.record_out, args.machine, local=True
        )
    except (AdsError, ValueError) as exc:
        why = exc.message if isinstance(exc, AdsError) else exc
        print(f"error: --record: {why}", file=sys.stderr)
        return False
    print(f"recording {st['columns']} values to {st['file']}", file=sys.stderr)
    return True


def finish(service: ObjectService) -> None:
    """Write the recording (once its trigger's samples are in, or at the end of `run`)."""
    if service.recordings.recording is None:
        return
    try:
        done = service.recordings.stop()
    except AdsError as exc:
        print(f"error: recording: {exc.message}", file=sys.stderr)
        return
    print(
        f"recording written: {done['file']} ({done['rows']} rows), inputs "
        f"{done['inputs_file']} ({done['inputs']} lines)",
        flush=True,
    )


# ---------------------------------------------------------------------- replay, compare


def add_replay_parser(sub: Any) -> None:
    p = sub.add_parser(
        "replay",
        help="replay recorded inputs into a stepped run and record it",
        description="Run a fresh machine stepped, apply the inputs a recording captured "
        "in their cycles, record the same objects, write the trace (docs/recorder.md §5).",
    )
    p.add_argument("inputs", help="inputs file (FILE.inputs.jsonl)")
    p.add_argument("startup", nargs="?", help="start-up list (default: the default machine)")
    p.add_argument("--cycles", type=int, required=True, help="cycles to run")
    p.add_argument("--out", required=True, help="trace file to write (.csv or .parquet)")
    p.add_argument("--not-homed", action="store_true", help="start with the axes not homed")
    p.add_argument("--cycle-ms", type=float, default=1.0)
    p.add_argument("--time-scale", type=float, help="the twin's time scale")
    add_spec_arguments(p)
    p.set_defaults(func=_replay)


def _replay(args: argparse.Namespace) -> int:
    from geo_server.listfile import ListFileError
    from geo_server.paths import default_startup_list
    from geo_server.recorder.replay import replay

    if not args.record:
        print("error: replay needs --record SEL (what to record)", file=sys.stderr)
        return 2
    startup = Path(args.startup) if args.startup else default_startup_list()
    try:
        trace = replay(
            startup,
            load_inputs(args.inputs),
            spec_from_args(args),
            args.cycles,
            homed=not args.not_homed,
            cycle_ms=args.cycle_ms,
            time_scale=args.time_scale,
        )
        trace.save(args.out)
    except (TraceFileError, SelectionError, ListFileError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"replayed {args.cycles} cycles: {args.out} ({len(trace)} rows)")
    return 0


def add_compare_parser(sub: Any) -> None:
    p = sub.add_parser(
        "compare",
        help="compare a trace with a golden one (exit 1 when they differ)",
        description="Compare NEW against GOLDEN by cycle with per-object tolerances; "
        "prints a readable diff. Exit 0: match, 1: differ, 2: unreadable.",
    )
    p.add_argument("golden")
    p.add_argument("new")
    p.add_argument(
        "--tol",
        action="append",
        default=[],
        metavar="PATTERN=VALUE",
        help="tolerance of the columns PATTERN matches: TEMPC::*=0.5, *@2=1%%",
    )
    p.add_argument(
        "--default-tol",
        type=float,
        default=0.0,
        help="tolerance of every other column (default 0: equal)",
    )
    p.set_defaults(func=_compare)


def _compare(args: argparse.Namespace) -> int:
    try:
        result = compare(
            load_trace(args.golden),
            load_trace(args.new),
            parse_tolerances(args.tol),
            args.default_tol,
        )
    except (TraceFileError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(result.report())
    return 0 if result.ok else 1
