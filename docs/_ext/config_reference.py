"""Sphinx directive that tabulates a dataclass's fields from the dataclass itself.

``.. dataclass-fields:: terrashift_rl.sim.config.TerraShiftConfig`` reads the class's source with
:mod:`ast`: every field's attribute docstring (the string literal right below it, written as
a string ``Description [unit], range.``), its default from :func:`dataclasses.fields`, and the
``# --- section ---`` comment above it. Nothing is copied by hand, so the table follows the code.
"""

from __future__ import annotations

import ast
import dataclasses
import importlib
import inspect
import re
import textwrap

from docutils import nodes
from sphinx.util.docutils import SphinxDirective

_SECTION = re.compile(r"^\s*#\s*-+\s*(.+?)\s*-*\s*$")
_BRACKETS = re.compile(r"\[([^\[\]]*)\]")


@dataclasses.dataclass
class FieldDoc:
    """One dataclass field as the reference shows it."""

    name: str
    type: str
    default: str
    unit: str
    range: str
    description: str
    section: str


def split_docstring(doc: str) -> tuple[str, str, str]:
    """Splits ``"Description [unit], range."`` into (description, unit, range).

    The unit is the last bracketed group that is not an interval (it holds no comma); the range
    is what follows it. Without a unit, an interval at the end (``in [0, 1]``) or a ``one of``
    list is the range.

    Example:
        >>> split_docstring("Sphere radius [m], > 0.")
        ('Sphere radius', 'm', '> 0')
        >>> split_docstring("Clipped to [-a, a] [m], > 0.")
        ('Clipped to [-a, a]', 'm', '> 0')
        >>> split_docstring("Discount of the shaping term, in [0, 1].")
        ('Discount of the shaping term', '', '[0, 1]')
        >>> split_docstring("Shaping scale [1/m]; 0 turns it off.")
        ('Shaping scale', '1/m', 'any; 0 turns it off')
    """
    doc = " ".join(doc.split())
    units = [m for m in _BRACKETS.finditer(doc) if "," not in m.group(1)]
    if units:
        unit = units[-1]
        description = doc[: unit.start()].rstrip(" ,.")
        rest = doc[unit.end() :].strip().lstrip(",").strip().rstrip(".")
        if rest.startswith(";"):  # "[1/m]; 0 turns it off": any value, with a note
            rest = "any; " + rest[1:].strip()
        return description, unit.group(1).strip(), rest
    interval = re.search(r",?\s*in ([\[(][^\]]*\])\.?$", doc)
    if interval:
        return doc[: interval.start()].rstrip(" ,."), "", interval.group(1)
    bound = re.search(r",\s*((?:>=|<=|>|<)\s*[^,]+?)\.?$", doc)
    if bound:
        return doc[: bound.start()].rstrip(" ,."), "", bound.group(1)
    choice = re.search(r":?\s*one of (.+?)\.?$", doc)
    if choice:
        return doc[: choice.start()].rstrip(" ,.:"), "", "one of " + choice.group(1)
    return doc.rstrip("."), "", ""


def _attribute_docs(cls: type) -> dict[str, tuple[str, str]]:
    """Every field docstring written in the class body of ``cls``, with its section."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    body = ast.parse(source).body[0].body
    docs: dict[str, tuple[str, str]] = {}
    for node, after in zip(body, [*body[1:], None], strict=True):
        if not (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)):
            continue
        if (
            isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            section = ""
            for line in reversed(lines[: node.lineno - 1]):
                match = _SECTION.match(line)
                if match:
                    section = match.group(1)
                    break
            docs[node.target.id] = (after.value.value, section)
    return docs


def field_docs(cls: type) -> list[FieldDoc]:
    """Every field of dataclass ``cls`` with its docstring parts, default and section; a field
    that a base class declares has its docstring there. A field declared with
    :func:`terrashift_rl.fields.setting` shows the range it allows."""
    docs: dict[str, tuple[str, str]] = {}
    for base in reversed(cls.__mro__):  # a subclass's docstring wins
        if dataclasses.is_dataclass(base):
            docs.update(_attribute_docs(base))
    result = []
    for field in dataclasses.fields(cls):
        if field.name not in docs:
            raise ValueError(f"{cls.__name__}.{field.name} has no attribute docstring")
        doc, section = docs[field.name]
        if field.default is not dataclasses.MISSING:
            default = repr(field.default)
        elif field.default_factory is not dataclasses.MISSING:
            default = repr(field.default_factory())
        else:
            default = "(required)"
        description, unit, allowed = split_docstring(doc)
        type_name = field.type if isinstance(field.type, str) else field.type.__name__
        declared = field.metadata.get("allowed")
        if declared is not None:
            allowed = declared.text
        if field.metadata.get("null"):
            allowed = f"{allowed or 'any'}; null: {field.metadata['null']}"
        if not allowed and type_name == "bool":
            allowed = "True / False"
        elif not allowed and unit:
            allowed = "any"
        result.append(FieldDoc(field.name, type_name, default, unit, allowed, description, section))
    return result


def _paragraph(text: str, *, literal: bool = False) -> nodes.paragraph:
    """A cell's paragraph; ````code```` spans become inline literals. Built as docutils nodes,
    so the table is the same from a reStructuredText page and from a MyST Markdown page."""
    if literal:
        return nodes.paragraph("", "", nodes.literal(text, text))
    if not text:
        return nodes.paragraph("", "—")
    paragraph = nodes.paragraph()
    for index, part in enumerate(text.split("``")):
        if part:
            paragraph += nodes.literal(part, part) if index % 2 else nodes.Text(part)
    return paragraph


def _table(title: str, fields: list[FieldDoc]) -> nodes.table:
    headers = ("field", "default", "unit", "range", "meaning")
    table = nodes.table(classes=["dataclass-fields"])
    table += nodes.title(title, title)
    group = nodes.tgroup(cols=len(headers))
    table += group
    for width in (18, 10, 8, 12, 52):
        group += nodes.colspec(colwidth=width)
    head = nodes.thead()
    row = nodes.row()
    for header in headers:
        row += nodes.entry("", nodes.paragraph("", header))
    head += row
    group += head
    body = nodes.tbody()
    for field in fields:
        row = nodes.row()
        for cell in (
            _paragraph(field.name, literal=True),
            _paragraph(field.default, literal=True),
            _paragraph(field.unit),
            _paragraph(field.range),
            _paragraph(field.description),
        ):
            row += nodes.entry("", cell)
        body += row
    group += body
    return table


class DataclassFieldsDirective(SphinxDirective):
    """``.. dataclass-fields:: module.Class``: one table of fields per ``# --- section ---``."""

    required_arguments = 1
    has_content = False

    def run(self) -> list[nodes.Node]:
        module_name, _, class_name = self.arguments[0].rpartition(".")
        cls = getattr(importlib.import_module(module_name), class_name)
        self.env.note_dependency(inspect.getsourcefile(cls))
        sections: dict[str, list[FieldDoc]] = {}
        for doc in field_docs(cls):
            sections.setdefault(doc.section, []).append(doc)
        return [
            _table(section.capitalize() if section else class_name, fields)
            for section, fields in sections.items()
        ]


def setup(app):
    app.add_directive("dataclass-fields", DataclassFieldsDirective)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
