"""ISO 230-2:2014 evaluation (geo_server/twin/iso230.py), checked by hand.

Every expected value below is worked out in the comments from the definitions of
ISO 230-2:2014 §2.10 … §2.24, never by calling the module.
"""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from geo_clients.plc_tempcomp import load_reference

from geo_server.twin.iso230 import (
    DEVIATIONS_HEADER,
    REFERENCE_HEADER,
    Evaluation,
    deviations_csv,
    evaluate,
    reference_csv,
    reference_rows,
    targets_iso,
)

# ============================================================================ by hand

# 3 targets, 3 runs. Three values m−d, m, m+d (any order) have mean m and sample standard
# deviation √((d² + 0 + d²)/(3 − 1)) = d, so every s below is a whole number.
TARGETS = [0.0, 50.0, 100.0]
#           P=0  P=50 P=100
UP = [
    [1.0, 8.0, -1.0],
    [2.0, 10.0, -1.0],
    [3.0, 9.0, -1.0],
]
DOWN = [
    [2.0, 4.0, -4.0],
    [4.0, 6.0, -2.0],
    [3.0, 8.0, 0.0],
]


@pytest.fixture
def hand() -> Evaluation:
    return evaluate(TARGETS, UP, DOWN)


def test_per_target_values_by_hand(hand):
    # x̄_i↑: (1+2+3)/3 = 2, (8+10+9)/3 = 9, −1;   s_i↑: d = 1, 1, 0
    assert hand.mean_up.tolist() == [2.0, 9.0, -1.0]
    assert hand.s_up.tolist() == pytest.approx([1.0, 1.0, 0.0])
    # x̄_i↓: (2+4+3)/3 = 3, (4+6+8)/3 = 6, (−4−2+0)/3 = −2;   s_i↓: 1, 2, 2
    assert hand.mean_down.tolist() == [3.0, 6.0, -2.0]
    assert hand.s_down.tolist() == pytest.approx([1.0, 2.0, 2.0])
    # B_i = x̄_i↑ − x̄_i↓ = 2−3, 9−6, −1−(−2)
    assert hand.reversal_i.tolist() == [-1.0, 3.0, 1.0]
    # x̄_i = (x̄_i↑ + x̄_i↓)/2 = 2.5, 7.5, −1.5
    assert hand.mean.tolist() == [2.5, 7.5, -1.5]
    # R_i↑ = 4 s_i↑, R_i↓ = 4 s_i↓
    assert hand.repeatability_up_i.tolist() == pytest.approx([4.0, 4.0, 0.0])
    assert hand.repeatability_down_i.tolist() == pytest.approx([4.0, 8.0, 8.0])
    # R_i = max(2s↑ + 2s↓ + |B_i|, R_i↑, R_i↓):
    #   P=0:   max(2+2+1 = 5, 4, 4) = 5     (the combined term)
    #   P=50:  max(2+4+3 = 9, 4, 8) = 9     (the combined term)
    #   P=100: max(0+4+1 = 5, 0, 8) = 8     (R_i↓ wins)
    assert hand.repeatability_i.tolist() == pytest.approx([5.0, 9.0, 8.0])
    assert (hand.n, hand.m) == (3, 3)


def test_axis_figures_by_hand(hand):
    f = hand.figures()
    expected = {
        # B = max |B_i| = max(1, 3, 1); B̄ = (−1 + 3 + 1)/3 — signed
        "reversal": 3.0,
        "mean_reversal": 1.0,
        # R↑ = max(4, 4, 0), R↓ = max(4, 8, 8), R = max(5, 9, 8)
        "repeatability_up": 4.0,
        "repeatability_down": 8.0,
        "repeatability": 9.0,
        # E↑ = 9 − (−1), E↓ = 6 − (−2), E = max(2,9,−1,3,6,−2) − min(…) = 9 − (−2)
        "systematic_up": 10.0,
        "systematic_down": 8.0,
        "systematic": 11.0,
        # M = max x̄_i − min x̄_i = 7.5 − (−1.5)
        "mean_error": 9.0,
        # x̄↑ ± 2s↑: upper 4, 11, −1; lower 0, 7, −1 → A↑ = 11 − (−1)
        "accuracy_up": 12.0,
        # x̄↓ ± 2s↓: upper 5, 10, 2; lower 1, 2, −6 → A↓ = 10 − (−6)
        "accuracy_down": 16.0,
        # A = max(11, 10) − min(−1, −6): the top from ↑, the bottom from ↓
        "accuracy": 17.0,
    }
    assert set(f) == set(expected)
    assert f == pytest.approx(expected)


