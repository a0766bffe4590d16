"""What both command-line programs share about their terminal."""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable


def closes_quietly_on_broken_pipe(main: Callable[..., int]) -> Callable[..., int]:
    """`geo-server objects | head` must not end in a traceback.

    When the reader of stdout goes away, Python raises BrokenPipeError at the next write
    and again when it flushes stdout at exit. Point stdout at /dev/null so the exit flush
    succeeds, and end with status 0: the reader took what it wanted (the recipe of the
    Python documentation, "Note on SIGPIPE").
    """

    @functools.wraps(main)
    def wrapper(*args: object, **kwargs: object) -> int:
        try:
            return main(*args, **kwargs)
        except BrokenPipeError:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            return 0

    return wrapper
