"""The kernel's per-cycle inputs (docs/design.md §11): the source vector S of this cycle's
commands and the gather G of every input a compensation needs from them. Shared by the
kernel and the compensation modules, which fill their part of G at load time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True, eq=False)
class SourceVector:
    """S = [pos | vel | acc | trunc(rev) | 0 | 1 | direction]: this cycle's commands and
    the direction state in one vector, so that every per-cycle input is a gather from S.

    The direction is the sign of the command velocity, held at standstill; it starts from
    `anwahl_losekomp` (000 §2.3.2, P-AXIS-00021; docs/design.md §3.6) and is kept across
    reloads.
    """

    n: int
    S: np.ndarray
    inputs: np.ndarray  # S[:4n]: filled with one concatenate
    pos: np.ndarray
    vel: np.ndarray
    rev: np.ndarray  # cycles until a reversal known in advance (< 0: none)
    dir: np.ndarray  # ±1
    dp: np.ndarray  # (direction, position) as one [2, n] view of S
    zero: int  # index of the constant 0
    one: int  # index of the constant 1

    @classmethod
    def create(cls, n: int, init_dir: list[float]) -> SourceVector:
        S = np.zeros(5 * n + 2)
        S[4 * n + 1] = 1.0
        d = S[4 * n + 2 :]
        d[:] = init_dir
        dp = np.lib.stride_tricks.as_strided(
            S[4 * n + 2 :], shape=(2, n), strides=(-(4 * n + 2) * 8, 8), writeable=False
        )
        return cls(
            n=n,
            S=S,
            inputs=S[: 4 * n],
            pos=S[:n],
            vel=S[n : 2 * n],
            rev=S[3 * n : 4 * n],
            dir=d,
            dp=dp,
            zero=4 * n,
            one=4 * n + 1,
        )

    def index(self, block: int, slots: np.ndarray | int) -> np.ndarray | int:
        """Index into S of block (POS, VEL, ACC, REV) of the axes in `slots`."""
        return block * self.n + slots

    def dir_index(self, slots: np.ndarray) -> np.ndarray:
        """Index into S of the direction of the axes in `slots`."""
        return 4 * self.n + 2 + slots


@dataclass(slots=True, eq=False)
class Gather:
    """G = S[src]: every input that only needs this cycle's commands, with one `take`.

    G = [xt vel | xt acc | friction vel | 1-D queries | plane (u, v) | mode 3 (x, y, 1)].
    One `sign` serves the first three parts (`ns` entries), one subtract and one divide
    the query parts q = G[ns:], q ← (q − sub)/div (neutral 0 and 1 where nothing is
    scaled); before that, the 1-D and plane queries over a modulo master (the first `nw`
    query entries) are wrapped into [0, period) (000 p.31). `layout` allocates G from the
    part sizes; each compensation's builder fills `src`, `sub`, `div`, `per` and `wrap`
    for its part (arrays over the whole of G) and keeps views of its values.
    """

    G: np.ndarray
    src: np.ndarray  # index into S of every entry
    sub: np.ndarray
    div: np.ndarray
    per: np.ndarray
    wrap: np.ndarray
    sign_in: np.ndarray  # G[:ns]
    sign: np.ndarray  # sign(G[:ns])
    q: np.ndarray  # G[ns:]
    q_sub: np.ndarray
    q_div: np.ndarray
    w: np.ndarray  # G[ns:ns + nw]: the entries that may wrap
    w_per: np.ndarray
    w_wrap: np.ndarray
    w_tmp: np.ndarray
    any: bool
    any_sign: bool
    any_q: bool
    any_wrap: bool = False

    @classmethod
    def layout(cls, ns: int, nw: int, nq: int) -> Gather:
        """`ns` sign entries, then `nq` query entries of which the first `nw` may wrap."""
        ng = ns + nq
        G = np.zeros(ng)
        src = np.full(ng, -1, dtype=np.int64)
        sub, div, per = np.zeros(ng), np.ones(ng), np.ones(ng)
        wrap = np.zeros(ng, dtype=bool)
        return cls(
            G=G,
            src=src,
            sub=sub,
            div=div,
            per=per,
            wrap=wrap,
            sign_in=G[:ns],
            sign=np.zeros(ns),
            q=G[ns:],
            q_sub=sub[ns:],
            q_div=div[ns:],
            w=G[ns : ns + nw],
            w_per=per[ns : ns + nw],
            w_wrap=wrap[ns : ns + nw],
            w_tmp=np.zeros(nw),
            any=bool(ng),
            any_sign=bool(ns),
            any_q=bool(nq),
        )

    def finish(self) -> None:
        """After every part has been filled."""
        assert (self.src >= 0).all(), "every gather entry has a source"
        self.any_wrap = bool(self.w_wrap.any())


@dataclass(frozen=True, slots=True, eq=False)
class GatherWork:
    """The gather's buffers for a leading shape (one cycle: the `Gather`'s own arrays; a
    pass of B cycles: [B, ...])."""

    S: np.ndarray  # [*lead, len(S)]
    G: np.ndarray  # [*lead, len(G)]
    sign_in: np.ndarray  # G[..., :ns]
    sign: np.ndarray  # [*lead, ns]
    q: np.ndarray  # G[..., ns:]
    w: np.ndarray  # G[..., ns:ns + nw]
    w_tmp: np.ndarray  # [*lead, nw]

    @classmethod
    def of(cls, g: Gather, S: np.ndarray) -> GatherWork:
        """The single cycle's: `g`'s own buffers."""
        return cls(S=S, G=g.G, sign_in=g.sign_in, sign=g.sign, q=g.q, w=g.w, w_tmp=g.w_tmp)

    @classmethod
    def batch(cls, g: Gather, SB: np.ndarray) -> GatherWork:
        """Buffers for a pass of len(SB) cycles."""
        B, ns, nw = len(SB), len(g.sign), len(g.w)
        G = np.zeros((B, len(g.G)))
        return cls(
            S=SB,
            G=G,
            sign_in=G[:, :ns],
            sign=np.zeros((B, ns)),
            q=G[:, ns:],
            w=G[:, ns : ns + nw],
            w_tmp=np.zeros((B, nw)),
        )


def gather(g: Gather, w: GatherWork) -> None:
    """G = S[src], then sign(G[:ns]) and, for the query entries, the position wrapped into
    [0, period) over a modulo master (000 p.31) and q ← (q − sub)/div: every input that
    only needs this cycle's commands, for a single cycle and a pass alike."""
    w.S.take(g.src, axis=-1, out=w.G)
    if g.any_sign:
        np.sign(w.sign_in, w.sign)
    if g.any_q:
        q = w.q
        if g.any_wrap:
            np.mod(w.w, g.w_per, w.w_tmp)
            np.copyto(w.w, w.w_tmp, where=g.w_wrap)
        np.subtract(q, g.q_sub, q)
        np.divide(q, g.q_div, q)