def test_reference_rows_by_hand(hand):
    # what the compensation must add: −x̄_i
    assert reference_rows(2, 25.0, hand) == [
        (2, 25.0, 0.0, -2.5),
        (2, 25.0, 50.0, -7.5),
        (2, 25.0, 100.0, 1.5),
    ]


def test_as_dict_is_json_and_complete(hand):
    d = json.loads(json.dumps(hand.as_dict()))
    assert d["standard"] == "ISO 230-2:2014"
    assert (d["n"], d["m"]) == (3, 3)
    assert d["targets"] == TARGETS
    assert d["figures"]["accuracy"] == pytest.approx(17.0)
    assert d["symbols"]["accuracy"] == "A" and d["symbols"]["mean_reversal"] == "B̄"
    assert d["per_target"]["reversal_i"] == [-1.0, 3.0, 1.0]
    assert d["per_target"]["repeatability_i"] == pytest.approx([5.0, 9.0, 8.0])
    assert d["deviations"] == {"up": UP, "down": DOWN}


def test_table_markdown(hand):
    text = hand.table_markdown()
    lines = text.strip().splitlines()
    assert lines[0].startswith("| parameter (µm)") and "ISO 230-2:2014" in lines[0]
    assert set(lines[1]) <= set("|-:")
    body = {ln.split("|")[2].strip(): [c.strip() for c in ln.split("|")[4:7]] for ln in lines[2:]}
    assert body["A"] == ["12.0", "16.0", "17.0"]
    assert body["R"] == ["4.0", "8.0", "9.0"]
    assert body["E"] == ["10.0", "8.0", "11.0"]
    assert body["M"] == ["", "", "9.0"]
    assert body["B"] == ["", "", "3.0"]
    assert body["B̄"] == ["", "", "1.0"]
    assert "(0.001°)" in hand.table_markdown(unit="0.001°")


def test_arrays_are_read_only(hand):
    with pytest.raises(ValueError):
        hand.mean[0] = 1.0
    with pytest.raises(AttributeError):
        hand.accuracy = 0.0


@pytest.mark.parametrize(
    ("targets", "up", "down", "match"),
    [
        ([0, 1], [[0, 0]], [[0, 0]], "n ≥ 2"),
        ([0, 1], [[0, 0], [0, 0]], [[0, 0], [0, 0], [0, 0]], "same number of runs"),
        ([0, 1, 2], [[0, 0], [0, 0]], [[0, 0], [0, 0]], "shape"),
        ([1, 0], [[0, 0], [0, 0]], [[0, 0], [0, 0]], "increasing"),
        ([0, 1], [[0, math.nan], [0, 0]], [[0, 0], [0, 0]], "finite"),
    ],
)
def test_bad_input(targets, up, down, match):
    with pytest.raises(ValueError, match=match):
        evaluate(targets, up, down)


# ============================================================================ pure cases


