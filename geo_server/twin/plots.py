"""Figures of a positioning test and of a warm-up, written as PNG and SVG (optional).

matplotlib is an optional dependency (`pip install geo-server[plots]`); it is imported
inside the functions, so the rest of geo-server runs without it. The figures are drawn
on matplotlib's non-interactive Agg canvas, object-oriented (no pyplot, no global
backend switch, nothing shown on screen).

Every function writes `<stem>.png` (150 dpi) and `<stem>.svg` with the title in the
files' metadata, and returns the two paths. The presentation follows ISO 230-2:2014 §7
(presentation of results): the mean unidirectional positioning deviations x̄_i↑, x̄_i↓
(§2.10) over the target positions with the bands x̄_i ± 2 s_i (§2.15, coverage factor 2),
and the axis figures A, E, M, B, R (§2.13 … §2.24).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from geo_server.twin.iso230 import STANDARD, Evaluation

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

MISSING = "plots need matplotlib: pip install geo-server[plots]"

UP_COLOR = "tab:blue"
DOWN_COLOR = "tab:red"
MEAN_COLOR = "black"
DPI = 150


def available() -> bool:
    """Whether matplotlib can be imported, asked before minutes of measuring: a program
    that plots at its end checks this at its start."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def _figure(width: float, height: float) -> Figure:
    """A figure on an Agg canvas (RuntimeError `MISSING` without matplotlib)."""
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise RuntimeError(MISSING) from exc
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path_stem: Path | str, title: str) -> tuple[Path, Path]:
    """Write `<stem>.png` and `<stem>.svg` (folders created); the title in the metadata,
    no date in the SVG so the same data gives the same file."""
    stem = Path(path_stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    png = stem.with_name(stem.name + ".png")
    svg = stem.with_name(stem.name + ".svg")
    fig.savefig(png, dpi=DPI, metadata={"Title": title})
    fig.savefig(svg, metadata={"Title": title, "Date": None})
    return png, svg


def _f(v: float) -> str:
    """One decimal, with the typographic minus the tick labels use."""
    return f"{v + 0.0:.1f}".replace("-", "\u2212")


def _figures_text(ev: Evaluation, unit: str) -> str:
    """The axis figures of ISO 230-2:2014 as lines of a text box."""

    def line(symbol: str, field: str, directional: bool = True) -> str:
        text = f"{symbol} = {_f(getattr(ev, field))}"
        if directional:
            up, down = _f(getattr(ev, field + "_up")), _f(getattr(ev, field + "_down"))
            text += f"  ({symbol}↑ {up}, {symbol}↓ {down})"
        return text

    return "\n".join(
        [
            f"{STANDARD} ({unit})",
            line("A", "accuracy"),
            line("E", "systematic"),
            line("M", "mean_error", directional=False),
            line("R", "repeatability"),
            line("B", "reversal", directional=False) + f"  ($\\bar{{B}}$ = {_f(ev.mean_reversal)})",
            f"n = {ev.n} runs, m = {ev.m} targets",
        ]
    )


def _deviation_panel(
    ax: Axes, ev: Evaluation, label: str, unit: str, position_unit: str, legend: bool
) -> None:
    """x̄_i↑, x̄_i↓ with ±2s bands and x̄_i over P_i; the figures in a box to the right."""
    p = ev.targets
    handles: list[Artist] = []
    for xbar, s, color, arrow, word in (
        (ev.mean_up, ev.s_up, UP_COLOR, r"\uparrow", "positive"),
        (ev.mean_down, ev.s_down, DOWN_COLOR, r"\downarrow", "negative"),
    ):
        (line,) = ax.plot(
            p,
            xbar,
            color=color,
            marker="o",
            markersize=3.5,
            linewidth=1.4,
            label=rf"$\bar{{x}}_i{arrow}$ mean deviation, {word} approach",
        )
        band = ax.fill_between(
            p,
            xbar - 2 * s,
            xbar + 2 * s,
            color=color,
            alpha=0.18,
            linewidth=0,
            label=rf"$\bar{{x}}_i{arrow} \pm 2s_i{arrow}$ (coverage factor 2)",
        )
        handles += [line, band]
    (mean,) = ax.plot(
        p,
        ev.mean,
        color=MEAN_COLOR,
        linestyle="--",
        linewidth=1.0,
        label=r"$\bar{x}_i$ mean bidirectional deviation",
    )
    handles.append(mean)
    ax.axhline(0.0, color="0.5", linewidth=0.6, zorder=0)
    if label:
        ax.set_title(label, loc="left", fontsize="medium")
    ax.set_ylabel(f"deviation actual − target ({unit})")
    ax.set_xlabel(f"target position $P_i$ ({position_unit})")
    ax.grid(True, linewidth=0.4, alpha=0.6)
    ax.margins(x=0.02)
    ax.text(
        1.02,
        0.0,
        _figures_text(ev, unit),
        transform=ax.transAxes,
        va="bottom",
        ha="left",
        fontsize="small",
        family="DejaVu Sans Mono",
        bbox={"boxstyle": "round,pad=0.4", "facecolor": "white", "edgecolor": "0.6"},
    )
    if legend:
        ax.legend(
            handles=handles,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            fontsize="small",
            frameon=True,
        )


def error_curves(
    before: Evaluation,
    after: Evaluation | None,
    path_stem: Path | str,
    title: str,
    *,
    unit: str = "µm",
    position_unit: str = "mm",
) -> tuple[Path, Path]:
    """The positioning deviations of an ISO 230-2:2014 test (§7 presentation): x̄_i↑ and
    x̄_i↓ (§2.10) with their bands x̄ ± 2s (§2.15) and x̄_i (§2.11) over the targets P_i,
    and the figures A, E, M, R, B in a box. With `after` (the test repeated with the
    compensation active) a second panel below, on its own deviation scale.

    Writes `<path_stem>.png` and `.svg`; returns their paths. `unit`: the deviations'
    (µm; "0.001°" on a rotary axis), shown in the labels and the box heading, not after
    each number; `position_unit`: the targets' (mm or °).
    """
    panels: list[tuple[Evaluation, str]] = [(before, "")]
    if after is not None:
        panels = [(before, "before compensation"), (after, "after compensation")]
    fig = _figure(11.0, 4.6 * len(panels) + 0.6)
    axes = fig.subplots(len(panels), 1, squeeze=False)[:, 0]
    for k, (ax, (ev, label)) in enumerate(zip(axes, panels, strict=True)):
        _deviation_panel(ax, ev, label, unit, position_unit, legend=k == 0)
    fig.suptitle(title)
    return _save(fig, path_stem, title)


def hysteresis(
    evaluation: Evaluation,
    path_stem: Path | str,
    title: str,
    *,
    unit: str = "µm",
    position_unit: str = "mm",
) -> tuple[Path, Path]:
    """The reversal value B_i = x̄_i↑ − x̄_i↓ (ISO 230-2:2014 §2.12) over the targets P_i,
    with the mean reversal value B̄ (§2.14) and B = max |B_i| (§2.13). A negative B_i is
    lost motion (the axis stops short of the target in both directions).

    Writes `<path_stem>.png` and `.svg`; returns their paths.
    """
    ev = evaluation
    fig = _figure(11.0, 4.6)
    ax = fig.subplots()
    ax.axhline(0.0, color="0.5", linewidth=0.6, zorder=0)
    ax.plot(
        ev.targets,
        ev.reversal_i,
        color="tab:purple",
        marker="o",
        markersize=4,
        linewidth=1.4,
        label=r"$B_i = \bar{x}_i\uparrow - \bar{x}_i\downarrow$ reversal value",
    )
    ax.axhline(
        ev.mean_reversal,
        color="tab:purple",
        linestyle="--",
        linewidth=1.0,
        label=rf"$\bar{{B}}$ = {_f(ev.mean_reversal)} ({unit}) mean reversal value",
    )
    k = int(np.argmax(np.abs(ev.reversal_i)))
    ax.plot(
        [ev.targets[k]],
        [ev.reversal_i[k]],
        linestyle="none",
        marker="o",
        markersize=9,
        markerfacecolor="none",
        markeredgecolor="black",
        label=f"$B$ = max |$B_i$| = {_f(ev.reversal)} ({unit})",
    )
    ax.set_ylabel(f"reversal value $B_i$ ({unit})")
    ax.set_xlabel(f"target position $P_i$ ({position_unit})")
    ax.grid(True, linewidth=0.4, alpha=0.6)
    ax.margins(x=0.02, y=0.15)
    ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    ax.set_title(f"{STANDARD} §2.12–2.14, n = {ev.n} runs", loc="left", fontsize="medium")
    fig.suptitle(title)
    return _save(fig, path_stem, title)


def _time_axis(times_s: np.ndarray) -> tuple[np.ndarray, str]:
    """Times in s, min or h: hours from a span of 3 h, minutes from 10 min."""
    span = float(np.ptp(times_s)) if times_s.size else 0.0
    if span >= 3 * 3600:
        return times_s / 3600.0, "h"
    if span >= 600:
        return times_s / 60.0, "min"
    return times_s, "s"


def warmup(
    times_s: ArrayLike,
    residual_um: Mapping[str, ArrayLike],
    temperatures_C: Mapping[str, ArrayLike],
    path_stem: Path | str,
    title: str,
    *,
    unit: str = "µm",
) -> tuple[Path, Path]:
    """A warm-up: the residual positioning error (top, one line per series, e.g. per axis
    or with/without temperature compensation) and the sensor temperatures (bottom) over
    time, the two panels sharing the time axis (s, min, or h from a span of 3 h).

    Every series must have one value per time. Writes `<path_stem>.png` and `.svg`;
    returns their paths.
    """
    t = np.asarray(times_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"times must be one-dimensional, got shape {t.shape}")
    series: list[tuple[str, dict[str, np.ndarray]]] = []
    for kind, data in (("residual", residual_um), ("temperature", temperatures_C)):
        arrays = {}
        for name, values in data.items():
            a = np.asarray(values, dtype=np.float64)
            if a.shape != t.shape:
                raise ValueError(f"{kind} {name!r}: shape {a.shape}, times {t.shape}")
            arrays[name] = a
        series.append((kind, arrays))
    x, time_unit = _time_axis(t)
    fig = _figure(11.0, 6.8)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    for name, a in series[0][1].items():
        top.plot(x, a, linewidth=1.3, label=name)
    top.axhline(0.0, color="0.5", linewidth=0.6, zorder=0)
    top.set_ylabel(f"residual error ({unit})")
    for name, a in series[1][1].items():
        bottom.plot(x, a, linewidth=1.2, label=name)
    bottom.set_ylabel("temperature (°C)")
    bottom.set_xlabel(f"time ({time_unit})")
    for ax in (top, bottom):
        ax.grid(True, linewidth=0.4, alpha=0.6)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small")
    top.margins(x=0)
    fig.suptitle(title)
    return _save(fig, path_stem, title)


__all__ = ["MISSING", "error_curves", "hysteresis", "warmup"]
