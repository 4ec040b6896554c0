"""Benchmarks behind ``slipfleet bench <name> [--json PATH]``.

Each module has ``run(json_path=None) -> dict`` that prints a plain-text table and, given a path,
writes the same numbers as JSON.
"""
