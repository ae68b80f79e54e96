"""Validation errors in the words of a schema's reader, not pydantic's: every file swarmloc
reads (scenarios, agent configurations, study specs, faults, estimator settings) is checked by a
pydantic model, and its errors name union members (`constrained-float`, `literal['x']`), classes
(`instance of Prior`), Python types (`NoneType`) and carry prefixes ("Value error, ") that mean
nothing to someone who wrote YAML."""

from __future__ import annotations

from pydantic import BaseModel, ValidationError


def readable(err: dict) -> str:
    """A pydantic error's message in this schema's words: no "Value error, " prefix, no class
    names, YAML's names for types."""
    kind, msg = err["type"], err["msg"]
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return f"must be a mapping of fields, got {yaml_type(err.get('input'))}"
    if kind == "missing":
        return "required"
    if kind == "extra_forbidden":
        return "unknown field"
    ctx, got = err.get("ctx") or {}, yaml_type(err.get("input"))
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()), "?")
        return f"must be {bounds[kind]} {limit}, got {err.get('input')!r}"
    if kind in ("int_parsing", "int_type", "int_from_float"):
        return f"must be a whole number, got {got}"
    if kind in ("float_parsing", "float_type"):
        return f"must be a number, got {got}"
    if kind in ("bool_parsing", "bool_type"):
        return f"must be true or false, got {got}"
    if kind in ("list_type", "tuple_type"):
        return f"must be a list, got {got}"
    if kind in ("string_type",):
        return f"must be text, got {got}"
    if kind == "string_pattern_mismatch":
        return f"must match {ctx.get('pattern')}, got {got}"
    if kind == "literal_error":
        return f"must be {ctx.get('expected')}, got {got}"
    if kind == "finite_number":
        return f"must be a finite number, got {err.get('input')!r}"
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        tags = str(ctx.get("expected_tags", "")).replace("'", "")
        if kind == "union_tag_not_found":
            return "required"  # the field that says which kind this is (kind, action)
        return f"unknown {ctx.get('discriminator', 'kind').strip(chr(39))} {ctx.get('tag')!r}; one of: {tags}"
    if kind in ("too_short", "too_long"):
        n = ctx.get("min_length" if kind == "too_short" else "max_length")
        return f"must have at {'least' if kind == 'too_short' else 'most'} {n} item{'s' if n != 1 else ''}, got " \
               f"{ctx.get('actual_length')}"
    return msg.removeprefix("Value error, ").removeprefix("Assertion failed, ")


def yaml_type(value) -> str:
    """What a YAML reader calls the type of a parsed value."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (int, float)):
        return f"{value!r}"
    return {str: f"the text {value!r}", list: "a list", dict: "a mapping"}.get(type(value), type(value).__name__)


def _field_path(loc: tuple, fields: set[str], unknown: bool = False) -> str:
    """A pydantic location as the YAML path a user wrote: list indices kept, pydantic's own
    parts (the member tags of a union such as `constrained-float` or `literal['x']`, a
    discriminated union's tag) dropped."""
    last = len(loc) - 1 if unknown else len(loc)  # an unknown field's name is the last part
    return ".".join(str(p) for i, p in enumerate(loc) if isinstance(p, int) or p in fields or i == last)


def schema_fields(*models) -> set[str]:
    """Every field name of these pydantic models and of the models nested in them."""
    seen, names = set(), set()
    todo = list(models)
    while todo:
        m = todo.pop()
        if m in seen or not (isinstance(m, type) and issubclass(m, BaseModel)):
            continue
        seen.add(m)
        for name, f in m.model_fields.items():
            names.add(name)
            todo.extend(_models_in(f.annotation))
    return names


def _models_in(annotation) -> list:
    import typing

    out = [annotation] if isinstance(annotation, type) and issubclass(annotation, BaseModel) else []
    for a in typing.get_args(annotation):
        out.extend(_models_in(a))
    return out


def problems_of(exc: ValidationError, fields: set[str]) -> list[tuple[str, str]]:
    """(field path, message) per error; the members of one union that all failed on the same
    field are one problem."""
    out: dict[str, list[str]] = {}
    for err in exc.errors():
        msgs = out.setdefault(_field_path(err["loc"], fields, err["type"] == "extra_forbidden"), [])
        if (m := readable(err)) not in msgs:
            msgs.append(m)
    return [(loc, "; or ".join(msgs)) for loc, msgs in out.items()]
