"""The documentation site's API reference: Sphinx roles in the docstrings shown as code.

A MkDocs hook (``mkdocs.yml``: ``hooks``). The docstrings are numpydoc, and some name
other objects with Sphinx roles (``:func:`flatserve.coordinates.coordinates```,
``:class:`~flatserve.Field```), which mkdocstrings leaves as text before the code:
this drops the role (and the ``~`` that shortens a name), keeping the code.
"""
from __future__ import annotations

import re

#: A role before the code it marks, as the page's HTML has it.
ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|exc|obj|const|ref):(<code>)~?")


def on_page_content(html, page, config, files):
    """MkDocs hook: the reference pages without the roles' text."""
    if page.file.src_uri.startswith("reference/"):
        return ROLE.sub(r"\1", html)
    return html
