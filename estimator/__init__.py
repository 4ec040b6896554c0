"""Slipfleet's estimators: a pure library (numpy, scipy, filterpy; no I/O, no clock).

See ``docs/method.md`` for the equations each module implements.
"""
