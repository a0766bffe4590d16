"""Console-script entry points that import nothing before they can catch Ctrl-C.

A console script imports its entry's module first; Ctrl-C while that import still runs
(Zenoh, numpy: tenths of a second) printed a traceback of thirty lines. The entries here
import the program's module inside their `try`, so the only window left is the
interpreter's own start-up.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys

#: The exit status of a program stopped by Ctrl-C (128 + SIGINT), as shells report it.
EXIT_INTERRUPTED = 130


def client() -> None:
    """`geo-client`: Ctrl-C at any moment ends it with one line and status 130 (issue 45
    #18)."""
    try:
        from geo_server.client.cli import main

        code = main()
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        code = EXIT_INTERRUPTED
    exit_now(code)


def exit_now(code: int) -> None:
    """End the process at once, its output flushed, without the interpreter's
    finalization: that unwinds the stack of every thread still in the interpreter, and
    one inside Rust or C++ code (a Zenoh thread, LLVM compiling) then aborts the
    process (SIGABRT, `FATAL: exception not rethrown`) — as after a Ctrl-C that came
    while Zenoh opened its session."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    os._exit(code)
