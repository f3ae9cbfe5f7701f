"""m3t.reporting: cells, Markdown tables and CSV text, each checked against text written out by hand."""
from __future__ import annotations

import math

import pytest

from m3t.reporting import csv_text, fixed, frame_csv, markdown_table, significant


@pytest.mark.parametrize(("value", "digits", "expected"), [
    (1.23456, 2, "1.23"), (0.0, 3, "0.000"), (-2.5, 0, "-2"), (7, 1, "7.0"),
    (None, 2, "-"), (math.nan, 2, "-"), (math.inf, 1, "inf"),
])
def test_fixed(value, digits, expected):
    assert fixed(value, digits) == expected


def test_fixed_with_another_placeholder():
    assert fixed(None, 4, "") == "" and fixed(math.nan, 4, "") == "" and fixed(0.5, 4, "") == "0.5000"


@pytest.mark.parametrize(("value", "digits", "whole_from", "expected"), [
    (1.23456, 3, None, "1.23"), (-0.00012345, 3, None, "-0.000123"), (999.6, 3, None, "1e+03"),
    (1000.0, 3, None, "1000"), (12345.678, 3, None, "12346"), (99.95, 2, None, "1e+02"), (150, 2, None, "150"),
    (99.96, 3, 100, "100"), (100.0, 3, 100, "100"), (999.6, 3, 100, "1000"), (-123456.7, 3, 100, "-123457"),
    (None, 3, None, "-"), ("text", 3, None, "-"), (math.nan, 3, None, "-"), (-math.inf, 3, 100, "-"),
])
def test_significant(value, digits, whole_from, expected):
    assert significant(value, digits, whole_from) == expected


def test_markdown_table():
    assert markdown_table(["a", "b c"], [[1, None], ["x", 2.5]]) == (
        "| a | b c |\n"
        "|---|---|\n"
        "| 1 | None |\n"
        "| x | 2.5 |")


def test_markdown_table_without_rows_is_header_and_separator():
    assert markdown_table(["only"], []) == "| only |\n|---|"


def test_markdown_table_escapes_only_when_asked():
    header, rows = ["a|b"], [["x\ny"]]
    assert markdown_table(header, rows) == "| a|b |\n|---|\n| x\ny |"
    assert markdown_table(header, rows, escape=True) == "| a\\|b |\n|---|\n| x y |"


def test_csv_text():
    rows = [{"id": 1, "text": 'a,"b"\nc', "score": 0.1 + 0.2}, {"id": 2, "score": math.nan}, {"id": 3, "text": None}]
    assert csv_text(rows, ["id", "text", "score"]) == (
        "id,text,score\n"
        '1,"a,""b""\nc",0.30000000000000004\n'
        "2,,nan\n"
        "3,,\n")


def test_csv_text_without_rows_is_the_header():
    assert csv_text([], ("a", "b")) == "a,b\n"


def test_csv_text_refuses_a_column_outside_the_header():
    with pytest.raises(ValueError, match="extra"):
        csv_text([{"a": 1, "extra": 2}], ["a"])


def test_frame_csv_writes_as_pandas_does():
    rows = [{"a": 1, "b": 0.5, "c": "x"}, {"a": 2.5, "c": None, "d": math.nan}, {"a": 3, "b": True}]
    assert frame_csv(rows) == (
        "a,b,c,d\n"
        "1.0,0.5,x,\n"
        "2.5,,,\n"
        "3.0,True,,\n")
