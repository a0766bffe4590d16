"""`geo-client`: talk to a running geo-server (transports arrive with issues 4–6)."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    print(
        "geo-client: no transport is available yet (Zenoh, Modbus and ADS come next); "
        "use `geo-server objects` to list the objects",
        file=sys.stderr,
    )
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
