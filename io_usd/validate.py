"""Validate a stage with usd-core's registered validators (pxr.UsdValidation)."""

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
