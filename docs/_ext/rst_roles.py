"""Griffe extension for the docs build: Sphinx roles in docstrings become cross-references.

diffkin's docstrings are Google style but refer to other objects with Sphinx roles (``:func:`solve```,
``:class:`~diffkin.chain.DHChain```, ``:mod:`.error_models```). Markdown would print those literally; this
extension rewrites each role, once the package is loaded, into an *optional* mkdocs-autorefs reference:
a link where the target is documented on the site, plain code where it is not (private helpers, peers'
classes), never a build warning. Names are resolved the way Sphinx does: as written, then relative to the
class, module and package of the docstring's owner.

Loaded from mkdocs.yml (``extensions: [docs/_ext/rst_roles.py:RstRoles]``); not part of the library.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(func|class|mod|meth|attr|data|exc|obj|const):`(~?)([^`<>]+?)`")


def _exists(collection: Any, path: str) -> bool:
    try:
        collection[path]
    except Exception:  # KeyError, AliasResolutionError, ...: not an object griffe knows
        return False
    return True


def _candidates(obj: griffe.Object, target: str) -> list[str]:
    module = obj if obj.is_module else obj.module
    package = module.path.rsplit(".", 1)[0] if "." in module.path else module.path
    if target.startswith("."):
        rel = target.lstrip(".")
        return [f"{module.path}.{rel}", f"{package}.{rel}"]
    scopes = []
    if obj.is_class:
        scopes.append(obj.path)
    elif obj.parent is not None and obj.parent.is_class:
        scopes.append(obj.parent.path)
    scopes += [module.path, package, module.path.split(".")[0]]
    return [target] + [f"{scope}.{target}" for scope in scopes]


def _rewrite(obj: griffe.Object, collection: Any, text: str) -> str:
    def replace(match: re.Match) -> str:
        tilde, target = match.group(2), match.group(3).strip()
        shown = target.lstrip(".")
        if tilde:
            shown = shown.rsplit(".", 1)[-1]
        if match.group(1) in ("func", "meth"):
            shown += "()"
        code = f"<code>{html.escape(shown)}</code>"
        for path in _candidates(obj, target):
            if _exists(collection, path):
                return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'
        return code

    return _ROLE.sub(replace, text)


class RstRoles(griffe.Extension):
    """Rewrite Sphinx roles in every docstring of a loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        collection = loader.modules_collection
        stack: list[griffe.Object] = [pkg]
        seen: set[int] = set()
        while stack:
            obj = stack.pop()
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            if obj.docstring is not None and ":" in obj.docstring.value:
                obj.docstring.value = _rewrite(obj, collection, obj.docstring.value)
            stack.extend(m for m in obj.members.values() if not m.is_alias)

    # griffe 1.x names the same event ``on_package_loaded``; the rewrite is idempotent if both fire.
    on_package_loaded = on_package
