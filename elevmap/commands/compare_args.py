"""The arguments of ``elevmap compare``: effects, mappers, the reality and map settings, parsed and checked."""

from __future__ import annotations

import hashlib
from dataclasses import fields, replace

from noise_model.sim.effects import EFFECTS, Effect, make_effect
from noise_model.valid_margin import DEFAULT_VALID_MARGIN_PX

from ..map.fusion import FusionParams
from ..pipeline import MappingConfig

__all__ = ["effects_help", "parse_effects", "parse_mappers", "parse_reality", "parse_settings", "apply_settings",
           "camera_settings",
           "REALITIES"]

#: Simulated realities by name; a path ending in ``.json`` names a gap report (:func:`parse_reality`).
REALITIES = ("reference", "stereo")
#: The map settings ``--set`` may change besides the fields of :class:`elevmap.FusionParams`.
MAP_SETTINGS = ("visibility_cleanup",)
#: The camera settings ``--set`` may change (:class:`elevmap.Camera`).
CAMERA_SETTINGS = ("bin_at_plane", "valid_margin_px")


def _number(text: str, where: str):
    t = text.strip()
    if t.lower() in ("none", "null"):
        return None
    try:
        v = float(t)
    except ValueError:
        raise ValueError(f"{where}: {text!r} is not a number") from None
    return v


def effects_help() -> str:
    """One line per effect of :data:`noise_model.sim.effects.EFFECTS`: its name and default parameters."""
    import inspect

    lines = []
    width = max(len(n) for n in EFFECTS)
    for name, factory in EFFECTS.items():
        params = [f"{k}={v.default!r}" if v.default is not None else f"{k}=..." for k, v in
                  inspect.signature(factory).parameters.items()
                  if k not in ("model",) and v.default is not inspect.Parameter.empty]
        lines.append(f"  {name:{width}s}  {', '.join(params)}")
    return "\n".join(lines)


def parse_effects(spec) -> list[Effect]:
    """Effects from a ``--sim-effects`` string or a sequence of effects / names.

    The string is a comma-separated list of effect names (:data:`noise_model.sim.effects.EFFECTS`), each
    optionally followed by ``:key=value`` overrides of its defaults, several separated by ``:`` or by
    commas: ``correlated_noise``, ``correlated_noise:length_px=5:sigma_z_fraction=0.5,depth_bias``,
    ``correlated_noise:length_px=5,sigma_z_fraction=0.5``. ``none`` or an empty string: no effect.
    A path ending in ``.json``: the effects of a gap report (``elevmap gap --json``), with their
    fitted parameters, in the simulator's canonical order (their pixel parameters are in the pixels
    of the diagnosed stream: simulate the walk at that resolution).

    Returns
    -------
    list of Effect

    Raises
    ------
    ValueError
        Unknown effect or parameter, malformed override, bad value.
    """
    if spec is None:
        return []
    if isinstance(spec, Effect):
        return [spec]
    if not isinstance(spec, str):
        out = []
        for item in spec:
            if isinstance(item, Effect):
                out.append(item)
            elif isinstance(item, str):
                out += parse_effects(item)
            else:
                raise ValueError(f"sim effects must be names or noise_model.sim.effects.Effect objects, got {item!r}")
        return out
    text = spec.strip()
    if text.lower() in ("", "none"):
        return []
    if text.lower().endswith(".json"):          # the effects a gap diagnosis selected and fitted
        from noise_model.sim.effects import canonical_order, effects_from_report

        return canonical_order(effects_from_report(text))
    entries: list[tuple[str, dict]] = []
    for token in (t.strip() for t in text.split(",")):
        if not token:
            raise ValueError(f"--sim-effects {spec!r}: empty entry")
        parts = [p.strip() for p in token.split(":")]
        if "=" in parts[0]:
            if not entries:
                raise ValueError(f"--sim-effects {spec!r}: {token!r} has no effect name before it")
            name, overrides = entries[-1][0], parts
        else:
            name, overrides = parts[0], parts[1:]
            if name not in EFFECTS:
                raise ValueError(f"unknown effect {name!r}; effects: {', '.join(EFFECTS)}")
            entries.append((name, {}))
        for kv in overrides:
            if kv.count("=") != 1 or not kv.split("=")[0].strip():
                raise ValueError(f"--sim-effects: override {kv!r} of {name} must be key=value")
            k, v = (s.strip() for s in kv.split("="))
            entries[-1][1][k] = _number(v, f"{name}:{k}")
    return [make_effect(name, **params) for name, params in entries]


def parse_mappers(spec) -> tuple[str, ...]:
    """Mapper names of :data:`ALL_MAPPERS` from a comma-separated string or a sequence (None: :data:`MAPPERS`)."""
    from noise_model.reporting import check_names

    from .compare import ALL_MAPPERS, MAPPERS

    if spec is None:
        return MAPPERS
    return tuple(check_names(spec, "--mappers", ALL_MAPPERS, "mapper"))


