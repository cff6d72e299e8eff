"""The grammar of a procedural warp spec (`name:key=value,...`), checked where settings are
validated; the warps themselves (`texelbake.deform.warps`) place it on an asset."""

from __future__ import annotations

import math

#: the axes a warp may name
AXIS_NAMES = ("x", "y", "z")

#: name -> {parameter: default}
WARP_PARAMS: dict[str, dict[str, object]] = {
    "twist": {"angle": 90.0, "axis": "y"},
    "bend": {"angle": 90.0, "axis": "y", "toward": "x"},
    "sine": {"amplitude": 0.1, "periods": 1.0, "phase": 0.0, "axis": "y", "toward": "x"},
    "stretch": {"x": 1.0, "y": 2.0, "z": 1.0},
    "scale": {"s": 2.0},
    "rigid": {"angle": 30.0, "axis": "z", "tx": 0.0, "ty": 0.0, "tz": 0.0},
}


def parse_warp_fields(spec: str) -> tuple[str, dict[str, object]]:
    """(name, parameters with their defaults filled in) of a warp spec; ValueError naming the
    field (`warp.<key>`) when a name, key or value is not the grammar's."""
    text = spec.strip()
    name, _, rest = text.partition(":")
    name = name.strip().lower()
    if name not in WARP_PARAMS:
        raise ValueError(f"field 'warp': unknown warp {name!r} in {spec!r}; expected one of "
                            f"{sorted(WARP_PARAMS)}")
    params = dict(WARP_PARAMS[name])
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq:
            raise ValueError(f"field 'warp': {item!r} in {spec!r} is not key=value")
        if key not in params:
            raise ValueError(f"field 'warp.{key}': {name} takes {sorted(params)}, got "
                                f"{key!r}")
        if isinstance(params[key], str):
            v = value.strip().lower()
            if v not in AXIS_NAMES:
                raise ValueError(f"field 'warp.{key}': expected x, y or z, got {value!r}")
            params[key] = v
        else:
            try:
                params[key] = float(value)
            except ValueError:
                raise ValueError(f"field 'warp.{key}': expected a number, got "
                                    f"{value!r}") from None
            if not math.isfinite(float(params[key])):  # type: ignore[arg-type]
                raise ValueError(f"field 'warp.{key}': must be finite, got {value!r}")
    return name, params


def check_warp_spec(spec: str) -> str:
    """Check a warp spec before any asset is read (a setting, a CLI flag): its name, fields
    and values, and an axis-bent warp's `toward` off its axis; returns the spec. What depends
    on the asset (a flat extent along the axis) is checked by `parse_warp`."""
    name, prm = parse_warp_fields(spec)
    if name in ("bend", "sine") and prm["axis"] == prm["toward"]:
        raise ValueError(f"field 'warp.toward': must differ from the axis "
                            f"{prm['axis']!r}, got {prm['toward']!r}")
    return spec
