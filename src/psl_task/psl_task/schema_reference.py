"""The task file's reference (docs/task_reference.md), generated from its schema so that it
cannot drift from it.

One table per section of a task YAML (`psl_task.schema`), in the order a reader meets them:
each key with its type, its default (or "required"), the values or the range the schema
accepts, and its description. Everything comes from the classes through pydantic: the JSON
schema gives a key's type, its allowed values and range and its description (the docstring
under the key); the classes give the defaults (a factory's value and an infinity, which a JSON
schema leaves out or cannot spell, stay as they are). The kinds of ``task_parameters[].binds``
come from the registry `psl_task.bindings.BINDINGS`, each with its keys. What sections hold
together (a posture's length against the joints, ...) is checked where the task is built
(`psl_task.task`) and is not listed.

    python -m psl_task.schema_reference > docs/task_reference.md

``test_schema_reference`` holds the committed file to this output. Imports no ROS.
"""
from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from typing import Annotated, Any

import yaml
from pydantic import BaseModel, TypeAdapter
from pydantic.json_schema import GenerateJsonSchema, JsonSchemaValue
from pydantic_core import core_schema

from psl_task.bindings import BINDINGS, Binding
from psl_task.schema import TaskFile, TaskParameterEntry

COMMAND = 'python -m psl_task.schema_reference > docs/task_reference.md'
BINDS = (TaskParameterEntry, 'binds')   # the key whose mapping a binding kind validates
REQUIRED = 'required'                   # the default cell of a key the file must give


@dataclasses.dataclass(frozen=True)
class Section:
    """A section of the YAML: where it is (``robot.end_effector``, ``scene[]`` for each entry
    of a list, '' for the top level) and the class that validates it."""

    path: str
    kind: type


@dataclasses.dataclass(frozen=True)
class Key:
    """One key of a section, as the reference shows it."""

    name: str
    required: bool
    default: Any            # the value when not given (None when required)
    schema: dict            # the key's JSON schema (pydantic's, defaults left out)


class _ReferenceSchema(GenerateJsonSchema):
    """pydantic's JSON schema with two changes for the reference: defaults are left out (they
    are taken from the classes, where a factory's value and inf stay as they are), and a float
    that must be finite says so (``finite: true``, which JSON schema has no word for)."""

    def default_schema(self, schema: core_schema.WithDefaultSchema) -> JsonSchemaValue:
        return self.generate_inner(schema['schema'])

    def float_schema(self, schema: core_schema.FloatSchema) -> JsonSchemaValue:
        json_schema = super().float_schema(schema)
        if schema.get('allow_inf_nan') is False:
            json_schema['finite'] = True
        return json_schema


def json_schema(kind: type) -> dict:
    """The JSON schema of a section's class, as the reference reads it."""
    return TypeAdapter(kind).json_schema(schema_generator=_ReferenceSchema)


def sections(root: type = TaskFile, path: str = '') -> list[Section]:
    """`root` and every section under it, depth-first in the order of the keys: a key whose
    type is a model or a dataclass (also as X | None or as a list's entry) is a section."""
    found = [Section(path, root)]
    for name, annotation in typing.get_type_hints(root, include_extras=True).items():
        if name not in _field_names(root):
            continue
        kind, listed = _section_class(annotation)
        if kind is not None:
            child = f'{path}.{name}' if path else name
            found += sections(kind, child + ('[]' if listed else ''))
    return found


def keys(kind: type) -> list[Key]:
    """The keys of a section's (or a binding kind's) class, in declaration order."""
    properties = json_schema(kind)['properties']
    out = []
    if isinstance(kind, type) and issubclass(kind, BaseModel):
        for name, field in kind.model_fields.items():
            required = field.is_required()
            out.append(Key(name, required,
                           None if required else field.get_default(call_default_factory=True),
                           properties[name]))
    else:
        for field in dataclasses.fields(kind):
            if field.default is not dataclasses.MISSING:
                required, default = False, field.default
            elif field.default_factory is not dataclasses.MISSING:
                required, default = False, field.default_factory()
            else:
                required, default = True, None
            out.append(Key(field.name, required, default, properties[field.name]))
    return out


