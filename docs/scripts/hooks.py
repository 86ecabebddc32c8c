"""MkDocs hooks: the docstrings' Sphinx roles as links in the API reference.

The package's docstrings are numpy style, with Sphinx cross-references
(``:func:`~logsph_trace.trace```), which read well in ``help()`` and in an
editor. mkdocstrings renders them as text; this turns each into the name in
code, linked to its entry on the API page when it has one there.
"""

import re

ROLE = re.compile(r":(?:func|class|meth|attr|mod|data):<code>(~?)([\w.]+)</code>")


def on_page_content(html, page, **kwargs):
    """Replace ``:role:`target``` in a page's HTML with a link or plain code."""
    on_api_page = page.file.src_uri == "reference/api.md"
    prefix = "" if on_api_page else "../reference/api/"

    def link(match):
        short, target = match.group(1) == "~", match.group(2)
        shown = target.rsplit(".", 1)[-1] if short else target
        if not target.startswith("logsph_trace."):
            target = f"logsph_trace.{target}"
        return f'<a href="{prefix}#{target}"><code>{shown}</code></a>'

    return ROLE.sub(link, html)
