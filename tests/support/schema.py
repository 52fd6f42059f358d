"""Records checked against the package's JSON Schemas (:data:`service.output.records.SCHEMAS`,
draft 2020-12) by jsonschema, an independent validator.

One rule is added to the standard's: a number must be finite. JSON has no NaN or Infinity,
and Python's ``json`` would write them, so a record carrying one is not valid output.
"""

from __future__ import annotations

import math
from typing import Any

from jsonschema import Draft202012Validator, ValidationError, validators

from service.output.records import SCHEMAS

_STANDARD = Draft202012Validator.TYPE_CHECKER


def _finite_number(checker: Any, value: Any) -> bool:
    return _STANDARD.is_type(value, "number") and math.isfinite(value)


def _finite_integer(checker: Any, value: Any) -> bool:
    # draft 2020-12, section 6.1.1: 1.0 is an integer (jsonschema's checker agrees)
    return _STANDARD.is_type(value, "integer") and math.isfinite(value)


FiniteValidator = validators.extend(
    Draft202012Validator,
    type_checker=_STANDARD.redefine_many({"number": _finite_number, "integer": _finite_integer}),
)

ENVELOPE = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "type": "object",
    "required": ["class"],
    "properties": {"class": {"enum": sorted(SCHEMAS)}},
}
"""What every record is: an object whose ``class`` names one of the schemas."""

_ENVELOPE = FiniteValidator(ENVELOPE)
_BY_CLASS = {cls: FiniteValidator(schema) for cls, schema in SCHEMAS.items()}


def schema_errors(record: Any) -> list[ValidationError]:
    """Every violation of the schema of ``record["class"]`` (or of the envelope)."""
    errors = list(_ENVELOPE.iter_errors(record))
    if errors:
        return errors
    return sorted(_BY_CLASS[record["class"]].iter_errors(record), key=lambda e: e.json_path)


def validate(record: Any) -> list[str]:
    """``"<json path>: <message>"`` for every violation; an empty list means valid."""
    return [f"{e.json_path}: {e.message}" for e in schema_errors(record)]
