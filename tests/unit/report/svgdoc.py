"""Reading the report's inline SVG figures back (tests only)."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

NS = "{http://www.w3.org/2000/svg}"
_SVG = re.compile(r"<svg\b.*?</svg>", re.DOTALL)


def figures(page: str) -> list[ET.Element]:
    """Every ``<svg>`` of ``page``, parsed (raises on markup that is not well-formed)."""
    return [ET.fromstring(s) for s in _SVG.findall(page)]


def texts(svg: ET.Element) -> list[str]:
    """The text of every ``<text>`` element, in document order."""
    return ["".join(t.itertext()) for t in svg.iter(f"{NS}text")]


def title(svg: ET.Element) -> str:
    """The figure's ``<title>`` (its alt text)."""
    t = svg.find(f"{NS}title")
    return "" if t is None or t.text is None else t.text
