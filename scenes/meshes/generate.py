"""Regenerate the meshes of scenes/meshes.wd with trimesh (`python scenes/meshes/generate.py`)."""

from pathlib import Path

import trimesh

here = Path(__file__).parent
crate = trimesh.creation.box(extents=(600, 400, 400))  # mm, y-up (as CAD exports often are)
crate.apply_translation((0, 200, 0))
crate.export(here / "crate.obj")
can = trimesh.creation.cylinder(radius=0.12, height=0.3, sections=48)
can.apply_translation((0, 0, 0.15))
can.export(here / "can.stl")
trimesh.creation.cone(radius=0.2, height=0.5, sections=40).export(here / "cone.ply")
ball = trimesh.creation.icosphere(subdivisions=3, radius=0.15)  # y-up, as glTF is
ball.apply_translation((0, 0.15, 0))
ball.export(here / "ball.glb")
