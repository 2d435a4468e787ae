"""Griffe extension for the API reference (mkdocs.yml): how the package's source is read for the pages.

1. The top-level ``kernels/`` folder is documented as ``neurogf_warp.kernels``. pyproject's ``package-dir``
   installs it as that subpackage, but griffe reads packages from the source tree and would not find it; this
   loads ``kernels`` beside ``neurogf_warp`` and attaches it as the member ``kernels``.
2. Parameter entries written as ``name : description`` (the description on the type's line, a numpydoc variant the
   package uses for short entries) are rendered as descriptions, not as types. An entry counts as such when the
   text after the colon is more than a few words, or when its indented text continues that line (starts in lower
   case) instead of starting a sentence of its own. The type then comes from the signature's annotation.
3. Sphinx roles in docstrings (``:class:`Conditioned```, ``:meth:`~x.y```) render as code, the way the rest of the
   docstrings mark names.
"""
from __future__ import annotations

import re

import griffe

PARAMETER_SECTIONS = {griffe.DocstringSectionKind.parameters, griffe.DocstringSectionKind.other_parameters}


TYPE_WORDS = 4  # "int or (3,) float" is a type; "model file to write (e.g. ...)" is not


def _is_description(first_line: str, rest: str) -> bool:
    rest = rest.lstrip()
    return len(first_line.split()) > TYPE_WORDS or (bool(rest) and rest[0].islower())


def _reword_parameters(obj) -> None:
    if obj.docstring is None:
        return
    signature = getattr(obj, "parameters", None)
    for section in obj.docstring.parsed:
        if section.kind not in PARAMETER_SECTIONS:
            continue
        for p in section.value:
            if p.annotation is None:
                continue
            first = str(p.annotation)
            if not _is_description(first, p.description or ""):
                continue
            p.description = f"{first} {p.description}".strip() if p.description else first
            name = p.name.lstrip("*")
            p.annotation = signature[name].annotation if signature is not None and name in signature else None


SPHINX_ROLE = re.compile(r":(?:py:)?(?:meth|class|func|attr|mod|data|exc|obj|const):`~?([^`]+)`")


def _plain_roles(obj) -> None:
    if obj.docstring is not None and ":`" in obj.docstring.value:
        obj.docstring.value = SPHINX_ROLE.sub(r"``\1``", obj.docstring.value)


def _walk(obj, seen) -> None:
    if id(obj) in seen:
        return
    seen.add(id(obj))
    _plain_roles(obj)
    for member in list(obj.members.values()):
        if member.is_alias:
            continue
        _plain_roles(member)
        if member.is_function or member.is_class:
            _reword_parameters(member)
        if member.is_module or member.is_class:
            _walk(member, seen)


class KernelsSubpackage(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs) -> None:
        if pkg.name != "neurogf_warp":
            return
        if "kernels" not in pkg.members:
            kernels = loader.load("kernels", try_relative_path=False)
            # the same module object, now reached (and named) as neurogf_warp.kernels
            pkg.set_member("kernels", kernels)
        _walk(pkg, set())
