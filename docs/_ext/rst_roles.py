"""Griffe extension for the docs build: reStructuredText leftovers in docstrings become markdown.

The docstrings are markdown, but some cross-reference with Sphinx roles (``:func:`simulate```) and
introduce literal blocks with a trailing ``::``. Here a role becomes an autorefs link when its target
is an object the API reference documents, and inline code otherwise; ``::`` becomes ``:``.
"""

from __future__ import annotations

import importlib
import inspect
import re

import griffe

NAMESPACES = ("rigidjax", "rigidjax.kinematics", "rigidjax.elliptic", "rigidjax.solvers")
ROLE = re.compile(r":(?:py:)?(?:class|func|meth|attr|data|mod|obj|exc|const):`~?([^`]+)`")
# Public methods the API reference leaves out (mkdocs.yml's filters): simulate's per-body machinery.
HIDDEN = {"body_leaves", "leaf_rules", "replace_body_leaves"}
LITERAL = re.compile(r"(\S)::[ \t]*$", re.MULTILINE)
LONE_LITERAL = re.compile(r"^[ \t]*::[ \t]*$", re.MULTILINE)


def documented() -> set[str]:
    """The paths the API reference renders: every public name and the documented public members of
    its classes."""
    paths = set()
    for name in NAMESPACES:
        module = importlib.import_module(name)
        for export in module.__all__:
            path = f"{name}.{export}"
            paths.add(path)
            obj = getattr(module, export)
            if inspect.isclass(obj):
                for member, value in vars(obj).items():
                    if member.startswith("_") or member in HIDDEN:
                        continue
                    value = getattr(value, "__func__", value)
                    if inspect.getdoc(value) and (callable(value) or isinstance(value, property)):
                        paths.add(f"{path}.{member}")
    return paths


class RstRoles(griffe.Extension):
    def __init__(self) -> None:
        super().__init__()
        self._paths: set[str] | None = None

    def _resolve(self, target: str) -> str | None:
        if self._paths is None:
            self._paths = documented()
        candidates = [target] if target.startswith("rigidjax.") else [f"{ns}.{target}" for ns in NAMESPACES]
        return next((c for c in candidates if c in self._paths), None)

    def _convert(self, text: str) -> str:
        def link(match: re.Match) -> str:
            target = match.group(1)
            path = self._resolve(target)
            return f"[`{target}`][{path}]" if path else f"`{target}`"

        text = ROLE.sub(link, text)
        text = LONE_LITERAL.sub("", text)
        return LITERAL.sub(r"\1:", text)

    @staticmethod
    def _filled(obj) -> str:
        """The docstring with the ``{common}`` placeholder that the fits fill in at import (their
        shared arguments) filled in as Python sees it: the source's text is read statically."""
        text = obj.docstring.value
        if "{common}" not in text or obj.kind is not griffe.Kind.FUNCTION:
            return text
        module = importlib.import_module(obj.module.path)
        return inspect.getdoc(getattr(module, obj.name)) or text

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        if pkg.name != "rigidjax":
            return
        stack, seen = [pkg], set()
        while stack:
            obj = stack.pop()
            if obj.is_alias or id(obj) in seen:
                continue
            seen.add(id(obj))
            if obj.docstring is not None:
                obj.docstring.value = self._convert(self._filled(obj))
            stack.extend(obj.members.values())
