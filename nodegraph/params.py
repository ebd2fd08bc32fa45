"""A node type's parameters: the `NodeParams` model base, `Param` fields, their strict
number checks and the (parameter, message) pairs errors report.

A parameter model's own check of one parameter raises `ParamProblem(param, problem)`, so that
the error names the parameter (`'fps': expected a number ...`) whatever pydantic's location
for a model-wide validator says.
"""

from __future__ import annotations

import numbers
import types
from typing import TYPE_CHECKING, Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

if TYPE_CHECKING:
    from .node import Node

__all__ = ["MAX_MAGNITUDE", "NodeParams", "Param", "ParamProblem", "Index", "number_problem", "field_flag",
           "path_params", "format_validation_error"]


class ParamProblem(ValueError):
    """Raised by a parameter model's validator: parameter `param` is wrong, `problem` says how
    (what was expected and what was found)."""

    def __init__(self, param: str, problem: str):
        super().__init__(f"'{param}': {problem}")
        self.param = param
        self.problem = problem


MAX_MAGNITUDE = 1e12
"""Largest magnitude of a float parameter on a side where its field declares no bound (`ge`,
`gt`, `le`, `lt`): beyond it a value is a typo or a probe, and arithmetic on it overflows."""


class NodeParams(BaseModel):
    """Base of every node's parameter model.

    Unknown names are errors; values are frozen; floats must be finite, and at most
    `MAX_MAGNITUDE` (1e12) in magnitude on a side where the field declares no bound of its own;
    numbers are strict (`true` or "3" is not an integer, `true` or "1.5" is not a float; an
    integer is a valid float); booleans are strict (only `true` / `false`: not "yes", "true"
    or 1).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _strict_numbers(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for name, value in data.items():
                info = cls.model_fields.get(name)
                if info is not None:
                    problem = number_problem(info.annotation, value, tuple(info.metadata))
                    if problem:
                        raise ParamProblem(name, problem)
        return data


def _number_kinds(annotation: Any) -> tuple[set[type], Any]:
    """({int, float} the annotation admits directly, element annotation of a list/tuple)."""
    origin = get_origin(annotation)
    if origin is Annotated:
        return _number_kinds(get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        kinds: set[type] = set()
        element = None
        for arg in get_args(annotation):
            k, e = _number_kinds(arg)
            kinds |= k
            element = element or e
        return kinds, element
    if origin in (list, tuple):
        args = [a for a in get_args(annotation) if a is not Ellipsis]
        return set(), (args[0] if args else None)
    if annotation in (int, float):
        return {annotation}, None
    if annotation is bool or annotation is str:
        return {annotation}, None
    if origin is Literal:  # Literal["a", "b"] admits those strings: a union with it takes strings
        return {type(a) for a in get_args(annotation) if isinstance(a, (str, bool))}, None
    return set(), None


def _declared_bounds(metadata: tuple[Any, ...]) -> tuple[bool, bool]:
    """(has a lower bound, has an upper bound) among a field's constraints (`ge`, `gt`, `le`, `lt`)."""
    lower = upper = False
    for item in metadata:
        if hasattr(item, "metadata") and isinstance(item.metadata, list):  # a Field() inside Annotated
            inner = _declared_bounds(tuple(item.metadata))
            lower, upper = lower or inner[0], upper or inner[1]
            continue
        lower = lower or getattr(item, "ge", None) is not None or getattr(item, "gt", None) is not None
        upper = upper or getattr(item, "le", None) is not None or getattr(item, "lt", None) is not None
    return lower, upper


