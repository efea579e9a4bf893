"""Every number of every plan kind is finite, normal and within its field's range
(`rigctl.plans.schema`, docs/plans.md): a subnormal, a huge number, NaN or an infinity in any
numeric field is refused by `validate` and by the daemon's `load` alike, in one line naming the
field. An agent radius of 1e-320 passed `validate` and was answered `internal` by `load` (an
OverflowError in the model's wall step).

The fields are not listed by hand: they are walked from the pydantic models of each plan kind,
and the documents below must give every one of them a value (a field added to a model and to no
document fails `test_the_documents_give_every_numeric_field_of_every_plan_kind_a_value`)."""

from __future__ import annotations

import copy
import json
import math
import types
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from rigctl.apps.cli.main import main
from rigctl.apps.daemon.plan_runs import PlanRuns
from rigctl.core.errors import PlanError
from rigctl.plans.schema import (
    FieldSequencePlan,
    GlobalMovesPlan,
    PairFormationPlan,
    parse_plan,
)

EXAMPLES = Path(__file__).resolve().parents[2] / "plans" / "examples"
KINDS = {"global-moves": GlobalMovesPlan, "pair-formation": PairFormationPlan,
         "field-sequence": FieldSequencePlan}
BAD = {"subnormal": 1e-320, "negative subnormal": -5e-324, "huge": 1e300, "negative huge": -1e300,
       "NaN": math.nan, "infinity": math.inf, "negative infinity": -math.inf}


# -- the numeric fields of a plan kind, from its models --------------------------------------------

