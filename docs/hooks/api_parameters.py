"""griffe extension for the API reference: every public function and class whose docstring has no parameter
section gets one from its signature (name, annotation, default), so mkdocstrings renders it as a table; a
dataclass field's trailing comment is its parameter's description."""
from __future__ import annotations

import re

import griffe

COMMENT = re.compile(r"#\s*(.+?)\s*$")


class SignatureParameters(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        """Once the package is loaded; griffe's dataclasses extension (run after this one) first, for the fields."""
        griffe.DataclassesExtension().on_package(pkg=pkg, **kwargs)
        _walk(pkg)


def _walk(obj) -> None:
    for member in obj.members.values():
        if member.is_alias:
            continue
        if member.is_function or member.is_class:
            _add(member, member.parameters)
        if member.is_class or member.is_module:
            _walk(member)


def _comment(obj, name: str) -> str:
    """The trailing comment of attribute `name`'s line in class `obj` ('' for a function or no comment)."""
    member = obj.members.get(name) if isinstance(obj, griffe.Class) else None
    if member is None or member.is_alias or not member.is_attribute or not member.lineno:
        return ""
    found = COMMENT.search(obj.lines_collection[member.filepath][member.lineno - 1])
    return found.group(1).replace("`", "'") if found else ""


def _add(obj, parameters) -> None:
    if obj.name.startswith("_") or obj.docstring is None or "Args:" in obj.docstring.value:
        return
    rows = [p for p in parameters if p.name not in ("self", "cls") and p.kind.value not in
            ("variadic positional", "variadic keyword")]
    if rows:
        lines = [f"    {p.name}: {_comment(obj, p.name)}" for p in rows]
        obj.docstring.value = obj.docstring.value.rstrip() + "\n\nArgs:\n" + "\n".join(lines)
