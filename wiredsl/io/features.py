"""The feature dump (`features.json`) and the view-dependency file, as pydantic models: their schemas, and the
readers and `emit.features` that validate. A build writes its dump from arrays (io/emit.py) and does not import
this module; what it makes as models (the manifest, the scene reference) is in io/manifest.py."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_serializer

from wiredsl.io.manifest import Manifest, ManifestStage, Node, SceneRef, StageRecord  # noqa: F401 - re-exported
from wiredsl.scene import SCHEMA_VERSION, Camera, Mat34, Vec2, Vec3, omitted_when_none


class Feature(Node):
    """Common to every emitted feature: which model feature it came from."""

    source: str = Field(description="placement.feature")
    segment: int | None = Field(None, description="segment index within a polyline, silhouette side 0 or 1")
    fragment: int | None = Field(None, description="fragment index after edge loss")
    clipped: bool = Field(False, description="cut by the image border or the near plane")
    occluded: bool = Field(False, description="a visible part of a feature that occlusion cut (--visibility exact)")


def _contour_field():
    return Field(False, description="(part of) a smooth mesh surface's occluding contour in this view: "
                                    "view-dependent, not a fixed edge of the object (written only when true)")


def _omit_plain(self, handler):  # dumps of scenes without meshes stay as they were
    out = handler(self)
    if not self.contour:
        out.pop("contour", None)
    return out


class ImageLine(Feature):
    kind: Literal["line"] = "line"
    points: tuple[Vec2, Vec2]
    contour: bool = _contour_field()
    _omit_plain = model_serializer(mode="wrap")(_omit_plain)


class ImagePolyline(Feature):
    kind: Literal["polyline"] = "polyline"
    points: list[Vec2] = Field(min_length=2)
    closed: bool = False
    contour: bool = _contour_field()
    _omit_plain = model_serializer(mode="wrap")(_omit_plain)


class ImageConic(Feature):
    """An undistorted ellipse image: centre, semi-axes, angle of the first axis, arc range."""

    kind: Literal["conic"] = "conic"
    centre: Vec2
    axes: Vec2
    angle: float
    arc: Vec2 | None = Field(None, description="parameter range of a section, None for the whole ellipse")


class ImageCorner(Feature):
    kind: Literal["corner"] = "corner"
    at: Vec2


class View(Node):
    """What one camera sees at one pose: its parameters, its pose, and its features."""

    camera: Camera
    rotation: tuple[Vec3, Vec3, Vec3] = Field(description="R of P_cam = R P_world + t")
    translation: Vec3 = Field(description="t of P_cam = R P_world + t")
    lines: list[ImageLine] = []
    polylines: list[ImagePolyline] = []
    conics: list[ImageConic] = []
    corners: list[ImageCorner] = []


class PoseViews(Node):
    """Both cameras' views at one pose of the path."""

    index: int
    pose: Vec3 = Field(description="(x, y, heading) of the robot (of a 6-DoF pose: its projection on the floor)")
    transform: Mat34 | None = Field(None, description="a 6-DoF pose (a path read from a trajectory file): "
                                    "world_from_robot [R | t] (rows)")
    viewpoint: str | None = Field(None, description="the view-point whose visibility list was used")
    left: View
    right: View | None = None
    _dump = omitted_when_none("transform")


class Features(Node):
    """A dump of the (ideal or disturbed) feature sets of every pose."""

    document: Literal["features"] = "features"
    schema_version: Literal["1"] = SCHEMA_VERSION
    tool_version: str
    scene: SceneRef
    pipeline: str | None = None
    stages: list[StageRecord] = []
    seed: int | None = None
    trial: int | None = None
    poses: list[PoseViews] = []


class ViewDependency(Node):
    """A view-dependency file: the features visible from each view-point (`wiredsl viewdep`)."""

    document: Literal["viewdep"] = "viewdep"
    schema_version: Literal["1"] = SCHEMA_VERSION
    tool_version: str
    scene: SceneRef
    threshold: float = Field(ge=0, le=1, description="fraction of a feature's samples that must be seen")
    eye_height: float = Field(description="metres above the floor the view-points see from")
    viewpoints: dict[str, list[str]]
