"""wiredsl: Monte-Carlo simulation of wire-frame worlds seen by a stereo robot, without rendering.

Stages, one module each: parse (lark tree) -> ast (spans) -> compile (Scene)
-> simulate (numpy) -> emit (JSON, SVG).
"""

__version__ = "0.1.0"