def markdown() -> str:
    """The reference: a table per section, the binding kinds after ``task_parameters[]``."""
    found = sections()
    links = {s.kind.__name__: f'[`{s.path or "top level"}`](#{_anchor(_heading(s))})'
             for s in found}
    at = [s.kind for s in found].index(BINDS[0])
    binds = f'{found[at].path}.{BINDS[1]}'
    contents = [links[s.kind.__name__] for s in found]
    contents.insert(at + 1, f'[`{binds}`](#{_anchor(_binds_heading(binds))})')
    lines = [f'<!-- Generated by `{COMMAND}` from src/psl_task/psl_task/schema.py and '
             'bindings.py: do not edit by hand. -->',
             '# Task file reference',
             '',
             'Every key of a task YAML, section by section: its type, its default ("required": '
             'the file must give it), the values or the range the schema accepts, and what it '
             'means. A key no section knows is refused, naming the nearest valid one. What the '
             'sections must agree on (a posture\'s length against the driven joints, the '
             'demonstration against the duration, ...) is checked when the task is loaded '
             '(`psl check --task T`, and `psl up` before it starts). The sections explained, '
             'with examples: [tasks.md](tasks.md).',
             '',
             f'Generated from the schema (`psl_task.schema`, `psl_task.bindings`) by `{COMMAND}`;'
             ' `src/psl_task/test/test_schema_reference.py` fails when this file is out of date.',
             '',
             'Sections: ' + ', '.join(contents) + '.',
             '']
    for section in found:
        lines += _section(section, links, binds)
        if section.kind is BINDS[0]:
            lines += _binding_kinds(binds)
    return '\n'.join(lines)


def _section(section: Section, links: dict[str, str], binds: str) -> list[str]:
    schema = json_schema(section.kind)
    lines = [f'## {_heading(section)}', '', _oneline(schema.get('description', '')), '']
    rows = []
    for key in keys(section.kind):
        kind = (f'mapping: a [binding kind](#{_anchor(_binds_heading(binds))})'
                if (section.kind, key.name) == BINDS else _type(key.schema, links))
        rows.append(_row(key, kind))
    return lines + _table(rows)


def _binding_kinds(binds: str) -> list[str]:
    """The binding kinds of the registry, a table each; `binds` is where they go in the YAML."""
    flags = sorted(name for name in Binding.__class_vars__ if name != 'kind')
    lines = [f'## {_binds_heading(binds)}', '',
             f'A task parameter\'s `binds` names its `kind`, one of the registry '
             f'`psl_task.bindings.BINDINGS` ({", ".join(f"`{k}`" for k in BINDINGS)}), and the '
             'keys of that kind; the value applied is the task parameter\'s value plus `offset`. '
             f'Each kind\'s flags ({", ".join(f"`{f}`" for f in flags)}) are explained in '
             '`psl_task.bindings.Binding`.', '']
    for name, kind in BINDINGS.items():
        schema = json_schema(kind)
        doc = _oneline(schema.get('description', ''))
        lines += [f'### `kind: {name}` ({kind.__name__})', '', doc, '',
                  'Flags: ' + ', '.join(f'`{f}` {_yaml(getattr(kind, f))}' for f in flags) + '.',
                  '']
        rows = [['`kind`', 'string', REQUIRED, f'`{name}`', 'Selects this kind.']]
        rows += [_row(key, _type(key.schema, {})) for key in keys(kind)]
        lines += _table(rows)
    return lines


def _row(key: Key, kind: str) -> list[str]:
    return [f'`{key.name}`', kind, REQUIRED if key.required else f'`{_yaml(key.default)}`',
            _allowed(key.schema), _oneline(key.schema.get('description', ''))]


def _table(rows: list[list[str]]) -> list[str]:
    lines = ['| key | type | default | allowed | description |', '|---|---|---|---|---|']
    lines += ['| ' + ' | '.join(cell.replace('|', '\\|') for cell in row) + ' |'
              for row in rows]
    return lines + ['']


def _heading(section: Section) -> str:
    where = f'`{section.path}`' if section.path else 'Top level'
    return f'{where} ({section.kind.__name__})'


def _binds_heading(binds: str) -> str:
    return f'`{binds}`: binding kinds'


def _anchor(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r'[^a-z0-9 _-]', '', heading.lower()).replace(' ', '-')


def _oneline(text: str) -> str:
    return ' '.join(text.split())


