"""MkDocs hook: the generated reference blocks (`<!-- generated: NAME -->`) filled from the code's own tables."""

from wiredsl import docgen


def on_page_markdown(markdown, **kwargs):
    return docgen.expand(markdown)
