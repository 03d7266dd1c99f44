"""Panda MJCF assets: compose the arm with a swappable tool and optional scene objects (no downloads)."""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from pathlib import Path

from a3cqp_rl.robot.exceptions import MjcfError, UnknownToolError

__all__ = ["ASSETS_DIR", "PANDA_XML", "TOOLS", "DEFAULT_TOOL", "compose_mjcf", "mjcf_file", "table_xml"]

ASSETS_DIR = Path(__file__).resolve().parent / "assets"
PANDA_XML = ASSETS_DIR / "panda.xml"
"""The arm with the default tool (peg) inline; a complete, loadable MJCF file."""
TOOLS = ("peg", "disc", "none", "peg_mesh", "disc_mesh")
"""Tool names; each has assets/tool_<name>.xml (a single <body name="tool"> with a site "tcp", optionally preceded by
an <asset> block, e.g. a collision mesh, which compose_mjcf moves to the model's top level). "peg_mesh" and
"disc_mesh" are "peg" and "disc" colliding as 32-sided prisms (the Panda scenes use them: see their files)."""
DEFAULT_TOOL = "peg"

_TOOL_MARKERS = ("<!-- TOOL BEGIN -->", "<!-- TOOL END -->")
_SCENE_MARKERS = ("<!-- SCENE BEGIN -->", "<!-- SCENE END -->")


def _replace_between(text: str, markers: tuple[str, str], body: str) -> str:
    """Replace what lies between two marker comments (markers kept)."""
    start, end = text.find(markers[0]), text.find(markers[1])
    if start < 0 or end < start:
        raise MjcfError(f"marker {markers} not found in {PANDA_XML}")
    return text[: start + len(markers[0])] + "\n" + body + "\n" + text[end:]


def table_xml(height: float = 0.3, size: tuple[float, float] = (0.3, 0.3), center: tuple[float, float] = (0.45, 0.0),
              thickness: float = 0.04, name: str = "table") -> str:
    """A fixed box whose top face is at `height` [m] (world z), for contact tests and scenes."""
    return (f'<body name="{name}" pos="{center[0]} {center[1]} {height - thickness / 2}">'
            f'<geom name="{name}" type="box" size="{size[0]} {size[1]} {thickness / 2}" contype="1" conaffinity="2" '
            f'rgba="0.6 0.45 0.3 1" solref="0.005 1" friction="0.4 0.005 0.0001"/></body>')


def _split_assets(text: str) -> tuple[str, str]:
    """(the <asset> blocks' contents, the text without them): assets are only valid at the model's top level."""
    assets = re.findall(r"<asset>(.*?)</asset>", text, flags=re.S)
    return "\n".join(assets), re.sub(r"<asset>.*?</asset>", "", text, flags=re.S)


_TOP_LEVEL = re.compile(r"<option\b[^>]*/>|<contact>.*?</contact>", flags=re.S)


def _split_top_level(text: str) -> tuple[str, str]:
    """(the `<option .../>` and `<contact>` elements of a scene, the text without them): both are only valid at the
    model's top level (MuJoCo merges a second `<option>` into the first)."""
    return "\n".join(_TOP_LEVEL.findall(text)), _TOP_LEVEL.sub("", text)


def compose_mjcf(tool: str = DEFAULT_TOOL, scene: str = "") -> str:
    """The Panda MJCF text with `tool` mounted below the F/T sensor and `scene` (MJCF bodies) in the worldbody.

    <asset> blocks in the tool file or the scene text, and the scene's <option .../> and <contact> elements, are moved
    to the model's top level."""
    if tool not in TOOLS:
        raise UnknownToolError(f"unknown tool {tool!r}; known tools: {TOOLS}")
    text = PANDA_XML.read_text()
    tool_assets, tool_body = _split_assets((ASSETS_DIR / f"tool_{tool}.xml").read_text())
    scene_assets, scene = _split_assets(scene)
    scene_top, scene = _split_top_level(scene)
    text = _replace_between(text, _TOOL_MARKERS, tool_body)
    text = _replace_between(text, _SCENE_MARKERS, scene)
    if scene_top:
        end = text.rindex("</mujoco>")
        text = text[:end] + scene_top + "\n" + text[end:]
    assets = "\n".join(a for a in (tool_assets, scene_assets) if a.strip())
    return text.replace("<worldbody>", f"<asset>{assets}</asset>\n  <worldbody>", 1) if assets else text


def mjcf_file(tool: str = DEFAULT_TOOL, scene: str = "") -> Path:
    """Path of a loadable MJCF file for (tool, scene): the packaged file for the default, else a cached copy."""
    if tool == DEFAULT_TOOL and not scene:
        return PANDA_XML
    text = compose_mjcf(tool, scene)
    digest = hashlib.sha1(text.encode()).hexdigest()[:12]
    cache = Path(os.environ.get("A3CQP_CACHE", Path(tempfile.gettempdir()) / "a3cqp_rl")) / "mjcf"
    cache.mkdir(parents=True, exist_ok=True)
    path = cache / f"panda_{tool}_{digest}.xml"
    if not path.exists():
        tmp = path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(text)
        tmp.replace(path)  # atomic: concurrent workers never read a half-written file
    return path
