"""``rig sim --fault DEVICE:FAULT[=VALUE]``: faults injected into the running simulators, so operators can
rehearse failures (the fault hooks of the simulator models and of ``simulators.serve.Faults``).

Examples: ``sphere:led_fault``, ``sphere:over_temperature``, ``sphere:busy=3``, ``trigger:busy=2``,
``total_station:busy=2``, ``total_station:corrupt=0.003``, ``any:latency=0.2``, ``sphere:mute``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from drivers.errors import ConfigError

__all__ = ["FAULTS", "FaultSpec", "parse_faults", "apply_faults", "describe"]

DEVICES = ("sphere", "trigger", "total_station")

# fault -> (devices it applies to, value kind, what it does)
FAULTS: dict[str, tuple[tuple[str, ...], str, str]] = {
    "led_fault": (("sphere",), "", "the sphere reports its LED-fault status bit"),
    "over_temperature": (("sphere",), "", "the sphere's over-temperature interlock trips (dark, refuses to light)"),
    "busy": (DEVICES, "count", "the next N commands are answered BUSY (default 3)"),
    "latency": (DEVICES, "seconds", "every reply is delayed this long"),
    "drop": (DEVICES, "probability", "each reply byte is lost with this probability"),
    "corrupt": (DEVICES, "probability", "each reply byte gets a flipped bit with this probability"),
    "split": (DEVICES, "count", "replies are written in chunks of N bytes"),
    "mute": (DEVICES, "", "the device stops answering"),
}


@dataclass(frozen=True)
class FaultSpec:
    device: str
    fault: str
    value: float | None

    def __str__(self) -> str:
        return f"{self.device}:{self.fault}" + ("" if self.value is None else f"={self.value:g}")


def describe() -> str:
    lines = ["DEVICE:FAULT[=VALUE], DEVICE one of " + ", ".join(DEVICES) + " or any:"]
    for name, (devs, kind, what) in FAULTS.items():
        lines.append(f"  {name + ('=' + kind.upper() if kind else ''):<26} {what} ({', '.join(devs)})")
    return "\n".join(lines)


def parse_faults(texts: list[str]) -> list[FaultSpec]:
    """Parse ``--fault`` values; a bad one is a :class:`ConfigError` naming it and the choices."""
    out: list[FaultSpec] = []
    for text in texts:
        if text == "list":
            raise SystemExit(describe())
        dev, sep, rest = text.partition(":")
        name, _, raw = rest.partition("=")
        if not sep or (dev not in DEVICES and dev != "any"):
            raise ConfigError("--fault", "device", "DEVICE:FAULT with DEVICE one of " + ", ".join(DEVICES) + ", any",
                              text)
        if name not in FAULTS:
            from rig.config.schema import did_you_mean
            raise ConfigError("--fault", "fault", "one of " + ", ".join(FAULTS) + did_you_mean(name, FAULTS), text)
        devs, kind, _ = FAULTS[name]
        value: float | None = None
        if kind:
            try:
                value = float(raw) if raw else (3.0 if kind == "count" else None)
            except ValueError:
                raise ConfigError("--fault", name, f"a number ({kind})", raw) from None
            if value is None:
                raise ConfigError("--fault", name, f"{name}=<{kind}>", text)
            if value < 0 or (kind == "probability" and value > 1):
                raise ConfigError("--fault", name, f"a {kind} " + ("in [0, 1]" if kind == "probability" else ">= 0"),
                                  value)
        elif raw:
            raise ConfigError("--fault", name, "no value", raw)
        for d in (devs if dev == "any" else (dev,)):
            if d not in devs:
                raise ConfigError("--fault", name, "a fault of " + ", ".join(devs), text)
            out.append(FaultSpec(d, name, value))
    return out


def apply_faults(sim: Any, faults: list[FaultSpec]) -> list[str]:
    """Apply ``faults`` to a running :class:`rig.acquire.factory.SimulatedRig`; returns one line per fault."""
    from drivers.total_station import codec as geocom

    applied = []
    for f in faults:
        server = sim.servers.get(f.device)
        if server is None:
            raise ConfigError("--fault", f.device, "a simulated device served on a byte stream (a serial sphere, an "
                              "ESPER trigger, the total station)", str(f))
        model, wire = server.device, server.faults
        if f.fault == "led_fault":
            model.led_fault = True
        elif f.fault == "over_temperature":
            model.force_over_temperature = True
        elif f.fault == "busy":
            n = int(f.value or 0)
            if f.device == "sphere":
                model.busy_for(n)
            elif f.device == "trigger":
                model.busy_next = n
            else:
                model.next_return_code(geocom.TMC_BUSY, count=n)
        elif f.fault == "latency":
            wire.latency_s = float(f.value or 0.0)
        elif f.fault == "drop":
            wire.drop_probability = float(f.value or 0.0)
        elif f.fault == "corrupt":
            wire.corrupt_probability = float(f.value or 0.0)
        elif f.fault == "split":
            wire.split_at = max(1, int(f.value or 1))
        elif f.fault == "mute":
            wire.mute = True
        applied.append(f"{f}: {FAULTS[f.fault][2]}")
    return applied
