"""Benchmarks: simulated sequences with truth, and real frames with independent references (``real``),
measured in one process.

Each suite is a module with ``run(...) -> dict`` (JSON-serialisable figures)
and ``format_table(result) -> str``; ``python -m app bench`` runs them.
"""
