"""Sphinx configuration of the mems-stereo API reference (autodoc + napoleon, numpy style).

Build: ``python -m sphinx -W --keep-going -b html docs/api build/api``.  The pages
list the public names through two small directives defined here, so that the
reference follows the packages' exports instead of a hand-kept list:

* ``.. public-names:: PACKAGE`` documents every name in ``PACKAGE.__all__``
  (functions, classes with their public members, data);
* ``.. public-modules:: PACKAGE`` documents every public (no leading
  underscore) module of ``PACKAGE`` with ``automodule`` and its public members.

The package is imported as installed (``pip install -e ".[dev]"``, scripts/setup.sh):
``mems_stereo.calib`` and ``mems_stereo.viz`` live in the top-level folders
``calib/`` and ``viz/`` and exist only through the install's package mapping.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import sys

from docutils import nodes
from docutils.parsers.rst import directives
from docutils.statemachine import StringList
from sphinx.pycode import ModuleAnalyzer
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective
from sphinx.util.nodes import nested_parse_with_titles

logger = logging.getLogger(__name__)

os.environ.setdefault("MPLBACKEND", "Agg")

project = "mems-stereo"
author = "mems-stereo authors"
copyright = "mems-stereo authors"
release = importlib.import_module("mems_stereo").__version__
version = release

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon"]
exclude_patterns = ["_build"]
html_theme = "alabaster"
html_static_path: list[str] = []

autodoc_member_order = "bysource"
autodoc_typehints = "signature"
autodoc_inherit_docstrings = False
autodoc_default_options = {"show-inheritance": False}
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_ivar = True
napoleon_use_rtype = False


def _lines(directive: str, target: str, options: tuple[str, ...] = ()) -> list[str]:
    return [f".. {directive}:: {target}", *(f"   :{o}:" for o in options), ""]


def _data_lines(target: str, obj, options: tuple[str, ...]) -> list[str]:
    """A module-level constant: its ``#:`` comment where it is assigned, else its type
    (``autodata`` would show the docstring of ``dict`` or ``tuple`` for a constant
    that a package imports from elsewhere)."""
    name = target.rsplit(".", 1)[1]
    for modname, module in sorted(sys.modules.items()):
        if not modname.startswith("mems_stereo") or vars(module).get(name) is not obj:
            continue
        try:
            docs = ModuleAnalyzer.for_module(modname).find_attr_docs()
        except Exception:  # no source (compiled, namespace): look further
            continue
        if ("", name) in docs:
            return [f".. py:data:: {target}", *(f"   :{o}:" for o in options), "",
                    *(f"   {line}" for line in docs["", name]), ""]
    keys = f": {', '.join(map(repr, sorted(obj)))}" if isinstance(obj, dict) else ""
    return [f".. py:data:: {target}", *(f"   :{o}:" for o in options), "",
            f"   A ``{type(obj).__name__}``{keys}.", ""]


class PublicNames(SphinxDirective):
    """Document every name in ``PACKAGE.__all__``.

    ``:exclude:`` drops names; ``:no-index:`` documents them without making them
    cross-reference targets (for a page that repeats names documented
    elsewhere); ``:index-own:`` indexes only the names defined inside
    ``PACKAGE`` (re-exported names are indexed on their own module's page).
    """

    required_arguments = 1
    option_spec = {"exclude": directives.unchanged, "no-index": directives.flag,
                   "index-own": directives.flag}

    def run(self):
        modname = self.arguments[0]
        module = importlib.import_module(modname)
        skip = set((self.options.get("exclude") or "").split())
        out: list[str] = []
        for name in getattr(module, "__all__", []):
            if name.startswith("_") or name in skip:
                continue
            try:
                obj = getattr(module, name)
            except Exception as exc:  # a broken lazy import: a warning, not a crash
                logger.warning("public-names: %s.%s cannot be imported: %s", modname, name, exc,
                               location=self.get_location())
                continue
            if inspect.ismodule(obj):
                continue
            own = getattr(obj, "__module__", modname).startswith(modname)
            no_index = "no-index" in self.options or ("index-own" in self.options and not own)
            options = ("no-index",) if no_index else ()
            target = f"{modname}.{name}"
            if inspect.isclass(obj):
                out += _lines("autoclass", target, ("members", *options))
            elif callable(obj):
                out += _lines("autofunction", target, options)
            else:
                out += _data_lines(target, obj, options)
        return self.parse_lines(out)

    def parse_lines(self, lines: list[str]):
        node = nodes.section()
        node.document = self.state.document
        nested_parse_with_titles(self.state, StringList(lines, source=self.get_source_info()[0]),
                                 node)
        return node.children


class PublicModules(PublicNames):
    """Document every public module of a package with ``automodule``: the
    public names each module defines (not the ones it imports)."""

    option_spec = {"exclude": directives.unchanged}

    def run(self):
        pkgname = self.arguments[0]
        package = importlib.import_module(pkgname)
        skip = set((self.options.get("exclude") or "").split())
        out: list[str] = []
        for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
            if info.name.startswith("_") or info.name in skip:
                continue
            target = f"{pkgname}.{info.name}"
            out += [target, "-" * len(target), ""]
            out += _lines("automodule", target, ("members", "ignore-module-all"))
        return self.parse_lines(out)


def setup(app):
    app.add_directive("public-names", PublicNames)
    app.add_directive("public-modules", PublicModules)
    return {"parallel_read_safe": True}
