"""Scene files (TOML) read into dataclasses, with errors that name the file, the key and the reason."""

import dataclasses
import difflib
import math
import tomllib


def _coerce(value, default, source, key):
    from .errors import InputError

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise InputError(source, key, f"expected a boolean, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(source, key, f"expected an integer, got {value!r}")
        if not -2 ** 31 <= value < 2 ** 31:  # the kernels' ints are 32-bit: larger ones wrapped silently
            raise InputError(source, key, f"must lie within 32-bit integers, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(source, key, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(source, key, f"expected a finite number, got {value!r}")
        return float(value)
    if isinstance(default, tuple):
        ok = isinstance(value, list) and len(value) == len(default) and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
        if not ok:
            raise InputError(source, key, f"expected a list of {len(default)} finite numbers, got {value!r}")
        return tuple(float(v) for v in value)
    if isinstance(default, str) or default is None:
        if not isinstance(value, str):
            raise InputError(source, key, f"expected a string, got {value!r}")
        return value
    return value



# Range checks for the settings' dataclasses (their __post_init__): the ValueError starts with the field's
# name, which from_table turns into the scene file's key.
def require_positive(settings, *names):
    for name in names:
        value = getattr(settings, name)
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value!r}")


def require_nonnegative(settings, *names):
    for name in names:
        value = getattr(settings, name)
        if not value >= 0:
            raise ValueError(f"{name} must be zero or positive, got {value!r}")


def require_length_at_most(settings, name, top):
    """A vector setting (gravity, wind) no longer than top."""
    value = getattr(settings, name)
    if math.hypot(*value) > top:
        raise ValueError(f"{name} must be at most {top:g} long, got {list(value)}")


def require_within(settings, name, low, high, high_open=False):
    """low <= value <= high (value < high when high_open)."""
    value = getattr(settings, name)
    if not (low <= value and (value < high if high_open else value <= high)):
        raise ValueError(f"{name} must be within [{low:g}, {high:g}{')' if high_open else ']'}, got {value!r}")


# the largest values that still make a scene a machine can run: beyond them a run hangs for hours or is
# killed for memory (substeps 2^31 took 24 GB; a detail level of 100,000 likewise) instead of failing at once
LIMITS = {
    ("scene", "frames"): 1_000_000,
    ("scene", "preroll"): 3600.0,
    ("solver", "substeps"): 10_000,
    ("cloth.solver", "substeps"): 10_000,
    ("cloth.solver", "body_candidates"): 4096,
    ("cloth.detail", "level"): 64,
    ("cloth", "particles"): 1_000_000,
    ("hair", "vertices"): 4096,
    ("hair", "count"): 10_000_000,
    ("scene", "fps"): 10_000.0,
    ("head", "sphere_leaves"): 1_000_000,
    ("solver", "shape_iterations"): 1000,
    ("solver", "rotation_iterations"): 1000,
    ("cloth.solver", "strain_iterations"): 1000,
    ("cloth.solver", "walk_steps"): 100_000,
    ("cloth.detail", "smoothing"): 1000,
    ("capture", "guides"): 10_000,
    ("capture", "ring_cameras"): 1000,
}
# settings past which a scene is no longer a character's: hair grown or pushed metres out, a garment fitted a
# room away, gusts faster than the wind by orders: such runs blew up or left the frame
SCALE_LIMITS = {
    ("hair", "length"): 10.0,
    ("hair", "density"): 1000.0,
    ("hair", "wave_amplitude"): 1.0,
    ("hair", "curl_radius"): 1.0,
    ("hair", "root_width"): 0.1,
    ("hair", "tip_width"): 0.1,
    ("hair", "clearance"): 0.1,
    ("solver", "collision_margin"): 0.1,
    ("solver", "wind_turbulence"): 10.0,
    ("solver", "wind_turbulence_scale"): 1000.0,
    ("solver", "wind_turbulence_rate"): 1000.0,
    ("cloth", "ease"): 0.2,
    ("cloth.solver", "collision_margin"): 0.1,
    ("cloth.solver", "body_proxy"): 1.0,
    ("cloth.solver", "wind_turbulence"): 10.0,
    ("cloth.solver", "wind_turbulence_scale"): 1000.0,
    ("cloth.solver", "wind_turbulence_rate"): 1000.0,
    ("cloth.detail", "margin"): 0.1,
    ("cloth.detail", "reference_fps"): 10_000.0,
    ("face", "lift"): 0.05,
}


def from_table(cls, table, source, section, overrides=None):
    """Build dataclass `cls` from a TOML table; unknown keys, wrong types and bad values raise InputError."""
    from .errors import InputError

    if not isinstance(table, dict):
        raise InputError(source, f"[{section}]", "expected a table")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    defaults = cls()
    kwargs = {}
    for key, value in table.items():
        where = f"{section}.{key}"
        if key not in fields:
            close = difflib.get_close_matches(key, fields, n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else f" (known: {', '.join(fields)})"
            raise InputError(source, where, f"unknown key{hint}")
        kwargs[key] = _coerce(value, getattr(defaults, key), source, where)
    kwargs.update(overrides or {})
    for key, value in kwargs.items():
        for limits, why in ((LIMITS, "a larger value would not finish"), (SCALE_LIMITS, "beyond a character's scale")):
            top = limits.get((section, key))
            if top is not None and isinstance(value, (int, float)) and value > top:
                raise InputError(source, f"{section}.{key}", f"at most {top:,} ({why}), got {value!r}")
    try:
        return cls(**kwargs)
    except ValueError as err:
        # dataclass checks name their field first: "shape_stiffness must be in (0, 1]"
        field = str(err).split(" ", 1)[0]
        where = f"{section}.{field}" if field in fields else f"[{section}]"
        raise InputError(source, where, str(err)) from None


def load_toml(path):
    from .errors import InputError

    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise InputError(path, None, "no such file") from None
    except IsADirectoryError:
        raise InputError(path, None, "is a directory, expected a TOML scene file") from None
    except tomllib.TOMLDecodeError as err:
        raise InputError(path, None, f"not valid TOML: {err}") from None
