"""Hardware abstraction layer: device contracts, transports and one package per device.

Each device package holds a sans-IO ``codec`` (bytes in, messages out, never touches a port)
and a ``driver`` that owns an injected transport. ``drivers`` imports nothing else of sssrig.
"""
