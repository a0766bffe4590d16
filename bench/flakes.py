"""The stress check: the whole suite several times in a row next to busy processes.

A CI runner is rarely quiet. This runs `python -m pytest -q` (the README's test command,
with this interpreter, in this checkout) `--runs` times in a row while `--busy` processes
each spin a core, and prints one line per run and the failures by name. The target is
no failure in any run: a test that fails here and passes alone is a flake, and a flake
is a bug in the product or the test, fixed at its cause (never retried).

    python bench/flakes.py [--runs 3] [--busy 2] [-- PYTEST_ARGS...]

Exit status 0 when every run passed, 1 otherwise. The busy processes end with it (they
are its children, and each also stops by itself after `--limit` seconds).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: a process that keeps one core busy for at most `limit` seconds
SPIN = "import time\nend = time.monotonic() + {limit}\nwhile time.monotonic() < end:\n    pass\n"

#: pytest's closing line, e.g. "2 failed, 2051 passed, 169 skipped in 612.3s"
SUMMARY = re.compile(r"^=*\s*(?P<body>(\d+ \w+(, )?)+) in (?P<secs>[\d.]+)s")
FAILED = re.compile(r"^(FAILED|ERROR) (\S+)")


def run_suite(pytest_args: list[str], log: Path) -> tuple[int, str, list[str], float]:
    """One run of the suite, its whole output in `log`: (exit code, its summary, the
    failed tests, seconds)."""
    t0 = time.monotonic()
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *pytest_args],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    secs = time.monotonic() - t0
    log.write_text(done.stdout + done.stderr, encoding="utf-8")
    summary, failed = "no summary", []
    for line in done.stdout.splitlines():
        if m := SUMMARY.match(line.strip("= ")):
            summary = m.group("body")
        if m := FAILED.match(line):
            failed.append(m.group(2))
    return done.returncode, summary, failed, secs


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--busy", type=int, default=2, help="CPU-bound processes beside it")
    ap.add_argument("--limit", type=float, default=3 * 3600, help="the busy ones' lifetime (s)")
    ap.add_argument("--logs", default=tempfile.gettempdir(), help="folder of each run's output")
    ap.add_argument("pytest_args", nargs="*", help="after --: passed to pytest")
    args = ap.parse_args()
    spin = SPIN.format(limit=args.limit)
    busy = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(args.busy)]
    bad = 0
    try:
        print(f"the suite {args.runs} times next to {args.busy} busy processes", flush=True)
        for i in range(1, args.runs + 1):
            log = Path(args.logs) / f"flakes-run{i}.log"
            code, summary, failed, secs = run_suite(args.pytest_args, log)
            bad += code != 0
            print(f"run {i}: exit {code}, {summary}, {secs / 60:.1f} min ({log})", flush=True)
            for name in failed:
                print(f"  {name}", flush=True)
    finally:
        for p in busy:
            p.kill()
            p.wait()
    print(f"{args.runs - bad} of {args.runs} runs passed", flush=True)
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