def test_pure_reversal():
    # no scatter; the axis lags by 6 µm on every approach: x↑ = e(P) − 3, x↓ = e(P) + 3
    p = np.linspace(0, 400, 5)
    e = np.array([0.0, 2.0, -1.0, 4.0, 1.0])  # systematic error curve, range 5
    up = np.tile(e - 3.0, (5, 1))
    down = np.tile(e + 3.0, (5, 1))
    ev = evaluate(p, up, down)
    assert ev.reversal_i.tolist() == [-6.0] * 5
    assert ev.reversal == 6.0 and ev.mean_reversal == -6.0
    # no scatter: s = 0, so R↑ = R↓ = 0 and R = |B| = 6 (the reversal alone)
    assert ev.repeatability_up == 0.0 and ev.repeatability_down == 0.0 and ev.repeatability == 6.0
    # x̄_i = e: M = range(e) = 5; E = max(e) + 3 − (min(e) − 3) = 5 + 6; A = E (no s)
    assert ev.mean.tolist() == e.tolist()
    assert ev.mean_error == 5.0 and ev.systematic_up == 5.0 and ev.systematic_down == 5.0
    assert ev.systematic == 11.0 and ev.accuracy == 11.0 and ev.accuracy_up == 5.0


def test_pure_noise_same_scatter_everywhere():
    # every target and direction sees the values −2, 0, 0, +2 in some order: mean 0,
    # s = √(8/3); no systematic error and no reversal
    pattern = np.array([-2.0, 0.0, 0.0, 2.0])
    up = np.stack([np.roll(pattern, k) for k in range(6)], axis=1)
    down = np.stack([np.roll(pattern[::-1], k) for k in range(6)], axis=1)
    ev = evaluate(np.arange(6) * 100.0, up, down)
    s = math.sqrt(8 / 3)
    assert ev.s_up == pytest.approx([s] * 6) and ev.s_down == pytest.approx([s] * 6)
    assert (
        ev.reversal == 0.0
        and ev.mean_reversal == 0.0
        and ev.systematic == 0.0
        and ev.mean_error == 0.0
    )
    # R_i = max(2s + 2s + 0, 4s, 4s) = 4s; with all means 0, A = (0 + 2s) − (0 − 2s) = 4s
    assert ev.repeatability == pytest.approx(4 * s) and ev.repeatability_up == pytest.approx(4 * s)
    assert ev.accuracy == pytest.approx(4 * s) and ev.accuracy_up == pytest.approx(4 * s)
    assert ev.accuracy == pytest.approx(ev.repeatability)


def test_pure_noise_random_relations():
    # relations that hold for any data, checked on seeded random scatter
    rng = np.random.default_rng(7)
    for _ in range(20):
        ev = evaluate(np.arange(8.0), rng.normal(0, 1.5, (5, 8)), rng.normal(0, 1.5, (5, 8)))
        tol = 1e-12
        # each ±2s band is inside the accuracy span: A↑ ≥ 4 s_i↑ for every i
        assert (
            ev.accuracy_up >= ev.repeatability_up - tol
            and ev.accuracy_down >= ev.repeatability_down - tol
        )
        assert ev.accuracy >= max(ev.accuracy_up, ev.accuracy_down) - tol
        assert ev.accuracy >= ev.systematic - tol and ev.systematic >= ev.mean_error - tol
        assert ev.systematic >= max(ev.systematic_up, ev.systematic_down) - tol
        assert (
            ev.repeatability >= max(ev.repeatability_up, ev.repeatability_down) - tol
            and ev.repeatability >= ev.reversal - tol
        )
        assert ev.reversal >= abs(ev.mean_reversal) - tol
        # pure noise: no systematic part, so the mean errors stay well inside A
        assert ev.mean_error < ev.accuracy / 2


# ============================================================================ targets


def test_targets_irregular_properties():
    t = targets_iso(0.0, 500.0, 11, seed=3)
    assert t.shape == (11,)
    assert t[0] == 0.0 and t[-1] == 500.0  # the measurement travel
    steps = np.diff(t)
    p = 50.0
    assert (steps > 0).all()  # in order
    # P_i = (i − 1)·p + r with |r| ≤ p/4: each target within p/4 of its grid point
    grid = np.arange(11) * p
    assert np.abs(t - grid).max() <= p / 4 + 1e-3
    assert len(set(np.round(steps, 3))) > 5  # irregular: the steps differ
    # the residues modulo a 5 mm screw pitch are spread, not all at one phase
    assert np.ptp(np.mod(t[1:-1], 5.0)) > 2.5
    assert (t == np.round(t, 3)).all()  # rounded to 0.001 mm


