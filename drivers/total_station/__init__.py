"""Leica total station (GeoCOM) as a :class:`~drivers.contracts.PositionFeed`.

* :mod:`.codec` - sans-IO GeoCOM ASCII frames, CRC-16/ARC, return-code table and classification.
* :mod:`.driver` - :class:`TotalStationFeed` over geocompy's ``GeoCom`` and the :func:`open_total_station`
  factory (any pyserial URL: a serial device, a pty, ``socket://host:port``).

Wire format, RPCs used and the rig-frame convention are in ``docs/protocols/geocom.md``.
"""
from __future__ import annotations

from .driver import TotalStationFeed, instrument_to_rig, open_total_station, rig_to_instrument

__all__ = ["TotalStationFeed", "open_total_station", "rig_to_instrument", "instrument_to_rig"]