def parse_reality(reality, sim_effects=None) -> dict:
    """The walk's reality from ``--reality`` and ``--sim-effects``.

    Parameters
    ----------
    reality : str
        ``"reference"``, ``"stereo"``, or the path of a gap report (``*.json``): the reference simulation
        plus the effects that report selected, as fitted.
    sim_effects : str or sequence, optional
        Effects added to the reference reality (:func:`parse_effects`); not with ``stereo`` or a gap report.

    Returns
    -------
    dict
        ``kind`` ("reference", "stereo" or "gap"), ``sensor`` ("reference" or "stereo"), ``effects`` (list of
        Effect), ``gap_report`` (str or None), ``effects_digest`` (SHA-256 of the effects' names and
        parameters, None without effects).

    Raises
    ------
    ValueError
        Unknown reality, an unreadable gap report, or effects where the reality takes none.
    """
    if not isinstance(reality, str):
        raise ValueError(f"reality must be a string, got {reality!r}")
    effects = parse_effects(sim_effects)
    if reality.lower().endswith(".json"):
        if effects:
            raise ValueError("a gap report is the reality's effects already: give --sim-effects or a gap report "
                             "as --reality, not both")
        effects = parse_effects(reality)
        kind, sensor, gap = "gap", "reference", reality
    elif reality in REALITIES:
        kind = sensor = reality
        gap = None
        if reality == "stereo" and effects:
            raise ValueError("the stereo reality makes its own noise: it takes no sim effects")
    else:
        raise ValueError(f"unknown reality {reality!r}; realities: {', '.join(REALITIES)} or a gap report "
                         "(elevmap gap --json PATH)")
    digest = None
    if effects:
        import json

        text = json.dumps([[e.name, {k: v for k, v in sorted(dict(e.params).items())}] for e in effects],
                          default=float)
        digest = hashlib.sha256(text.encode()).hexdigest()
    return {"kind": kind, "sensor": sensor, "effects": effects, "gap_report": gap, "effects_digest": digest}


def parse_settings(spec) -> dict:
    """Map settings from ``--set KEY=VALUE[,KEY=VALUE]``: fields of :class:`elevmap.FusionParams`,
    ``visibility_cleanup`` and the camera's ``bin_at_plane`` and ``valid_margin_px``. A value is read as the field's default is
    typed: ``none`` (a field that may be None), ``true``/``false``, an integer or a number;
    ``neighbour_estimator`` takes a name.

    Returns
    -------
    dict
        {name: value}; empty for None or an empty string.

    Raises
    ------
    ValueError
        Unknown setting, malformed entry, or a value of the wrong type.
    """
    if spec is None or (isinstance(spec, str) and not spec.strip()):
        return {}
    if isinstance(spec, dict):
        items = list(spec.items())
    else:
        items = []
        for token in (t.strip() for t in str(spec).split(",")):
            if token.count("=") != 1 or not token.split("=")[0].strip():
                raise ValueError(f"--set: {token!r} must be KEY=VALUE")
            k, v = (x.strip() for x in token.split("="))
            items.append((k, v))
    defaults = {f.name: f.default for f in fields(FusionParams)}
    defaults["visibility_cleanup"] = MappingConfig.visibility_cleanup
    defaults["bin_at_plane"] = True
    defaults["valid_margin_px"] = DEFAULT_VALID_MARGIN_PX
    out = {}
    for k, v in items:
        if k not in defaults:
            raise ValueError(f"--set: unknown setting {k!r}; settings: {', '.join(sorted(defaults))}")
        out[k] = _setting_value(k, v, defaults[k]) if isinstance(v, str) else v
    return out


def _setting_value(name: str, text: str, default):
    t = text.strip().lower()
    if t in ("none", "null"):
        return None
    if isinstance(default, bool):
        if t not in ("true", "false"):
            raise ValueError(f"--set {name}: {text!r} is not true or false")
        return t == "true"
    if name == "neighbour_estimator":
        return text.strip()
    try:
        return int(t) if isinstance(default, int) else float(t)
    except ValueError:
        raise ValueError(f"--set {name}: {text!r} is not a number") from None


def apply_settings(config: MappingConfig, settings: dict) -> MappingConfig:
    """``config`` with the ``settings`` of :func:`parse_settings` (the FusionParams and MappingConfig checks
    apply)."""
    fusion = {k: v for k, v in settings.items() if k not in MAP_SETTINGS + CAMERA_SETTINGS}
    mapping = {k: v for k, v in settings.items() if k in MAP_SETTINGS}
    return replace(config, fusion=replace(config.fusion, **fusion), **mapping)


def camera_settings(settings: dict) -> dict:
    """The keyword arguments of :class:`elevmap.Camera` among the ``settings`` of :func:`parse_settings`."""
    return {k: v for k, v in settings.items() if k in CAMERA_SETTINGS}
