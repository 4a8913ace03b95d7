"""Tables as the templates draw them: a header row and body rows of cells, each with
its alignment or verdict class, built here so that the templates stay plain loops."""

from __future__ import annotations

from dataclasses import dataclass

from fringecal.report.formatting import truthy

__all__ = ["Cell", "Span", "Table", "column_note", "pass_cell", "table"]


@dataclass(frozen=True)
class Cell:
    """One cell: its text (escaped by the template unless :class:`~markupsafe.Markup`),
    CSS class (``"l"`` left-aligned, ``"pass"``/``"fail"``/``"warn"`` a verdict) and,
    for a note standing for a whole column, the rows it spans."""

    text: object
    klass: str = ""
    rowspan: int | None = None


@dataclass(frozen=True)
class Table:
    """A table: header cells and body rows."""

    head: tuple[Cell, ...]
    rows: tuple[tuple[Cell, ...], ...]


@dataclass(frozen=True)
class Span:
    """A cell covering the same column of ``rows`` rows (the following rows leave it out)."""

    text: object
    rows: int


def _cell(column: int, value, left: int) -> Cell:
    if isinstance(value, Cell):
        return value
    if isinstance(value, Span):
        return Cell(value.text, "l", max(1, int(value.rows)))
    if isinstance(value, tuple):
        text, klass = value
        return Cell(text, klass)
    return Cell(value, "l" if column < left else "")


def table(headers, rows, left: int = 1) -> Table:
    """A table of ``rows`` (lists of values) under ``headers``; the first ``left``
    columns align left. A value ``(text, klass)`` is a coloured verdict cell, a
    :class:`Span` a note covering its column.

    >>> t = table(["Position", "Error"], [["bb01", "21.0 µm"], ["bb02", ("FAIL", "fail")]])
    >>> [c.klass for c in t.head], [[c.klass for c in r] for r in t.rows]
    (['l', ''], [['l', ''], ['l', 'fail']])
    """
    return Table(tuple(_cell(j, h, left) for j, h in enumerate(headers)),
                 tuple(tuple(_cell(j, v, left) for j, v in enumerate(r)) for r in rows))


def column_note(rows: list[list], text) -> list[list]:
    """``rows`` with one more column: ``text`` once, spanning all of them."""
    return [r + [Span(text, len(rows))] if i == 0 else list(r) for i, r in enumerate(rows)]


def pass_cell(value) -> tuple[str, str]:
    """A PASS/FAIL verdict cell of a flag as a file holds it.

    >>> pass_cell("True"), pass_cell(False)
    (('PASS', 'pass'), ('FAIL', 'fail'))
    """
    ok = truthy(value)
    return ("PASS" if ok else "FAIL", "pass" if ok else "fail")