def number_problem(annotation: Any, value: Any, metadata: tuple[Any, ...] = ()) -> str:
    """Why `value` is not a strict number or boolean for `annotation` ("" when fine).

    `metadata`: the field's constraints, for the `MAX_MAGNITUDE` check of floats.
    """
    if get_origin(annotation) is Annotated:
        base, *extra = get_args(annotation)
        return number_problem(base, value, (*metadata, *extra))
    kinds, element = _number_kinds(annotation)
    numeric = kinds & {int, float}
    if numeric:
        want = "an integer" if numeric == {int} else "a number"
        if isinstance(value, bool) and bool not in kinds:
            return f"expected {want}, found {value!r}"
        if isinstance(value, str) and str not in kinds:
            return f"expected {want}, found the string {value!r}"
        if numeric == {int} and isinstance(value, float):
            return f"expected {want}, found {value!r}"
        if float in numeric and isinstance(value, numbers.Real) and not isinstance(value, bool) \
                and abs(value) != float("inf"):  # non-finite values: pydantic's allow_inf_nan says so
            lower, upper = _declared_bounds(metadata)
            if (value > MAX_MAGNITUDE and not upper) or (value < -MAX_MAGNITUDE and not lower):
                text = repr(value)
                found = text if len(text) <= 24 else f"{text[:12]}... ({len(text)} digits)"
                limit = f"{MAX_MAGNITUDE:g}".replace("e+", "e")
                return (f"expected a number of magnitude at most {limit} (the parameter declares no bound of "
                        f"its own), found {found}")
    if bool in kinds and not isinstance(value, bool):
        if isinstance(value, str) and str not in kinds:
            return f"expected true or false, found the string {value!r}"
        if isinstance(value, numbers.Real) and not numeric:
            return f"expected true or false, found {value!r}"
    if element is not None and isinstance(value, (list, tuple)):
        for index, item in enumerate(value):
            problem = number_problem(element, item)
            if problem:
                return f"item {index}: {problem}"
    return ""


def path_params(cls: type["Node"]) -> list[str]:
    """Names of `cls.Params` fields declared as input or output file paths."""
    return [name for name in cls.Params.model_fields
            if field_flag(cls.Params, name, "input_file", False) or field_flag(cls.Params, name, "output_file", False)]


def Param(default: Any = ..., *, description: str = "", affects_output: bool = True,
          input_file: bool = False, output_file: bool = False, **constraints: Any) -> Any:
    """Declare a parameter field.

    Args:
        default: default value (`...` for required).
        description: meaning and units, shown by `nodegraph nodes`.
        affects_output: False for parameters that cannot change results (logging, device);
            they are left out of the cache key.
        input_file: the value is a path (or pattern) of a file the node reads; the cache key
            holds the files' content hash instead of the path. A relative path written in a
            graph file is resolved against the graph file's folder.
        output_file: the value is a path (or pattern, or folder) the node writes; resolved
            like `input_file` paths. Before a run, every output path is checked against every
            input path (`nodegraph.pathcheck`); writers write through `nodegraph.files` so that
            their files are held back until the whole run succeeded (`nodegraph.staging`).
        constraints: pydantic bounds (`ge`, `gt`, `le`, `lt`, `min_length`, ...).
    """
    extra = {"affects_output": affects_output, "input_file": input_file, "output_file": output_file}
    if isinstance(default, (list, dict)):
        value = default
        return Field(default_factory=lambda: type(value)(value), description=description,
                     json_schema_extra=extra, **constraints)
    return Field(default, description=description, json_schema_extra=extra, **constraints)


Index = Annotated[int, Field(ge=0)]
"""A non-negative integer (vertex, frame or landmark index): `vertices: list[Index]`."""


def field_flag(model: type[BaseModel], name: str, flag: str, default: bool) -> bool:
    extra = model.model_fields[name].json_schema_extra
    return bool(extra.get(flag, default)) if isinstance(extra, dict) else default


def format_validation_error(err: ValidationError) -> list[tuple[str, str]]:
    """Turn a pydantic error into (parameter name, message) pairs (a `ParamProblem` raised by a
    model's validator names its parameter)."""
    out = []
    for item in err.errors():
        loc = ".".join(str(x) for x in item.get("loc", ())) or "params"
        msg = item.get("msg", "invalid")
        problem = (item.get("ctx") or {}).get("error")
        if isinstance(problem, ParamProblem):  # a model's own check of one parameter
            out.append((problem.param, problem.problem))
            continue
        if item.get("type") == "extra_forbidden":
            msg = "unknown parameter"
        if item.get("type") == "value_error":  # a validator's own message says what was found
            out.append((loc, msg.removeprefix("Value error, ")))
            continue
        out.append((loc, f"{msg} (found {item.get('input')!r})" if "input" in item and
                    item.get("type") != "missing" else msg))
    return out