def test_targets_deterministic_with_seed():
    a = targets_iso(-200.0, 200.0, 9, seed=11)
    b = targets_iso(-200.0, 200.0, 9, seed=11)
    c = targets_iso(-200.0, 200.0, 9, seed=12)
    assert a.tolist() == b.tolist()
    assert a.tolist() != c.tolist()
    assert not a.flags.writeable


def test_targets_equidistant_and_options():
    assert targets_iso(0.0, 100.0, 5, equidistant=True).tolist() == [0, 25, 50, 75, 100]
    # r_max = 0 is the same grid; a larger r_max reaches farther (up to < p/2)
    assert targets_iso(0.0, 100.0, 5, seed=1, r_max=0.0).tolist() == [0, 25, 50, 75, 100]
    wide = targets_iso(0.0, 1000.0, 101, seed=1, r_max=4.9, decimals=None)
    assert np.abs(wide - np.linspace(0, 1000, 101)).max() > 4.0
    with pytest.raises(ValueError, match="r_max"):
        targets_iso(0.0, 100.0, 5, r_max=12.5)
    with pytest.raises(ValueError):
        targets_iso(0.0, 100.0, 1)
    with pytest.raises(ValueError):
        targets_iso(100.0, 0.0, 5)


# ============================================================================ writers


def test_deviations_csv(hand):
    rows = list(csv.reader(io.StringIO(deviations_csv(hand))))
    assert tuple(rows[0]) == DEVIATIONS_HEADER
    assert len(rows) == 1 + 3 * 2 * 3  # n runs · 2 directions · m targets
    # run 1: up at targets 1, 2, 3, then down at 3, 2, 1 (the standard test cycle)
    assert rows[1:7] == [
        ["1", "+", "1", "0", "1"],
        ["1", "+", "2", "50", "8"],
        ["1", "+", "3", "100", "-1"],
        ["1", "-", "3", "100", "-4"],
        ["1", "-", "2", "50", "4"],
        ["1", "-", "1", "0", "2"],
    ]
    assert rows[-1] == ["3", "-", "1", "0", "3"]


def test_reference_rows_load_in_the_plc_client(tmp_path):
    # a straight error that grows with temperature: x̄(P) = a(T) + b(T)·P (µm, mm).
    # The client reads "deviation" as what to add, −x̄, fitted per temperature:
    #   intercept −a µm = −10·a increments, slope −b µm/mm = −b·1e-3 → −b·1e3 µm/m
    p = targets_iso(0.0, 400.0, 9, seed=5)
    rows = []
    for temp, a, b in ((20.0, 4.0, 0.02), (30.0, 5.0, 0.05)):
        xbar = a + b * p
        rng = np.random.default_rng(int(temp))
        noise = rng.normal(0, 0.3, (5, p.size))
        noise -= noise.mean(axis=0)  # keeps the means on the line
        ev = evaluate(p, xbar + 1.0 + noise, xbar - 1.0 + noise)  # ±1 µm reversal
        assert ev.mean == pytest.approx(xbar)
        rows += reference_rows(1, temp, ev)
    path = tmp_path / "reference.csv"
    path.write_text(reference_csv(rows, ["ISO 230-2 test on the twin"]), encoding="utf-8")
    text = path.read_text(encoding="utf-8")
    assert text.splitlines()[1] == ",".join(REFERENCE_HEADER)
    table = load_reference(path)
    assert table.form == "points"
    lines = table.lines(1)
    assert [ln.temperature for ln in lines] == [20.0, 30.0]
    assert lines[0].intercept == pytest.approx(-40.0, abs=1e-3)
    assert lines[0].coefficient == pytest.approx(-20.0, abs=1e-3)
    assert lines[1].intercept == pytest.approx(-50.0, abs=1e-3)
    assert lines[1].coefficient == pytest.approx(-50.0, abs=1e-3)
    assert sorted(set(table.axes[1].positions)) == pytest.approx(sorted(p * 10_000))
