"""JSON Schemas (2020-12) generated from the pydantic models, and validation against them."""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

from pydantic import BaseModel

DIALECT = "https://json-schema.org/draft/2020-12/schema"
NAMES = ("scene", "features", "viewdep", "manifest", "study", "study-manifest")


def _model(name: str) -> type[BaseModel]:
    if name == "scene":
        return _scene_with_stages()
    from wiredsl.io import features, manifest, study_documents
    return {"features": features.Features, "viewdep": features.ViewDependency, "manifest": manifest.Manifest,
            "study": study_documents.StudyTable, "study-manifest": study_documents.StudyManifest}[name]


def _scene_with_stages() -> type[BaseModel]:
    """The Scene model with each pipeline stage's parameters spelt out per effect (built-in and installed):
    the compiled scene keeps a stage as a name and a dict, which the compiler checked against the effect."""
    import functools as ft
    import operator
    from typing import Annotated

    from pydantic import Field, create_model

    from wiredsl.effects import stage_models
    from wiredsl.scene import Pipeline, Scene

    stage = Annotated[ft.reduce(operator.or_, stage_models().values()), Field(discriminator="effect")]
    pipeline = create_model("Pipeline", __base__=Pipeline, __doc__=Pipeline.__doc__, stages=(list[stage], []))
    return create_model("Scene", __base__=Scene, __doc__=Scene.__doc__, pipelines=(list[pipeline], []))


def generate(name: str) -> dict:
    """The schema of a document kind, as generated from its model."""
    body = _model(name).model_json_schema(mode="serialization")
    return {"$schema": DIALECT, "$id": f"urn:wiredsl:schema:{name}:1", **body}


def render(name: str) -> str:
    return json.dumps(generate(name), indent=2, sort_keys=True) + "\n"


def schema_dir() -> Path:
    """The committed schemas: packaged copy when installed, the checkout's `schema/` otherwise."""
    here = Path(__file__).resolve().parent.parent  # the package folder
    for candidate in (here / "schema", here.parent / "schema"):
        if (candidate / "scene.schema.json").is_file():
            return candidate
    raise FileNotFoundError("schema/ not found next to the package")


def _with_plugins(name: str) -> bool:
    """Whether the schema of `name` here differs from the committed one: a scene's, where plug-in effects are
    installed (their parameter models join the built-ins')."""
    if name != "scene":
        return False
    from wiredsl.plugins import installed

    return bool(installed("effect"))


def text(name: str) -> str:
    """The schema of a document kind as `wiredsl schema` prints it: the committed file, or, for a scene where
    plug-in effects are installed, the schema generated with their parameters."""
    if _with_plugins(name):
        return render(name)
    return (schema_dir() / f"{name}.schema.json").read_text(encoding="utf-8")


def validator(name: str):
    installed = ()
    if name == "scene":
        from wiredsl.plugins import installed as scan

        installed = tuple(scan("effect"))
    return _validator(name, installed)


@functools.cache
def _validator(name: str, installed: tuple):  # (cached per set of installed plug-ins)
    import jsonschema

    return jsonschema.Draft202012Validator(json.loads(text(name)))


def problems(doc: object) -> list[str]:
    """Why a dump does not validate (empty when it does). A scene whose pipelines name an effect that is neither
    built in nor installed says so, naming it, instead of listing its parameters as unexpected."""
    kind = doc.get("document") if isinstance(doc, dict) else None
    if kind not in NAMES:
        return [f"not a wiredsl document: 'document' must be one of {', '.join(NAMES)}"]
    missing = _missing_effects(doc) if kind == "scene" else {}
    errors = sorted(validator(kind).iter_errors(doc), key=lambda e: list(map(str, e.absolute_path)))
    errors = [x for e in errors for x in _explain(e)
              if not any(tuple(e.absolute_path)[:len(at)] == at for at in missing)]
    return _non_finite(doc) + list(missing.values()) + [
        f"{'/'.join(map(str, e.absolute_path)) or '(root)'}: {_short(e.message)}" for e in errors]


def _missing_effects(doc: dict) -> dict[tuple, str]:
    """{path of a stage: why} for each pipeline stage whose effect is neither built in nor an installed plug-in."""
    from wiredsl.effects import REGISTRY

    out = {}
    pipelines = doc.get("pipelines")
    for i, p in enumerate(pipelines if isinstance(pipelines, list) else []):
        stages = p.get("stages") if isinstance(p, dict) else None
        for j, st in enumerate(stages if isinstance(stages, list) else []):
            effect = st.get("effect") if isinstance(st, dict) else None
            if isinstance(effect, str) and effect not in REGISTRY:
                out[("pipelines", i, "stages", j)] = (
                    f"pipelines/{i}/stages/{j}: effect '{effect}' is neither built in nor installed here: install "
                    "the plug-in package that provides it ('wiredsl plugins' lists those installed)")
    return out


def _non_finite(doc: object) -> list[str]:
    """Every NaN or infinity in a document (jsonschema's "number" admits them; JSON cannot hold them)."""
    out, stack = [], [((), doc)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, float) and not math.isfinite(v):
            out.append(f"{'/'.join(map(str, path)) or '(root)'}: {v} is not a finite number")
        elif isinstance(v, dict):
            stack += [((*path, k), x) for k, x in v.items()]
        elif isinstance(v, list):
            stack += [((*path, i), x) for i, x in enumerate(v)]
    return sorted(out)


def _short(message: str, limit: int = 160) -> str:
    """jsonschema quotes whole instances; keep a message to one readable line."""
    return message if len(message) <= limit else message[:limit - 5] + " ..."


def _explain(err) -> list:
    """A oneOf over tagged variants (pipeline stages) fails as a whole; report the errors of
    the variant whose tag matched instead."""
    if err.validator == "oneOf" and err.context:
        branches: dict[int, list] = {}
        for sub in err.context:
            branches.setdefault(sub.relative_schema_path[0], []).append(sub)
        tagged = [errs for errs in branches.values() if not any(e.validator == "const" for e in errs)]
        if len(tagged) == 1:
            return tagged[0]
    if err.context:  # anyOf / oneOf without a tag: the most relevant error of the branches
        import jsonschema

        return [jsonschema.exceptions.best_match(err.context)]
    return [err]
