"""Capture plans as data: an inspectable list of steps, each with the reason it is there.

A plan is built from a :class:`CaptureRequest` (what the user asks to estimate, which colour channels) and
what the config declares (the object's geometry, the sphere, the camera). Steps a request does not need are
left out, and :func:`omissions` says why:

- ``gradients`` (diffusion maps): ambient + full + x, y, z cross-polarized (x, y, z + complements when
  ``complements``);
- ``specular`` (specular normals, Ma et al. 2007): the same gradients parallel-polarized as well (specular =
  parallel - cross, so the cross-polarized gradients are captured too);
- ``single-image`` (Mukaigawa et al.): one key-light frame plus surveys of the key light and the object;
- an object given as a mesh in rig coordinates is not surveyed;
- a colour channel not requested stays dark in every pattern (not captured, not processed).

Step kinds: ``upload`` (a pattern into a slot), ``survey`` (a target's position), ``polarization``, then per
frame ``select`` (a slot, or dark for the ambient frame), ``settle``, ``trigger`` (arm the camera, fire),
``fetch`` (the frame into the session), ``checkpoint`` (a safe point to pause), and a final ``all_off``.
Every step carries the steps it ``serves`` (the ``fetch`` and ``survey`` steps whose journal entries make it
unnecessary on resume), a nominal duration and a timeout. ``rig plan --dry-run`` prints the table, the devices
used, the estimated duration, LED energy and thermal budget (:func:`budget`).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Sequence

import numpy as np

from drivers.errors import LimitError, RigError

from rig.config import RigConfig
from rig.acquire.patterns import FULL_SCALE, nearest_led, pattern_rgb16

ESTIMATORS = ("gradients", "single-image", "specular")
DEFAULT_ESTIMATE = ("gradients", "single-image")
CHANNELS = ("R", "G", "B")
STEP_KINDS = ("upload", "survey", "polarization", "select", "settle", "trigger", "fetch", "checkpoint",
              "all_off")
IDEMPOTENT = frozenset({"upload", "survey", "polarization", "select", "settle", "checkpoint", "all_off"})
"""Kinds that may be repeated as they are. ``trigger`` and ``fetch`` are retried only as a whole frame
(select -> settle -> trigger -> fetch), since nothing of a frame is journalled before its fetch commits."""

# Nominal device timings for the duration estimate (real rig; the simulated rig is faster).
NOMINAL_S = {"survey": 4.0,          # turn, ATR fine-pointing and an EDM distance
             "polarization": 0.2,    # polarizer banks switch
             "select": 0.01, "all_off": 0.01, "checkpoint": 0.0,
             "trigger_overhead": 0.05,
             "fetch": 1.0}           # RAW transfer from a tethered camera
SERIAL_BYTES_PER_S = 11520.0         # 115200 baud, 8N1
UPLOAD_OVERHEAD_S = 0.01             # per UPLOAD_PATTERN frame round trip


class RequestError(RigError, ValueError):
    """A capture request that cannot be planned (unknown estimator or channel, a region off the frame)."""


@dataclass(frozen=True)
class CaptureRequest:
    """What the user asks for. ``complements=None`` takes ``[estimation] complements`` from the config.

    ``roi_px``: the region of the image to process, ``(x0, y0, x1, y1)`` in pixels of the delivered frame
    (half-open, column 0 / row 0 at the top left); None = the whole frame. Pixels outside it are not
    processed (gradient maps are "unknown" there, the single-image method observes only patches whose
    centres project inside it; they still act as light sources). The camera still records whole frames:
    a RAW frame is read out whole, and keeping it whole keeps the session a faithful record."""

    estimate: tuple[str, ...] = DEFAULT_ESTIMATE
    channels: tuple[str, ...] = CHANNELS
    complements: bool | None = None
    roi_px: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        est = tuple(dict.fromkeys(self.estimate))
        if not est:
            raise RequestError("request: nothing to estimate; expected one or more of " + ", ".join(ESTIMATORS))
        for e in est:
            if e not in ESTIMATORS:
                raise RequestError(f"unknown estimator {e!r}: expected one of {', '.join(ESTIMATORS)}")
        ch = tuple(c.upper() for c in self.channels)
        if not ch or any(c not in CHANNELS for c in ch) or len(set(ch)) != len(ch):
            raise RequestError(f"channels {''.join(self.channels)!r}: expected a non-empty subset of R, G, B")
        object.__setattr__(self, "estimate", est)
        object.__setattr__(self, "channels", tuple(c for c in CHANNELS if c in ch))
        if self.roi_px is not None:
            roi = tuple(self.roi_px)
            if (len(roi) != 4 or not all(isinstance(v, int) and not isinstance(v, bool) for v in roi)
                    or min(roi) < 0 or roi[2] <= roi[0] or roi[3] <= roi[1]):
                raise RequestError(f"roi_px {self.roi_px!r}: expected four integers x0 y0 x1 y1 with "
                                 "0 <= x0 < x1 and 0 <= y0 < y1 (pixels, half-open)")
            object.__setattr__(self, "roi_px", roi)

    def check_frame(self, width_px: int, height_px: int, file: str = "request") -> None:
        """Raise ValueError if the region reaches outside a ``width_px`` x ``height_px`` frame."""
        if self.roi_px is not None and (self.roi_px[2] > width_px or self.roi_px[3] > height_px):
            raise RequestError(f"{file}: roi_px {list(self.roi_px)} reaches outside the {width_px}x{height_px} "
                             "frame; expected x1 <= width and y1 <= height")

    def resolved(self, config: RigConfig) -> "CaptureRequest":
        if self.complements is not None:
            return self
        return replace(self, complements=bool(config.estimation.complements))

    def to_dict(self) -> dict[str, Any]:
        return {"estimate": list(self.estimate), "channels": "".join(self.channels),
                "complements": self.complements,
                "roi_px": None if self.roi_px is None else list(self.roi_px)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "CaptureRequest":
        roi = d.get("roi_px")
        return cls(tuple(d["estimate"]), tuple(d["channels"]), d.get("complements"),
                   None if roi is None else tuple(int(v) for v in roi))


@dataclass(frozen=True)
class Step:
    index: int
    kind: str
    params: dict[str, Any] = field(default_factory=dict)
    reason: str = ""
    serves: tuple[int, ...] = ()    # fetch/survey steps this step is needed for; () = always run
    frame: str | None = None        # "pattern/polarization" for the select/settle/trigger/fetch of a frame
    nominal_s: float = 0.0          # estimated duration on a real rig
    timeout_s: float = 0.0          # the runner gives up on the step after this long (0: no step timeout)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["serves"] = list(self.serves)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Step":
        if d.get("kind") not in STEP_KINDS:
            raise ValueError(f"plan step {d.get('index')}: unknown kind {d.get('kind')!r}; expected one of "
                             + ", ".join(STEP_KINDS))
        return cls(int(d["index"]), d["kind"], dict(d.get("params", {})), d.get("reason", ""),
                   tuple(int(i) for i in d.get("serves", ())), d.get("frame"), float(d.get("nominal_s", 0.0)),
                   float(d.get("timeout_s", 0.0)))


def steps_from_dicts(items: Sequence[dict[str, Any]]) -> list[Step]:
    steps = [Step.from_dict(d) for d in items]
    if [s.index for s in steps] != list(range(len(steps))):
        raise ValueError("plan: step indices must be 0, 1, 2, ... in order")
    return steps


def _channel_mask(channels: Sequence[str]) -> np.ndarray:
    return np.array([c in channels for c in CHANNELS])


def pattern_for(name: str, led_directions: np.ndarray, *, peak: float, key_led: int | None,
                channels: Sequence[str]) -> np.ndarray:
    """The (N, 3) uint16 pattern the sphere displays: unrequested channels are dark."""
    q = pattern_rgb16(name, led_directions, peak=peak, key_led=key_led)
    q[:, ~_channel_mask(channels)] = 0
    return q


def pattern_current_a(rgb16: np.ndarray, led_current_a_per_channel: float) -> float:
    return float(np.asarray(rgb16, np.float64).sum() / FULL_SCALE * led_current_a_per_channel)


def build_plan(config: RigConfig, led_directions, *, estimate: Sequence[str] | None = None,
               complements: bool | None = None, channels: Sequence[str] | None = None,
               request: CaptureRequest | None = None) -> list[Step]:
    """Steps for ``request`` (or ``estimate``/``complements``/``channels``) on the configured rig.

    Raises ``ValueError`` for an unknown estimator or channel and :class:`LimitError` if the patterns do not
    fit the sphere's slots.
    """
    if request is None:
        request = CaptureRequest(tuple(estimate) if estimate is not None else DEFAULT_ESTIMATE,
                                 tuple(channels) if channels is not None else CHANNELS, complements)
    req = request.resolved(config)
    req.check_frame(config.camera.width_px, config.camera.height_px, "request")
    dirs = np.asarray(led_directions, float)
    est = set(req.estimate)
    sph, cam = config.sphere, config.camera
    ch = "".join(req.channels)
    key = nearest_led(dirs, config.estimation.key_light_direction)

    gradients = ["x", "y", "z", "x_c", "y_c", "z_c"] if req.complements else ["full", "x", "y", "z"]
    cross = gradients[:] if est & {"gradients", "specular"} else []
    if "single-image" in est:
        cross.append("key")
    parallel = gradients[:] if "specular" in est else []
    slot_patterns = list(dict.fromkeys(cross + parallel))
    if len(slot_patterns) > sph.slots:
        raise LimitError(f"the plan needs {len(slot_patterns)} pattern slots, the sphere has sphere.slots="
                         f"{sph.slots}")
    slot_of = {name: i for i, name in enumerate(slot_patterns)}
    n_leds = len(dirs)
    from drivers.led_sphere.codec import MAX_UPLOAD_LEDS
    upload_s = n_leds * 6 / SERIAL_BYTES_PER_S + math.ceil(n_leds / MAX_UPLOAD_LEDS) * UPLOAD_OVERHEAD_S

    rows: list[dict[str, Any]] = []

    def add(kind: str, reason: str, *, frame: str | None = None, nominal_s: float = 0.0,
            timeout_s: float = 0.0, **params: Any) -> dict[str, Any]:
        row = dict(kind=kind, reason=reason, params=params, frame=frame, nominal_s=nominal_s,
                   timeout_s=timeout_s, serves=[])
        rows.append(row)
        return row

    uploads: dict[str, dict[str, Any]] = {}
    for name in slot_patterns:
        rgb = pattern_for(name, dirs, peak=sph.pattern_peak, key_led=key if name == "key" else None,
                          channels=req.channels)
        why = {"key": "one LED as a point light for the single-image method"}.get(
            name, f"{'complement ' if name.endswith('_c') else ''}gradient pattern '{name}'"
                  if name != "full" else "constant pattern: albedo and the gradients' denominator")
        uploads[name] = add("upload", f"preload {why}, so the capture loop only switches slots",
                            nominal_s=upload_s, timeout_s=10.0 + 4 * upload_s, slot=slot_of[name],
                            pattern=name, key_led=key if name == "key" else None, channels=ch,
                            current_a=round(pattern_current_a(rgb, sph.led_current_a_per_channel), 4))

    needs_object = bool(cross or parallel)
    if needs_object and config.object.shape != "mesh":
        add("survey", "the estimators need the declared object's position in the rig frame",
            nominal_s=NOMINAL_S["survey"], timeout_s=60.0, target=config.object.survey_target)
        add("checkpoint", "survey journalled: a safe point to pause")
    if "single-image" in est:
        add("survey", "the single-image method needs the key light's position (a point light)",
            nominal_s=NOMINAL_S["survey"], timeout_s=60.0, target="key_led", led=key)
        add("checkpoint", "survey journalled: a safe point to pause")

    def frames(pol: str, names: list[str], pol_reason: str) -> None:
        prow = add("polarization", pol_reason, nominal_s=NOMINAL_S["polarization"], timeout_s=10.0, state=pol)
        prow["_frames"] = []
        for name in ["ambient", *names]:
            fid = f"{name}/{pol}"
            exposure = cam.key_exposure_s if name == "key" else cam.exposure_s
            if name == "ambient":
                why = f"{pol}-polarized ambient frame (sphere dark), subtracted from every lit {pol} frame"
                sel = add("select", "sphere dark for the ambient frame", frame=fid, nominal_s=NOMINAL_S["select"],
                          timeout_s=5.0, slot=None, pattern="ambient", current_a=0.0)
            else:
                why = {"full": "constant pattern: diffuse albedo and the gradients' denominator",
                       "key": "one LED as a surveyed point light: the single-image method's input"}.get(
                    name, f"spherical-gradient pattern '{name}': "
                          + ("diffuse normals (Ma et al. 2007)" if pol == "cross"
                             else "specular normals from parallel - cross (Ma et al. 2007)"))
                sel = add("select", f"light slot {slot_of[name]} ({name})", frame=fid, nominal_s=NOMINAL_S["select"],
                          timeout_s=5.0, slot=slot_of[name], pattern=name,
                          current_a=uploads[name]["params"]["current_a"])
            group = [sel]
            if sph.settle_s > 0:
                group.append(add("settle", "LEDs and polarizers settle before the exposure", frame=fid,
                                 nominal_s=sph.settle_s, timeout_s=sph.settle_s + 5.0, seconds=sph.settle_s))
            group.append(add("trigger", f"arm the camera and expose {exposure} s", frame=fid,
                             nominal_s=exposure + NOMINAL_S["trigger_overhead"], timeout_s=exposure + 10.0,
                             exposure_s=exposure))
            fetch = add("fetch", why, frame=fid, nominal_s=NOMINAL_S["fetch"], timeout_s=cam.fetch_timeout_s,
                        pattern=name, polarization=pol, exposure_s=exposure)
            group.append(fetch)
            fetch["_group"] = group
            prow["_frames"].append(fetch)
            if name != "ambient":
                uploads[name].setdefault("_frames", []).append(fetch)
            add("checkpoint", "frame committed: a safe point to pause")

    if cross:
        frames("cross", cross, "cross-polarized frames hold only subsurface (diffuse) light")
    if parallel:
        frames("parallel", parallel, "parallel-polarized frames add the specular reflection (specular normals)")
    add("all_off", "leave the sphere dark", nominal_s=NOMINAL_S["all_off"], timeout_s=5.0)

    # indices and the 'serves' links
    for i, r in enumerate(rows):
        r["index"] = i
    for r in rows:
        if r["kind"] == "survey":
            r["serves"] = [r["index"]]
        if r["kind"] == "fetch":
            for g in r["_group"]:
                g["serves"] = [r["index"]]
        if r["kind"] in ("upload", "polarization"):
            r["serves"] = [f["index"] for f in r.get("_frames", [])]
    return [Step(r["index"], r["kind"], r["params"], r["reason"], tuple(r["serves"]), r["frame"],
                 round(float(r["nominal_s"]), 4), round(float(r["timeout_s"]), 4)) for r in rows]


def omissions(config: RigConfig, request: CaptureRequest) -> list[str]:
    """What a plan for ``request`` leaves out, and why (printed by ``rig plan``)."""
    req = request.resolved(config)
    est = set(req.estimate)
    out = []
    if "specular" not in est:
        out.append("no parallel-polarized frames: specular normals not requested (--estimate specular)")
    if not est & {"gradients", "specular"}:
        out.append("no gradient frames: neither diffusion maps nor specular normals requested")
    elif req.complements:
        out.append("no full-on frame: complement gradients configured (the full-on frame is their sum)")
    else:
        out.append("no complement frames: not configured ([estimation] complements / --complements)")
    if "single-image" not in est:
        out.append("no key-light frame and no survey of the key light: single-image estimation not requested")
    if config.object.shape == "mesh":
        out.append(f"no survey of the object: its geometry is a mesh in rig coordinates "
                   f"({config.object.mesh_path})")
    missing = [c for c in CHANNELS if c not in req.channels]
    if missing:
        out.append(f"channel(s) {', '.join(missing)} not requested: dark in every pattern, not processed")
    if req.roi_px is not None:
        x0, y0, x1, y1 = req.roi_px
        out.append(f"pixels outside the region x {x0}..{x1 - 1}, y {y0}..{y1 - 1} not processed (frames are "
                   "still recorded whole: a RAW frame is read out whole)")
    return out


def devices_used(steps: Sequence[Step], config: RigConfig) -> dict[str, dict[str, str]]:
    kinds = {s.kind for s in steps}
    out: dict[str, dict[str, str]] = {}
    if kinds & {"upload", "select", "polarization", "all_off"}:
        out["sphere"] = {"driver": config.sphere.driver, "url": config.sphere.url,
                         "why": "patterns, polarizers, all-off"}
    if "trigger" in kinds:
        out["trigger"] = {"driver": config.trigger.driver, "url": config.trigger.url, "why": "exposures"}
    if "fetch" in kinds:
        out["camera"] = {"driver": config.camera.driver, "url": config.camera.folder, "why": "RAW frames"}
    if "survey" in kinds:
        out["total_station"] = {"driver": config.total_station.driver, "url": config.total_station.url,
                                "why": "positions of " + ", ".join(s.params["target"] for s in steps
                                                                   if s.kind == "survey")}
    return out


def budget(steps: Sequence[Step], config: RigConfig) -> dict[str, Any]:
    """Duration, LED energy and thermal budget of a plan, from nominal timings and the sphere's first-order
    thermal model (``[sphere]`` ``thermal_c_per_a``, ``thermal_tau_s``, ``ambient_c``,
    ``over_temperature_c``; energy = forward voltage x current x lit time). Problems a run would hit
    (current over the limit, watchdog shorter than an exposure, predicted over-temperature) are listed."""
    s = config.sphere
    current = 0.0
    temp = peak_temp = s.ambient_c
    energy_j = charge_as = lit_s = 0.0
    max_current = 0.0
    for st in steps:
        if st.kind == "select":
            current = float(st.params.get("current_a", 0.0))
            max_current = max(max_current, current)
        elif st.kind == "all_off":
            current = 0.0
        dt = st.nominal_s
        if current > 0:
            energy_j += s.led_forward_voltage_v * current * dt
            charge_as += current * dt
            lit_s += dt
        t_eq = s.ambient_c + s.thermal_c_per_a * current
        temp = t_eq + (temp - t_eq) * math.exp(-dt / s.thermal_tau_s)
        peak_temp = max(peak_temp, temp)
    problems: list[str] = []
    fields: list[str] = []          # the config field each problem is about (``rig config --check``)
    if max_current > s.max_total_current_a:
        fields.append("sphere.max_total_current_a")
        problems.append(f"a pattern draws {max_current:.2f} A, over sphere.max_total_current_a="
                        f"{s.max_total_current_a:g} A")
    longest = max((st.nominal_s for st in steps if st.kind in ("trigger", "settle")), default=0.0)
    exposure_s = max((st.params["exposure_s"] for st in steps if st.kind == "trigger"), default=0.0)
    if s.watchdog_s and s.watchdog_s <= exposure_s + s.settle_s + 0.5:
        fields.append("sphere.watchdog_s")
        problems.append(f"sphere.watchdog_s={s.watchdog_s:g} s does not cover the longest exposure "
                        f"({exposure_s:g} s) + settle ({s.settle_s:g} s) + 0.5 s: the sphere would go dark "
                        "mid-exposure")
    if peak_temp >= s.over_temperature_c:
        fields.append("sphere.over_temperature_c")
        problems.append(f"predicted peak temperature {peak_temp:.1f} C reaches the interlock at "
                        f"{s.over_temperature_c:g} C: the run would hold until the sphere cools")
    n_frames = sum(1 for st in steps if st.kind == "fetch")
    return {"frames": n_frames, "steps": len(steps),
            "duration_s": round(sum(st.nominal_s for st in steps), 3),
            "led_lit_s": round(lit_s, 3), "led_energy_j": round(energy_j, 3), "led_charge_as": round(charge_as, 4),
            "max_current_a": round(max_current, 4), "max_total_current_a": s.max_total_current_a,
            "peak_temperature_c": round(peak_temp, 2), "over_temperature_c": s.over_temperature_c,
            "thermal_headroom_c": round(s.over_temperature_c - peak_temp, 2),
            "longest_exposure_step_s": round(longest, 3), "problems": problems,
            "problem_fields": fields}


def _detail(s: Step) -> str:
    p = s.params
    if s.kind == "upload":
        return f"slot {p['slot']} <- {p['pattern']} ({p['current_a']:.2f} A)"
    if s.kind == "survey":
        return f"target {p['target']}"
    if s.kind == "polarization":
        return p["state"]
    if s.kind == "select":
        return "dark" if p["slot"] is None else f"slot {p['slot']} ({p['pattern']})"
    if s.kind == "settle":
        return f"{p['seconds']} s"
    if s.kind == "trigger":
        return f"{p['exposure_s']} s"
    if s.kind == "fetch":
        return f"{p['pattern']} {p['polarization']}"
    return ""


def summarize(steps: Sequence[Step], config: RigConfig | None = None,
              request: CaptureRequest | None = None) -> str:
    """The dry-run text: the steps with why each is there; with ``config`` also the devices used, the
    estimated duration, LED energy and thermal budget, and what was left out."""
    lines = [f"{'#':>3}  {'step':<12} {'details':<30} {'~s':>6}  why"]
    for s in steps:
        lines.append(f"{s.index:>3}  {s.kind:<12} {_detail(s):<30} {s.nominal_s:>6.2f}  {s.reason}")
    n_frames = sum(1 for s in steps if s.kind == "fetch")
    lines.append(f"{n_frames} frames")
    if config is None:
        return "\n".join(lines)
    lines.append("")
    lines.append("frames: " + ", ".join(s.frame or "" for s in steps if s.kind == "fetch"))
    lines.append("devices used:")
    for role, d in devices_used(steps, config).items():
        lines.append(f"  {role:<14} {d['driver']:<10} {d['url']:<12} {d['why']}")
    b = budget(steps, config)
    lines.append(f"estimated duration: {b['duration_s']:.1f} s (nominal device timings)")
    lines.append(f"LED energy: {b['led_energy_j']:.1f} J over {b['led_lit_s']:.2f} s lit "
                 f"({b['led_charge_as']:.2f} A s; peak {b['max_current_a']:.2f} A of "
                 f"{b['max_total_current_a']:g} A allowed)")
    lines.append(f"thermal budget: peak {b['peak_temperature_c']:.1f} C predicted, interlock at "
                 f"{b['over_temperature_c']:g} C ({b['thermal_headroom_c']:.1f} C headroom)")
    if request is not None:
        for note in omissions(config, request):
            lines.append(f"left out: {note}")
    for p in b["problems"]:
        lines.append(f"PROBLEM: {p}")
    return "\n".join(lines)
