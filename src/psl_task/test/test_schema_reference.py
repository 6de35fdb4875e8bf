"""docs/task_reference.md is the schema's reference: the committed file is the generator's output,
and every key of every section (and of every binding kind) is in it with its default and a
description.

The keys are found here from the classes directly (their type hints, pydantic's model_fields,
dataclasses.fields), not through the generator's walk, so a section or a key the generator
missed fails; a default is checked by reading its cell back as YAML through the key's own type.
"""
import dataclasses
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import pytest
import yaml
from pydantic import BaseModel, ConfigDict, TypeAdapter

from psl_task import schema_reference
from psl_task.bindings import BINDINGS
from psl_task.schema import TaskFile

ROOT = Path(__file__).resolve().parents[3]
REFERENCE = ROOT / 'docs' / 'task_reference.md'
REQUIRED = object()


def _fields(kind: type) -> dict[str, tuple[Any, Any]]:
    """Key -> (annotation, default or REQUIRED) of a model or a dataclass."""
    hints = typing.get_type_hints(kind, include_extras=True)
    if issubclass(kind, BaseModel):
        return {name: (hints[name], REQUIRED if field.is_required()
                       else field.get_default(call_default_factory=True))
                for name, field in kind.model_fields.items()}
    out = {}
    for field in dataclasses.fields(kind):
        if field.default is not dataclasses.MISSING:
            default = field.default
        elif field.default_factory is not dataclasses.MISSING:
            default = field.default_factory()
        else:
            default = REQUIRED
        out[field.name] = (hints[field.name], default)
    return out


def _inner(annotation: Any) -> tuple[Any, bool]:
    """The class inside Annotated / X | None / list[X], and whether it is a list's entry."""
    listed = False
    while True:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        origin = typing.get_origin(annotation)
        if origin is Annotated or (origin in (typing.Union, types.UnionType) and len(args) == 1):
            annotation = args[0]
        elif origin is list and not listed:
            annotation, listed = args[0], True
        else:
            return annotation, listed


def _is_section(kind: Any) -> bool:
    return isinstance(kind, type) and (issubclass(kind, BaseModel)
                                       or dataclasses.is_dataclass(kind))


def schema_sections(kind: type = TaskFile, path: str = '') -> dict[str, type]:
    """Heading text -> class of every section reachable from the top level of the file."""
    out = {f'`{path}`' if path else 'Top level': kind}
    for name, (annotation, _) in _fields(kind).items():
        inner, listed = _inner(annotation)
        if _is_section(inner):
            out.update(schema_sections(inner, (f'{path}.{name}' if path else name)
                                       + ('[]' if listed else '')))
    return out


def tables(text: str) -> dict[str, dict[str, list[str]]]:
    """Heading (without the #s) -> key -> the cells of its row (type, default, allowed,
    description), for every table of the reference."""
    out, heading = {}, None
    for line in text.splitlines():
        if line.startswith('#'):
            heading = line.lstrip('#').strip()
            out[heading] = {}
        elif line.startswith('| `') and heading is not None:
            cells = [c.strip().replace('\\|', '|') for c in re.split(r'(?<!\\)\|', line)[1:-1]]
            out[heading][cells[0].strip('`')] = cells[1:]
    return out


def _table(found: dict, heading_start: str) -> dict[str, list[str]]:
    matches = [rows for heading, rows in found.items() if heading.startswith(heading_start)]
    assert len(matches) == 1, f'no section {heading_start} in {REFERENCE.name}'
    return matches[0]


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b


def _every_key() -> list[tuple[str, str, Any, Any]]:
    """(heading start, key, annotation, default) for every key of the schema."""
    out = []
    for heading, kind in schema_sections().items():
        out += [(heading + ' (', name, annotation, default)
                for name, (annotation, default) in _fields(kind).items()]
    for name, kind in BINDINGS.items():
        out += [(f'`kind: {name}`', key, annotation, default)
                for key, (annotation, default) in _fields(kind).items()]
    return out


@pytest.fixture(scope='module')
def reference() -> dict[str, dict[str, list[str]]]:
    return tables(REFERENCE.read_text())


def test_the_committed_reference_is_the_generators_output():
    assert REFERENCE.read_text() == schema_reference.markdown(), \
        f'{REFERENCE} is out of date: regenerate it with `{schema_reference.COMMAND}` ' \
        '(from the repository root, scripts/env.sh sourced)'


def test_every_section_of_the_schema_is_there(reference):
    for heading in schema_sections():
        _table(reference, heading + ' (')
    for name in BINDINGS:
        assert _table(reference, f'`kind: {name}`')['kind'][2] == f'`{name}`'


def test_every_key_is_there_with_its_default(reference):
    config = ConfigDict(arbitrary_types_allowed=True)
    keys = _every_key()
    assert len(keys) > 80
    for heading, key, annotation, default in keys:
        rows = _table(reference, heading)
        assert key in rows, f'{heading}: no row for {key!r}'
        cell = rows[key][1]
        if default is REQUIRED:
            assert cell == 'required', f'{heading} {key}: {cell}'
            continue
        assert cell.startswith('`') and cell.endswith('`'), f'{heading} {key}: {cell}'
        # the cell, written in a YAML file, gives the default
        adapter = TypeAdapter(annotation) if _is_section(_inner(annotation)[0]) \
            else TypeAdapter(annotation, config=config)   # a section has its own config
        read = adapter.validate_python(yaml.safe_load(cell.strip('`')))
        assert _same(read, default), f'{heading} {key}: {cell} reads as {read!r}, ' \
                                     f'the default is {default!r}'


def test_every_key_has_a_description(reference):
    missing = [f'{heading} {key}' for heading, key, _, _ in _every_key()
               if not _table(reference, heading)[key][3]]
    assert not missing, f'keys without a description (a docstring under the key): {missing}'
