"""Clients of the calibration service (``evcal replay|query|record|demo``), installed as
``evcal.clients``. They reach zenoh only through :mod:`evcal.service.transport`."""
