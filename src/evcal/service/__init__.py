"""The live calibration service (``evcal serve``), installed as ``evcal.service``.

Modules: :mod:`.keys` (key expressions, encodings), :mod:`.core` (cameras, queues, OnEI states,
errors; no network), :mod:`.state` (atomic snapshots), :mod:`.transport` (the only zenoh
import), :mod:`.recording` (the only rerun import), :mod:`.server` (the wiring), :mod:`.cli`.
See docs/SERVICE.md and docs/WIRE.md.
"""
