"""Query-string rules every route shares."""

from __future__ import annotations

from fastapi import Request

from .errors import RequestError


def single_valued_query(request: Request) -> None:
    """422 naming every query parameter given more than once with different values
    (``method=tfp&method=tfi`` would otherwise silently take the last)."""
    values: dict[str, set[str]] = {}
    for name, value in request.query_params.multi_items():
        values.setdefault(name, set()).add(value)
    repeated = sorted(name for name, seen in values.items() if len(seen) > 1)
    if repeated:
        raise RequestError(
            422,
            "query parameters given more than once with different values: "
            + ", ".join(f"{name} ({', '.join(sorted(values[name]))})" for name in repeated),
        )
