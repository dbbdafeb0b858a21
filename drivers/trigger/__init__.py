"""Camera triggers: things that open the camera's shutter for an exposure (``contracts.Trigger``).

* :mod:`.esper` - ASCII trigger box of the ESPER TriggerBox kind on a serial/TCP byte transport.
* :mod:`.hid_box` - USB HID trigger box through hidapi, behind a small ``HidTransport`` seam.
* :mod:`.serial_release` - a serial port's RTS (focus) and DTR (shutter) lines driving an opto-isolator.

Wire formats are documented in ``docs/protocols/trigger-boxes.md``. Every ``fire(exposure_s)`` refuses an
out-of-range exposure with :class:`~drivers.errors.LimitError` before anything is sent, and returns only once
the exposure is over.
"""
from __future__ import annotations

from .esper import EsperTrigger, open_esper_trigger
from .hid_box import HidTrigger, open_hid_trigger
from .serial_release import SerialRelease, open_serial_release

__all__ = [
    "EsperTrigger", "open_esper_trigger",
    "HidTrigger", "open_hid_trigger",
    "SerialRelease", "open_serial_release",
]