def _type(schema: dict, links: dict[str, str]) -> str:
    """A key's type in words, from its JSON schema."""
    if '$ref' in schema:
        return f'mapping ({links[schema["$ref"].rsplit("/", 1)[-1]]})'
    if 'anyOf' in schema:
        return ' or '.join(_type(option, links) for option in schema['anyOf'])
    kind = schema.get('type')
    if kind == 'array':
        if 'prefixItems' in schema:
            return '[' + ', '.join(_type(item, links) for item in schema['prefixItems']) + ']'
        items = _plural(_type(schema.get('items', {}), links))
        count = schema.get('minItems')
        return f'{count} {items}' if count is not None and count == schema.get('maxItems') \
            else f'list of {items}'
    if kind == 'object':
        values = schema.get('additionalProperties')
        return f'mapping of string to {_type(values, links)}' if isinstance(values, dict) \
            else 'mapping'
    return kind if isinstance(kind, str) else 'any'


def _plural(kind: str) -> str:
    if kind in ('number', 'integer', 'string', 'boolean'):
        return kind + 's'
    if kind.startswith(('list ', 'mapping')):
        return kind.replace('list', 'lists', 1) if kind.startswith('list ') \
            else kind.replace('mapping', 'mappings', 1)
    return kind


def _allowed(schema: dict) -> str:
    """The values or the range a key's JSON schema accepts, in words ('' for any)."""
    parts = []
    if 'enum' in schema:
        parts.append(', '.join(f'`{_yaml(value)}`' for value in schema['enum']))
    if 'const' in schema:
        parts.append(f'`{_yaml(schema["const"])}`')
    for bound, sign in (('exclusiveMinimum', '>'), ('minimum', '>='),
                        ('exclusiveMaximum', '<'), ('maximum', '<=')):
        if bound in schema:
            parts.append(f'{sign} {schema[bound]:g}')
    if schema.get('finite'):
        parts.append('finite')
    for option in schema.get('anyOf', []):
        parts.append(_allowed(option))
    for inner, what in (('items', 'each'), ('additionalProperties', 'each value')):
        allowed = _allowed(schema[inner]) if isinstance(schema.get(inner), dict) else ''
        if allowed:    # a list of lists: "each finite", not "each each finite"
            parts.append(allowed if allowed.startswith('each ') else f'{what} {allowed}')
    return ', '.join(part for part in parts if part)


def _yaml(value: Any) -> str:
    """A default as it would be written in the YAML (flow style): reading it back gives the
    value (inf as .inf, None as null, a section at its defaults as {})."""
    if value is None:
        return 'null'
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, float) and not math.isfinite(value):
        return '.nan' if math.isnan(value) else ('.inf' if value > 0 else '-.inf')
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return value if value and yaml.safe_load(value) == value else repr(value)
    if hasattr(value, 'tolist'):
        return _yaml(value.tolist())
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_yaml(item) for item in value) + ']'
    if isinstance(value, dict):
        return '{' + ', '.join(f'{_yaml(k)}: {_yaml(v)}' for k, v in value.items()) + '}'
    if dataclasses.is_dataclass(value) or isinstance(value, BaseModel):
        return _yaml({key.name: getattr(value, key.name) for key in keys(type(value))
                      if key.required or not _same(getattr(value, key.name), key.default)})
    raise TypeError(f'no YAML form for the default {value!r}')


def _same(a: Any, b: Any) -> bool:
    return _yaml(a) == _yaml(b)


def _field_names(kind: type) -> list[str]:
    if isinstance(kind, type) and issubclass(kind, BaseModel):
        return list(kind.model_fields)
    return [field.name for field in dataclasses.fields(kind)]


def _section_class(annotation: Any) -> tuple[type | None, bool]:
    """The model or dataclass an annotation holds (through Annotated, X | None and list[X]),
    and whether as a list's entries; (None, False) for any other type."""
    listed = False
    while True:
        origin, args = typing.get_origin(annotation), typing.get_args(annotation)
        if origin is Annotated:
            annotation = args[0]
        elif origin in (typing.Union, types.UnionType) and len(
                [a for a in args if a is not type(None)]) == 1:
            annotation = next(a for a in args if a is not type(None))
        elif origin is list and len(args) == 1 and not listed:
            annotation, listed = args[0], True
        else:
            break
    is_section = isinstance(annotation, type) and (
        issubclass(annotation, BaseModel) or dataclasses.is_dataclass(annotation))
    return (annotation, listed) if is_section else (None, False)


if __name__ == '__main__':
    print(markdown(), end='')
