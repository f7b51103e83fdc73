"""The benchmark regression record (``benchmarks/regression.py``): tables parsed from the
benchmarks' Markdown output, durations in seconds, and the comparison of two records."""

import importlib.util
import pathlib
import sys

import pytest

BENCHMARKS = pathlib.Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))  # regression.py's neighbour machine.py
spec = importlib.util.spec_from_file_location("regression", BENCHMARKS / "regression.py")
regression = importlib.util.module_from_spec(spec)
spec.loader.exec_module(regression)
from machine import format_time, render  # noqa: E402


@pytest.mark.parametrize("cell, value", [("12.3 ms", 12.3e-3), ("4.1 s", 4.1), ("≈ 250 µs", 250e-6), ("3.2×", None),
                                         ("converged ×3", None), ("–", None)])
def test_durations_are_read_back_in_seconds(cell, value):
    assert regression.seconds(cell) == (pytest.approx(value) if value is not None else None)


def test_tables_round_trip_through_the_benchmarks_markdown():
    text = "header line\n\n" + render(("B", "batch solve", "statuses"), [(1, format_time(40.5), "converged ×1"),
                                                                         (8, format_time(0.0123), "nan ×8")])
    text += "\n\nnotes\n" + render(("what", "time"), [("compile", format_time(61.2))]) + "\n"
    tables = regression.parse_tables(text)
    assert len(tables) == 2
    assert tables[0][0] == {"B": "1", "batch solve": "40.5 s", "statuses": "converged ×1", "batch solve [s]": 40.5}
    assert tables[0][1]["batch solve [s]"] == pytest.approx(0.0123)
    assert tables[1] == [{"what": "compile", "time": "61.2 s", "time [s]": 61.2}]


def test_two_records_compare_duration_by_duration():
    def record(seconds):
        text = render(("B", "solve"), [(1, format_time(seconds))])
        return {"benchmarks": {"batched": {"tables": regression.parse_tables(text)}}}

    lines = regression.compare(record(30.0), record(10.0))
    assert lines == ["batched table 0 [1] solve [s]: 10 → 30 s (3.00×)  <-- slower"]
