"""One table, three renderings: Markdown, LaTeX (booktabs) and HTML; CSV is written from numbers."""

from __future__ import annotations

import csv
import html
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Cell:
    """One table cell: its text and whether it is bold (the best value of a row or column)."""

    text: str
    bold: bool = False


@dataclass
class Table:
    """A titled grid of cells; ``notes`` are printed under it (sources, daggers, what n means)."""

    key: str  # file stem: main_results, bounded_history, ...
    title: str
    header: list[str]
    rows: list[list[Cell]]
    notes: list[str] = field(default_factory=list)

    def markdown(self) -> str:
        """The table as GitHub Markdown (title, grid, notes)."""
        def cell(c: Cell) -> str:
            t = c.text.replace("|", "\\|")
            return f"**{t}**" if c.bold and t else t

        lines = [f"### {self.title}", "", "| " + " | ".join(self.header) + " |", "|" + "---|" * len(self.header)]
        lines += ["| " + " | ".join(cell(c) for c in row) + " |" for row in self.rows]
        if self.notes:
            lines += [""] + [f"{n}  " for n in self.notes]
        return "\n".join(lines) + "\n"

    def latex(self) -> str:
        """The table as a LaTeX ``table*`` (booktabs), special characters escaped."""
        def esc(text: str) -> str:
            out = text
            for a, b in (("\\", r"\textbackslash{}"), ("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"),
                         ("$", r"\$"), ("†", r"$^\dagger$"), ("∞", r"$\infty$")):  # fmt: skip
                out = out.replace(a, b)
            return out

        def cell(c: Cell) -> str:
            return rf"\textbf{{{esc(c.text)}}}" if c.bold and c.text else esc(c.text)

        cols = "l" + "c" * (len(self.header) - 1)
        lines = [r"\begin{table*}[t]", r"\centering", rf"\caption{{{esc(self.title)}}}", rf"\label{{tab:ppprops_{self.key}}}",
                 rf"\begin{{tabular}}{{{cols}}}", r"\toprule", " & ".join(esc(h) for h in self.header) + r" \\", r"\midrule"]  # fmt: skip
        lines += [" & ".join(cell(c) for c in row) + r" \\" for row in self.rows]
        lines += [r"\bottomrule"]
        for n in self.notes:
            lines.append(rf"\multicolumn{{{len(self.header)}}}{{l}}{{\footnotesize {esc(n)}}} \\")
        lines += [r"\end{tabular}", r"\end{table*}"]
        return "\n".join(lines) + "\n"

    def html(self) -> str:
        """The table as an HTML fragment for ``index.html`` (text escaped)."""
        def cell(c: Cell) -> str:
            t = html.escape(c.text)
            return f"<td><b>{t}</b></td>" if c.bold and t else f"<td>{t}</td>"

        head = "".join(f"<th>{html.escape(h)}</th>" for h in self.header)
        body = "\n".join("<tr>" + "".join(cell(c) for c in row) + "</tr>" for row in self.rows)
        notes = "".join(f"<p class='note'>{html.escape(n)}</p>" for n in self.notes)
        return (f"<h3 id='{self.key}'>{html.escape(self.title)}</h3>\n<table class='results' data-table='{self.key}'>"
                f"<thead><tr>{head}</tr></thead>\n<tbody>\n{body}\n</tbody></table>\n{notes}")  # fmt: skip


def write_csv(path: Path, rows: Sequence[dict[str, Any]], columns: Sequence[str]) -> None:
    """Numbers as numbers (empty where missing), one row per record."""
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=list(columns), extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if r.get(k) is None else r.get(k)) for k in columns})


def write_table(out: Path, table: Table, csv_rows: Sequence[dict[str, Any]], csv_columns: Sequence[str]) -> list[Path]:
    """``<key>.md``, ``<key>.tex`` and ``<key>.csv`` in ``out``."""
    paths = [out / f"{table.key}.md", out / f"{table.key}.tex", out / f"{table.key}.csv"]
    paths[0].write_text(table.markdown(), encoding="utf-8")
    paths[1].write_text(table.latex(), encoding="utf-8")
    write_csv(paths[2], csv_rows, csv_columns)
    return paths
