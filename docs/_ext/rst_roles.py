"""A griffe extension for the API reference: the identification core's docstrings are written
with reST roles (``:func:`prepare```), ``.. math::`` blocks and ``::`` literal blocks; this turns
them into what the site's Markdown renders (code spans, arithmatex display math, a plain colon)
as the docstrings are loaded, leaving the source as it is."""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const):`~?([^`]+)`")
MATH = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<first>.*)$")


def _role(match: re.Match[str]) -> str:
    target = match.group(1)
    shown = target.rsplit(".", 1)[-1] if match.group(0).count("~") else target
    return f"`{shown}`"


def _math(lines: list[str]) -> list[str]:
    """``.. math:: A`` and its indented continuation lines -> a ``$$ ... $$`` block."""
    out: list[str] = []
    k = 0
    while k < len(lines):
        m = MATH.match(lines[k])
        if not m:
            out.append(lines[k])
            k += 1
            continue
        indent = len(m.group("indent"))
        body = [m.group("first").strip()] if m.group("first").strip() else []
        k += 1
        while k < len(lines) and lines[k].strip() and len(lines[k]) - len(lines[k].lstrip()) > indent:
            body.append(lines[k].strip())
            k += 1
        out += ["", "$$", *body, "$$", ""]
    return out


def markdown_of(text: str) -> str:
    text = "\n".join(_math(ROLE.sub(_role, text).splitlines()))
    return re.sub(r"(\w)::[ \t]*$", r"\1:", text, flags=re.MULTILINE)  # "runs::" before a literal block


class RstRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = markdown_of(obj.docstring.value)