def _members(annotation) -> list:
    """The types an annotation stands for: Annotated and unions unwrapped, None left out."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _members(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        return [m for arg in typing.get_args(annotation) for m in _members(arg)]
    return [] if annotation is type(None) else [annotation]


def numeric_fields(model: type[BaseModel]) -> set[str]:
    """Every numeric leaf of a model: `Model.field` and, inside the field, `*` for a list's items
    and the position in a tuple (`RectShape.rect.2`, `GlobalMovesPlan.moves.*.0`)."""
    found: set[str] = set()

    def walk(annotation, where: str) -> None:
        for member in _members(annotation):
            origin = typing.get_origin(member)
            if isinstance(member, type) and issubclass(member, BaseModel):
                found.update(numeric_fields(member))
            elif origin is list:
                walk(typing.get_args(member)[0], f"{where}.*")
            elif origin is tuple:
                for index, item in enumerate(typing.get_args(member)):
                    walk(item, f"{where}.{index}")
            elif member in (int, float):
                found.add(where)

    for name, info in model.model_fields.items():
        walk(info.annotation, f"{model.__name__}.{info.alias or name}")
    return found


def numeric_values(document: dict, model: type[BaseModel]) -> dict[str, str]:
    """JSON path -> numeric field (`numeric_fields`'s name) of every number in a plan document."""
    paths: dict[str, str] = {}

    def walk(value, annotation, where: str, path: str) -> None:
        for member in _members(annotation):
            origin = typing.get_origin(member)
            if isinstance(member, type) and issubclass(member, BaseModel):
                if isinstance(value, dict) and _fits(value, member):
                    model_values(value, member, path)
            elif origin is list and isinstance(value, list):
                for index, item in enumerate(value):
                    walk(item, typing.get_args(member)[0], f"{where}.*", f"{path}.{index}")
            elif origin is tuple and isinstance(value, list):
                for index, (item, kind) in enumerate(zip(value, typing.get_args(member))):
                    walk(item, kind, f"{where}.{index}", f"{path}.{index}")
            elif member in (int, float) and isinstance(value, (int, float)):
                paths[path.lstrip(".")] = where

    def model_values(value: dict, model: type[BaseModel], path: str) -> None:
        for name, info in model.model_fields.items():
            key = info.alias or name
            if key in value:
                walk(value[key], info.annotation, f"{model.__name__}.{key}", f"{path}.{key}")

    model_values(document, model, "")
    return paths


def _fits(value: dict, model: type[BaseModel]) -> bool:
    """Whether a JSON object is of this member of a union (the shapes', the workspaces')."""
    keys = {info.alias or name for name, info in model.model_fields.items()}
    required = {info.alias or name for name, info in model.model_fields.items()
                if info.is_required()}
    return required <= set(value) <= keys


# -- documents that give every numeric field a value -----------------------------------------------

def _full(name: str, **changes) -> dict:
    """An example plan with every default written out (so each default field has a value)."""
    document = json.loads((EXAMPLES / name).read_text())
    document.update(changes)
    plan = parse_plan(document, name)
    return plan.model_dump(mode="json", by_alias=True, exclude_none=True)


EVERY_SHAPE = {"boundary": {"rect": [0.0, 0.0, 400.0, 400.0]},
               "obstacles": [{"polygon": [[10.0, 10.0], [30.0, 10.0], [20.0, 30.0]]},
                             {"disk": [200.0, 200.0, 5.0]}]}
IMAGE = {"image": "vessel-maze.png", "mm_per_px": 0.5, "origin": [1.0, 2.0]}
DOCUMENTS = {
    "global-moves": [_full("fig4-quick.json"), _full("fig4-quick.json", workspace=EVERY_SHAPE),
                     _full("fig4-quick.json", workspace=IMAGE)],
    "pair-formation": [_full("pair-microfactory.json"),
                       _full("pair-microfactory.json", workspace=EVERY_SHAPE),
                       _full("pair-microfactory.json", workspace=IMAGE)],
    "field-sequence": [_full("depm-plan.json")],
}


def _cases() -> list[tuple[str, str, str]]:
    """(plan kind, JSON path, field): each numeric field of each kind once, at its first place
    in the documents (the first item of a list stands for the rest)."""
    first: dict[tuple[str, str], str] = {}
    for kind, documents in DOCUMENTS.items():
        for document in documents:
            for path, field in numeric_values(document, KINDS[kind]).items():
                first.setdefault((kind, field), path)
    return sorted((kind, path, field) for (kind, field), path in first.items())


CASES = _cases()


PATHS = {kind: [set(numeric_values(document, KINDS[kind])) for document in documents]
         for kind, documents in DOCUMENTS.items()}


def _document_with(kind: str, path: str, value) -> dict:
    """The first document of `kind` that has `path`, with `value` there."""
    for document, paths in zip(DOCUMENTS[kind], PATHS[kind]):
        if path in paths:  # copied along the path only: the rest is shared, unchanged
            changed = node = copy.copy(document)
            *parents, last = (int(p) if p.isdigit() else p for p in path.split("."))
            for part in parents:
                node[part] = copy.copy(node[part])
                node = node[part]
            node[last] = value
            return changed
    raise AssertionError(f"no {kind} document has {path}")


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_documents_give_every_numeric_field_of_every_plan_kind_a_value(kind):
    covered = {field for document in DOCUMENTS[kind]
               for field in numeric_values(document, KINDS[kind]).values()}
    fields = numeric_fields(KINDS[kind])
    assert len(fields) > 10  # the walk found the fields (the shapes, the arms, ...)
    assert fields - covered == set(), "give these fields a value in a document of DOCUMENTS"
    for document in DOCUMENTS[kind]:
        parse_plan(document, "p.json")  # each document is a valid plan as it is


@pytest.mark.parametrize("kind, path, field", CASES, ids=[f"{k}:{p}" for k, p, _ in CASES])
def test_a_bad_number_in_any_numeric_field_is_refused_in_one_line_naming_it(kind, path, field):
    for what, value in BAD.items():
        document = _document_with(kind, path, value)
        for source, parse in (("p.json", lambda: parse_plan(document, "p.json")),  # validate's
                              ("plan", lambda: PlanRuns.parse_plan(None, document))):  # load's
            with pytest.raises(PlanError) as refused:
                parse()
            message = str(refused.value)
            assert message.startswith(f"{source}: {path}: ") and "\n" not in message, (
                what, message)


@pytest.mark.parametrize("kind", list(KINDS))
def test_validate_refuses_a_subnormal_in_every_numeric_field_with_one_line(kind, tmp_path,
                                                                           capsys):
    for path in sorted({p for k, p, _ in CASES if k == kind}):
        plan = tmp_path / "plan.json"
        plan.write_text(json.dumps(_document_with(kind, path, 1e-320)))
        assert main(["validate", str(plan)]) == 2, path
        err = capsys.readouterr().err
        assert err.startswith(f"error: {plan}: {path}: ") and err.count("\n") == 1, err


def test_a_subnormal_radius_says_why():
    document = _document_with("global-moves", "agents.0.radius", 1e-320)
    with pytest.raises(PlanError, match=r"agents.0.radius: Input should be greater than or equal"):
        parse_plan(document, "p.json")
    document = _document_with("global-moves", "moves.0.0", 1e-320)
    with pytest.raises(PlanError, match=r"p.json: moves.0.0: 1e-320 is subnormal: a number here "
                                        r"is 0 or at least 2.23e-308 in size"):
        parse_plan(document, "p.json")
