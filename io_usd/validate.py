"""Validate a stage with usd-core's registered validators (pxr.UsdValidation), and a cache for what
they do not look at (cache_errors)."""

import math

import numpy as np
from pxr import Usd, UsdValidation


def validation_errors(path_or_stage):
    """Every error (not warning) that usd-core's validators report, as readable strings."""
    stage = Usd.Stage.Open(path_or_stage) if isinstance(path_or_stage, str) else path_or_stage
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = context.Validate(stage)
    return [f"{e.GetName()}: {e.GetMessage()}" for e in errors
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def validation_report(path_or_stage):
    """All findings (errors and warnings) as strings."""
    stage = Usd.Stage.Open(path_or_stage) if isinstance(path_or_stage, str) else path_or_stage
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    return [f"{e.GetType()}: {e.GetName()}: {e.GetMessage()}" for e in context.Validate(stage)]


def cache_errors(reader):
    """What a cache must hold that usd-core's validators do not check (io_usd.cache.CacheReader):
    a positive frame rate, a time range that runs forward, known roles, finite points in every
    sample. Readable strings; none for a sound cache."""
    from .cache import ROLES

    errors = []
    if not (math.isfinite(reader.fps) and reader.fps > 0.0):
        errors.append(f"timeCodesPerSecond: must be positive, got {reader.fps:g}")
    if reader.end_frame < reader.start_frame:
        errors.append(f"endTimeCode: {reader.end_frame} is before startTimeCode {reader.start_frame}")
    for name, prim in reader.prims.items():
        if prim.role not in ROLES:
            errors.append(f"{prim.path}.cfx:role: unknown role {prim.role!r} (expected {', '.join(ROLES)})")
            continue
        for frame in reader.frames(name):
            if not np.all(np.isfinite(reader.points(name, frame))):
                errors.append(f"{prim.path}.points: non-finite positions at time {frame}")
                break
    return errors
