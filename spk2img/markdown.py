"""Markdown tables for the generated documents (benchmarks, the training campaign)."""

from __future__ import annotations


def table_head(columns: list[str]) -> list[str]:
    """A markdown table's header and separator lines."""
    return [table_row(columns), table_row(["---"] * len(columns))]


def table_row(cells: list) -> str:
    """One markdown table line."""
    return "| " + " | ".join(str(c) for c in cells) + " |"
