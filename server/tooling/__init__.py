"""Tooling around the server, never imported by it: the simulated fleet and its commands
(``demo``, ``simulate``, ``replay``, ``record``), the load generator and load test, server
shards and a standalone router process, the benchmarks, and helpers for ports, child processes
and PostgreSQL databases."""
