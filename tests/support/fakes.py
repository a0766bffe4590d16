"""Stand-ins the tests share: a virtual clock for the exact engine, and asyncio's side of
a socket without the socket."""

from __future__ import annotations

import asyncio

P = 1_000_000  # 1 ms in ns


class VirtualClock:
    """`clock` (ns) and `sleep` (s) for `Scheduler`: time moves only when told."""

    def __init__(self) -> None:
        self.t = 1_000 * P

    def clock(self) -> int:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += round(seconds * 1e9)


class Wire(asyncio.Transport):
    """What a protocol writes, kept (asyncio's side of a socket, no socket)."""

    def __init__(self) -> None:
        super().__init__()
        self.out: list[bytes] = []

    def write(self, data: bytes | bytearray | memoryview) -> None:
        self.out.append(bytes(data))

    def is_closing(self) -> bool:
        return False

    def get_extra_info(self, name: str, default: object = None) -> object:
        return ("127.0.0.1", 1) if name == "peername" else default

    def pause_reading(self) -> None:
        pass

    def resume_reading(self) -> None:
        pass

    def get_write_buffer_size(self) -> int:
        return 0

    def abort(self) -> None:
        pass

    def close(self) -> None:
        pass
