"""Every ``TaskConfig`` field of the proto is in the client: create_task, TaskConfig, docs.

These tests fail when a field is added to ``proto/tamrm/v1/shaping.proto``'s ``TaskConfig``
(and the stubs regenerated) without adding it to the client.
"""

from __future__ import annotations

import dataclasses
import inspect
import typing
from pathlib import Path

import pytest
from google.protobuf.descriptor import FieldDescriptor
from reference import RefConfig

import tamrm
import tamrm.aio
from tamrm._proto.tamrm.v1 import shaping_pb2
from tamrm._types import config_to_pb

PROTO_FIELDS = [f.name for f in shaping_pb2.TaskConfig.DESCRIPTOR.fields]
# The Python annotation each proto scalar type maps to.
PY_TYPES = {
    FieldDescriptor.TYPE_UINT32: int,
    FieldDescriptor.TYPE_DOUBLE: float,
    FieldDescriptor.TYPE_BOOL: bool,
}
DOCS = Path(__file__).resolve().parents[3] / "docs" / "python.md"


def test_proto_has_the_fields_we_know_of() -> None:
    # The comparison below is not vacuous.
    assert len(PROTO_FIELDS) >= 12
    assert "gate_potential" in PROTO_FIELDS
    assert "require_score_spread" in PROTO_FIELDS


def test_config_fields_constant() -> None:
    assert list(tamrm.CONFIG_FIELDS) == PROTO_FIELDS


def test_task_options_have_every_field() -> None:
    assert list(tamrm.TaskOptions.__annotations__) == PROTO_FIELDS
    hints = typing.get_type_hints(tamrm.TaskOptions)
    for field in shaping_pb2.TaskConfig.DESCRIPTOR.fields:
        assert hints[field.name] == PY_TYPES[field.type] | None, field.name
    assert tamrm.TaskOptions.__required_keys__ == frozenset()


@pytest.mark.parametrize("cls", [tamrm.Client, tamrm.aio.Client], ids=["sync", "aio"])
def test_create_task_takes_task_options(cls: type) -> None:
    params = list(inspect.signature(cls.create_task).parameters.values())
    # timeout= is the call's deadline, keyword-only: it can never be a TaskConfig field.
    assert [p.name for p in params] == ["self", "task_id", "timeout", "config"]
    assert params[2].kind is inspect.Parameter.KEYWORD_ONLY
    assert "timeout" not in PROTO_FIELDS
    assert params[3].kind is inspect.Parameter.VAR_KEYWORD
    assert params[3].annotation == "Unpack[TaskOptions]"


def test_create_task_rejects_unknown_keywords(client: tamrm.Client) -> None:
    with pytest.raises(TypeError, match="no_such_field"):
        client.create_task("t/unknown-keyword", num_actions=2, no_such_field=1)  # type: ignore[call-arg]


def test_task_config_dataclass_has_every_field() -> None:
    fields = dataclasses.fields(tamrm.TaskConfig)
    assert [f.name for f in fields] == PROTO_FIELDS
    hints = typing.get_type_hints(tamrm.TaskConfig)
    for field in shaping_pb2.TaskConfig.DESCRIPTOR.fields:
        assert hints[field.name] is PY_TYPES[field.type], field.name


def _sample(field: FieldDescriptor) -> object:
    return {int: 7, float: 0.25, bool: True}[PY_TYPES[field.type]]


def test_every_field_is_sent_and_read_back() -> None:
    """config_to_pb sets every field; TaskConfig._from_pb reads every field."""
    values = {f.name: _sample(f) for f in shaping_pb2.TaskConfig.DESCRIPTOR.fields}
    msg = config_to_pb(values)
    for name, value in values.items():
        assert getattr(msg, name) == value, name
    config = tamrm.TaskConfig._from_pb(msg)
    assert dataclasses.asdict(config) == values


BOOL_FIELDS = [f.name for f in shaping_pb2.TaskConfig.DESCRIPTOR.fields if f.type == f.TYPE_BOOL]


def test_the_bool_fields_are_the_ones_added_since_the_first_release() -> None:
    assert BOOL_FIELDS == ["gate_potential", "require_score_spread"]


@pytest.mark.parametrize("name", BOOL_FIELDS)
def test_bool_fields_round_trip(client: tamrm.Client, task_id: str, name: str) -> None:
    """A switch added after the first release (SPEC v1.1, v1.3): False unless sent, kept,
    part of the resolved config (idempotent create, a different value conflicts)."""
    plain = client.create_task(task_id + "-plain", num_actions=2)
    assert getattr(plain.config, name) is False
    on = client.create_task(task_id, num_actions=2, **{name: True})
    assert getattr(on.config, name) is True
    assert getattr(client.get_task(task_id).config, name) is True
    assert client.create_task(task_id, num_actions=2, **{name: True}) == on
    with pytest.raises(tamrm.AlreadyExists, match=name):
        client.create_task(task_id, num_actions=2, **{name: False})
    # Explicit False is the default.
    again = client.create_task(task_id + "-plain", num_actions=2, **{name: False})
    assert again == plain


@pytest.mark.parametrize("name", BOOL_FIELDS)
def test_bool_fields_are_type_checked(client: tamrm.Client, task_id: str, name: str) -> None:
    with pytest.raises(TypeError, match=name):
        client.create_task(task_id, num_actions=2, **{name: 1})  # type: ignore[arg-type]


def test_reference_config_has_every_field() -> None:
    assert list(RefConfig.__dataclass_fields__) == PROTO_FIELDS


def test_docs_list_every_field() -> None:
    text = DOCS.read_text(encoding="utf-8")
    line = next(ln for ln in text.splitlines() if ln.startswith("| `create_task("))
    for name in PROTO_FIELDS:
        assert f"{name}=" in line, name
