"""griffe extension for the API reference: every public function and class whose docstring has no parameter
section gets one from its signature (name, annotation, default), so mkdocstrings renders it as a table."""
from __future__ import annotations

import griffe


class SignatureParameters(griffe.Extension):
    def on_function_instance(self, *, func: griffe.Function, **kwargs) -> None:
        _add(func, func.parameters)

    def on_class_members(self, *, cls: griffe.Class, **kwargs) -> None:
        _add(cls, cls.parameters)


def _add(obj, parameters) -> None:
    if obj.name.startswith("_") or obj.docstring is None or "Args:" in obj.docstring.value:
        return
    rows = [p for p in parameters if p.name not in ("self", "cls") and p.kind.value not in
            ("variadic positional", "variadic keyword")]
    if rows:
        lines = [f"    {p.name}: " for p in rows]
        obj.docstring.value = obj.docstring.value.rstrip() + "\n\nArgs:\n" + "\n".join(lines)
