"""Capture plans as data: an inspectable list of steps, each with the reason it is there.

A plan is built from what the user asks to estimate; steps a request does not need are left out
(no parallel-polarized frames unless specular normals are wanted, no key-light frame or survey unless the
single-image method runs). ``rig plan`` prints a plan without touching a device.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from .config import RigConfig
from .patterns import nearest_led

ESTIMATORS = ("gradients", "single-image")


@dataclass(frozen=True)
class Step:
    index: int
    kind: str                      # upload | survey | polarization | capture | all_off
    params: dict[str, Any] = field(default_factory=dict)
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def build_plan(config: RigConfig, led_directions, *, estimate: tuple[str, ...] = ESTIMATORS,
               complements: bool = False) -> list[Step]:
    """Steps for the requested estimators on the configured rig."""
    for e in estimate:
        if e not in ESTIMATORS:
            raise ValueError(f"unknown estimator {e!r}: expected one of {', '.join(ESTIMATORS)}")
    steps: list[Step] = []

    def add(kind: str, reason: str, **params: Any) -> None:
        steps.append(Step(len(steps), kind, params, reason))

    gradients = ("x_c", "y_c", "z_c") if complements else ("full",)
    patterns: list[str] = []
    if "gradients" in estimate:
        patterns += [*gradients, "x", "y", "z"] if not complements else ["x", "y", "z", *gradients]
    if "single-image" in estimate:
        patterns.append("key")
    key = nearest_led(led_directions, config.estimation.key_light_direction)
    for slot, name in enumerate(patterns):
        add("upload", f"preload pattern '{name}' so the capture loop only switches slots",
            slot=slot, pattern=name, key_led=key if name == "key" else None)
    add("survey", "both estimators need the declared object's position in the rig frame",
        target=config.object.survey_target)
    if "single-image" in estimate:
        add("survey", "the single-image method needs the key light's position (point light)",
            target="key_led", led=key)
    add("polarization", "cross-polarized frames hold only subsurface (diffuse) light", state="cross")
    exposure = config.camera.exposure_s
    add("capture", "ambient frame, subtracted from every lit frame", pattern="ambient", slot=None,
        polarization="cross", exposure_s=exposure)
    for slot, name in enumerate(patterns):
        why = {"full": "constant pattern: diffuse albedo and the gradients' denominator",
               "key": "one LED as a surveyed point light: the single-image method's input"}.get(
            name, f"spherical-gradient pattern '{name}': diffuse normals (Ma et al. 2007)")
        add("capture", why, pattern=name, slot=slot, polarization="cross",
            exposure_s=config.camera.key_exposure_s if name == "key" else exposure)
    add("all_off", "leave the sphere dark")
    return steps


def summarize(steps: list[Step]) -> str:
    lines = [f"{'#':>3}  {'step':<13} {'details':<38} why"]
    for s in steps:
        p = s.params
        detail = {"upload": lambda: f"slot {p['slot']} <- {p['pattern']}",
                  "survey": lambda: f"target {p['target']}",
                  "polarization": lambda: f"{p['state']}",
                  "capture": lambda: f"{p['pattern']} {p['polarization']} {p['exposure_s']} s",
                  "all_off": lambda: ""}[s.kind]()
        lines.append(f"{s.index:>3}  {s.kind:<13} {detail:<38} {s.reason}")
    n_frames = sum(1 for s in steps if s.kind == "capture")
    lines.append(f"{n_frames} frames")
    return "\n".join(lines)
