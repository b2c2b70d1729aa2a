"""A griffe extension for the API reference (`mkdocs.yml`: mkdocstrings' `extensions`).

What griffe's static analysis does not do for rbdyn_jax's docstrings and classes:

- **References to the site's pages.** A plain `docs/physics.md#anchor` in a docstring
  (readable in the source) becomes a link to that section, titled by its heading; a
  `docs/<page>.md` a link to the page. A page or anchor the site lacks makes a broken
  link, which the strict build reports.
- **Signatures of `equinox.Module`s.** An `eqx.Module` is a dataclass whose `__init__` is
  generated from its annotated fields, which griffe's dataclass support does not see (it
  looks for `@dataclass`). For a module class that writes no `__init__` of its own, one is
  built from its fields and those of its module ancestors, with the defaults of
  `eqx.field(default=...)` or of a plain assignment; `eqx.AbstractVar` declarations and
  `eqx.field(init=False)` are not parameters. With `merge_init_into_class`, the class
  heading then shows how to construct it: `RigidBody(inertia, torque=None)`.
"""

from __future__ import annotations

import functools
import pathlib
import re
from typing import Any

import griffe

_MODULE = {"equinox.Module", "equinox._module.Module"}
_FIELD = {"equinox.field", "equinox._module.field"}
_NOT_FIELDS = ("equinox.AbstractVar", "equinox.AbstractClassVar", "typing.ClassVar")
# `docs/page.md#anchor` as plain text (not the target of a Markdown link)
_PAGE = re.compile(r"(?<!\]\()(?<![/\w])docs/(?P<page>[\w/-]+\.md)(?:#(?P<anchor>[\w-]+))?")
_DOCS = pathlib.Path(__file__).resolve().parents[1]


@functools.cache
def _titles(page: str) -> dict[str, str]:
    """Anchor → heading of every heading of `docs/<page>`, and `""` → its title."""
    from markdown.extensions.toc import slugify

    titles: dict[str, str] = {}
    path = _DOCS / page
    if path.is_file():
        in_code = False
        for line in path.read_text().splitlines():
            if line.startswith(("```", "~~~")):
                in_code = not in_code
            elif line.startswith("#") and not in_code:
                title = line.lstrip("#").strip()
                titles.setdefault("", title)
                titles[slugify(title, "-")] = title
    return titles


def link_guide(text: str) -> str:
    """`text` with every plain reference to a page of the site, `docs/<page>.md` or
    `docs/<page>.md#anchor`, made a link titled by that section's heading (or the page's
    title). A page or anchor the site lacks makes a broken link, which the strict build
    reports."""

    def link(m: re.Match) -> str:
        page, anchor = m["page"], m["anchor"] or ""
        title = _titles(page).get(anchor, anchor or page)
        return f"[{title}](../{page}{'#' + anchor if anchor else ''})"

    return _PAGE.sub(link, text)


def _canonical(expr: Any) -> str:
    return getattr(expr, "canonical_path", None) or str(expr)


def _resolve(cls: griffe.Class, expr: Any) -> griffe.Class | None:
    try:
        target = cls.modules_collection[_canonical(expr)]
    except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
        return None
    while isinstance(target, griffe.Alias):
        try:
            target = target.final_target
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return None
    return target if isinstance(target, griffe.Class) else None


def _module_ancestry(cls: griffe.Class, seen: frozenset[str] = frozenset()) -> list | None:
    """The `eqx.Module` classes `cls` derives from, base first, `cls` last; `None` if it is
    not an `eqx.Module`. A base that cannot be resolved and is not `eqx.Module` is
    treated as not one."""
    if cls.path in seen:
        return None
    chain: list[griffe.Class] = []
    found = False
    for base in cls.bases:
        if _canonical(base) in _MODULE:
            found = True
            continue
        parent = _resolve(cls, base)
        if parent is None:
            continue
        parents = _module_ancestry(parent, seen | {cls.path})
        if parents is not None:
            found = True
            chain.extend(p for p in parents if p not in chain)
    return [*chain, cls] if found else None


def _field_arguments(value: Any) -> dict[str, Any] | None:
    """The keyword arguments of an `eqx.field(...)` call, else `None`."""
    if isinstance(value, griffe.ExprCall) and _canonical(value.function) in _FIELD:
        return {a.name: a.value for a in value.arguments if isinstance(a, griffe.ExprKeyword)}
    return None


def _parameters(cls: griffe.Class) -> list[griffe.Parameter]:
    params: list[griffe.Parameter] = []
    for member in cls.members.values():
        if (
            not isinstance(member, griffe.Attribute)
            or member.annotation is None
            or "property" in member.labels
        ):
            continue
        if _canonical(member.annotation).startswith(_NOT_FIELDS):
            continue
        if isinstance(member.annotation, griffe.ExprSubscript) and _canonical(
            member.annotation.left
        ).startswith(_NOT_FIELDS):
            continue
        args = _field_arguments(member.value)
        if args is not None:
            if str(args.get("init", "True")) == "False":
                continue
            if "default_factory" in args:
                default = griffe.ExprCall(function=args["default_factory"], arguments=[])
            else:
                default = args.get("default")
        else:
            default = member.value
        params.append(
            griffe.Parameter(
                member.name,
                annotation=member.annotation,
                kind=griffe.ParameterKind.positional_or_keyword,
                default=default,
            )
        )
    return params


def _set_init(cls: griffe.Class) -> None:
    if "__init__" in cls.members:
        return
    chain = _module_ancestry(cls)
    if chain is None or any(_own_init(c) for c in chain):
        return
    # As a dataclass: a field keeps the place of its first declaration (base first) and
    # takes the annotation and default of its last.
    by_name: dict[str, griffe.Parameter] = {}
    for c in chain:
        for p in _parameters(c):
            by_name[p.name] = p
    init = griffe.Function(
        "__init__",
        lineno=0,
        endlineno=0,
        parent=cls,
        parameters=griffe.Parameters(
            griffe.Parameter("self", kind=griffe.ParameterKind.positional_or_keyword),
            *by_name.values(),
        ),
        returns="None",
    )
    init.extra["rbdyn_docs"]["generated"] = True
    cls.set_member("__init__", init)


def _own_init(cls: griffe.Class) -> bool:
    """Whether `cls` writes an `__init__` (one built here does not count)."""
    init = cls.members.get("__init__")
    return init is not None and not init.extra["rbdyn_docs"].get("generated", False)


def _walk(obj: griffe.Object, seen: set[str]) -> None:
    if obj.path in seen:
        return
    seen.add(obj.path)
    if obj.docstring is not None:
        obj.docstring.value = link_guide(obj.docstring.value)
    if isinstance(obj, griffe.Class):
        _set_init(obj)
    for member in list(obj.members.values()):
        if not member.is_alias:
            _walk(member, seen)


class EquinoxDocstrings(griffe.Extension):
    """Lists separated from their labels, links to the site's pages, and `__init__`s for
    `eqx.Module`s (see above)."""

    def on_package(self, *, pkg: griffe.Module, **kwargs: Any) -> None:
        if pkg.name == "rbdyn_jax":
            _walk(pkg, set())
