"""A griffe extension for the API reference: mkdocstrings reads docstrings from the source,
where a Parameters section may name a block of shared keywords (``<keywords: NAME>``);
this puts the block in its place, as :func:`stepsafe.api.keywords.shared_keywords` does
at import, so that the reference shows every parameter."""

from __future__ import annotations

from typing import Any

import griffe

from stepsafe.api.keywords import expand


class SharedKeywords(griffe.Extension):
    """Expand the marker lines of each function's docstring."""

    def on_function_instance(self, *, func: griffe.Function, **kwargs: Any) -> None:
        if func.docstring is not None and "<keywords:" in func.docstring.value:
            func.docstring.value = expand(func.docstring.value)
