"""Figures of the twin (geo_server/twin/plots.py): both files written, the PNG valid and of a
reasonable size (read from its header, no image library), the SVG titled; and a clear
error without matplotlib."""

from __future__ import annotations

import importlib.util
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from geo_server.twin import plots
from geo_server.twin.iso230 import Evaluation, evaluate, targets_iso

needs_matplotlib = pytest.mark.skipif(
    importlib.util.find_spec("matplotlib") is None, reason="matplotlib not installed"
)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from the IHDR chunk, which must follow the signature."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_SIGNATURE, "not a PNG"
    length, kind = struct.unpack(">I4s", head[8:16])
    assert (length, kind) == (13, b"IHDR")
    width, height = struct.unpack(">II", head[16:24])
    return width, height


def check_files(paths: tuple[Path, Path], stem: Path, title: str) -> tuple[int, int]:
    png, svg = paths
    assert (png, svg) == (stem.parent / f"{stem.name}.png", stem.parent / f"{stem.name}.svg")
    width, height = png_size(png)
    assert 800 <= width <= 3000 and 400 <= height <= 3000, (width, height)
    assert png.stat().st_size > 10_000
    text = svg.read_text(encoding="utf-8")
    assert text.lstrip().startswith("<?xml") and "<svg" in text
    assert title in text
    return width, height


def sample(seed: int, lag: float, scatter: float) -> Evaluation:
    rng = np.random.default_rng(seed)
    p = targets_iso(0.0, 500.0, 11, seed=seed)
    e = 0.04 * p + 3 * np.sin(p / 120) + 0.8 * np.sin(2 * np.pi * p / 10)
    up = e - lag / 2 + rng.normal(0, scatter, (5, p.size))
    down = e + lag / 2 + rng.normal(0, scatter, (5, p.size))
    return evaluate(p, up, down)


@pytest.mark.slow
@needs_matplotlib
def test_error_curves_before_and_after(tmp_path):
    stem = tmp_path / "figs" / "x_errors.v1"  # a dot in the name is kept, folders made
    title = "X axis ISO 230-2 test"
    paths = plots.error_curves(sample(1, 8.0, 0.6), sample(2, 1.0, 0.6), stem, title)
    _, height2 = check_files(paths, stem, title)
    single = plots.error_curves(sample(1, 8.0, 0.6), None, tmp_path / "single", title)
    _, height1 = check_files(single, tmp_path / "single", title)
    assert height2 > 1.5 * height1  # the second panel


@needs_matplotlib
def test_hysteresis(tmp_path):
    title = "X reversal values"
    paths = plots.hysteresis(sample(3, 8.0, 0.5), tmp_path / "rev", title)
    check_files(paths, tmp_path / "rev", title)


@needs_matplotlib
@pytest.mark.parametrize("hours", [0.5, 4.0])
def test_warmup(tmp_path, hours):
    t = np.linspace(0.0, hours * 3600, 200)
    temps = {"x_screw": 35 - 15 * np.exp(-t / 1800), "spindle": 28 - 8 * np.exp(-t / 3600)}
    residual = {"without TEMPC": 0.6 * (temps["x_screw"] - 20), "with TEMPC": 0.3 * np.sin(t)}
    title = f"warm-up {hours} h"
    paths = plots.warmup(t, residual, temps, tmp_path / "warm", title)
    check_files(paths, tmp_path / "warm", title)
    svg = paths[1].read_text(encoding="utf-8")
    assert ("time (h)" in svg) == (hours > 3)
    assert ("time (min)" in svg) == (hours <= 3)


@needs_matplotlib
def test_warmup_rejects_series_of_another_length(tmp_path):
    with pytest.raises(ValueError, match="'X'"):
        plots.warmup([0, 1, 2], {"X": [0, 1]}, {}, tmp_path / "w", "t")


def test_without_matplotlib_a_clear_error(tmp_path, monkeypatch):
    # a None entry in sys.modules makes the import fail as if it were not installed
    for name in ("matplotlib", "matplotlib.figure", "matplotlib.backends.backend_agg"):
        monkeypatch.setitem(sys.modules, name, None)
    ev = sample(1, 8.0, 0.6)
    for call in (
        lambda: plots.error_curves(ev, None, tmp_path / "e", "t"),
        lambda: plots.hysteresis(ev, tmp_path / "h", "t"),
        lambda: plots.warmup([0, 1], {"X": [0, 1]}, {"T": [20, 21]}, tmp_path / "w", "t"),
    ):
        with pytest.raises(RuntimeError, match=r"pip install geo-server\[plots\]"):
            call()
    assert list(tmp_path.iterdir()) == []
