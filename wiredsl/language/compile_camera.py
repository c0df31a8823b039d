"""Stage 3 for cameras and the rig: camera statements (with `like` and `read`), calibration files,
mounts (with `relative` extrinsics) and the rig's calibration uncertainty.

`CameraCompiler` is mixed into `Compiler`; it uses the compiler's collector (`out`), per-file
units and reference checks.
"""

from __future__ import annotations

import math
import os
from pathlib import Path as FsPath

import numpy as np

from wiredsl.diagnostics import Collector, Span, WiredslError, did_you_mean
from wiredsl.io import sources
from wiredsl.language.bind import Bound, bind
from wiredsl.language.statements import MAX_MAGNITUDE
from wiredsl.scene import CALIBRATION_PARAMETERS, Calibration, Camera, Mount, Rig, checked, trusted

MAX_MATRIX = 1_000
BARE_FOCAL_METRES = 0.1  # a bare focal length this long (in m) is more likely mm written without its unit
PLAUSIBLE_FOV = 1000  # f over the image's larger side beyond which a focal length is probably missing its unit
MAX_MATRIX_ENTRY = 1e100  # calibration entries: inverses, square roots and products of them stay finite
LENS = ("distortion", "k", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "xi", "alpha", "beta", "w")
ENTRIES = ("first", "second", "third")  # `read ... entry`: these, or camN (Kalibr's name, N from 0)
LENS_RANGES = {"unified": "xi in [0, 100]", "eucm": "alpha in [0, 1], beta in (0, 100]",
               "ds": "alpha in [0, 1], xi in (-1, 1]",
               "fov": "w in (0, 180) deg"}
STEREO_BASELINE = 5.0  # metres: a stereo pair's |T| beyond this is more likely in millimetres
MAX_READOUT = 1.0  # s: a rolling shutter's readout, and a stereo pair's sync offset, beyond a second is no camera's
FILE_UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # `relative "file" units U`: metres per unit of the file's T


class CameraCompiler:
    """The camera and rig part of `Compiler` (a mixin: `out`, `units`, `_units`, `_ref`, `camera_stmts`,
    `cameras` and `rig_without_calibration` are the compiler's)."""

    # ------------------------------------------------------------------ cameras
    def _camera_decl(self, b: Bound) -> None:
        if b.name in self.camera_stmts:
            self.out.error("E105", f"duplicate camera '{b.name}'", b.name_span,
                           f"first declared at {self.camera_stmts[b.name].name_span}")
            return
        self.camera_stmts[b.name] = b

    def _resolve_cameras(self) -> None:
        self.camera_reads: dict[str, tuple[FsPath, int]] = {}  # camera -> (calibration file, entry) it read
        settings: dict[str, dict[str, tuple[object, Span]] | None] = {}
        failed: set[str] = set()

        def resolve(name: str, chain: tuple[str, ...]) -> dict | None:
            if name in settings:
                return settings[name]
            b = self.camera_stmts[name]
            base: dict = {}
            if b.has("like"):
                parent = b.get("like")
                if parent in chain:
                    self.out.error("E104", "cameras are declared like each other in a cycle: "
                                           + " -> ".join((*chain, parent)), b.span("like"))
                    settings[name] = None
                    return None
                if not self._ref(self.camera_stmts, "camera", parent, b.span("like")):
                    settings[name] = None
                    return None
                base = resolve(parent, (*chain, parent))
                if base is None:
                    settings[name] = None
                    return None
                if parent in failed:  # what the parent would have set is unknown, so is what this one inherits:
                    failed.add(name)  # no knock-on 'needs focal' for a typo in the parent
            own = dict(base)
            here: set[str] = set()
            for stmt in b.stmt.block or ():
                if stmt.keyword == "read":
                    sb = bind(stmt, "camera", self._units(stmt), self.out)
                    if sb is not None and sb.ok:
                        read = self._camera_file(sb)
                        if read is None:  # reported: no cascade of "needs focal"
                            settings[name] = None
                            return None
                        for key in LENS:  # the file's lens replaces a `like` camera's whole lens
                            own.pop(key, None)
                        own.update(read)
            for stmt in b.stmt.block or ():
                if stmt.keyword == "read":
                    continue
                sb = bind(stmt, "camera", self._units(stmt), self.out)
                if sb is None or not sb.ok:
                    failed.add(name)  # what it would have set is unknown: no 'needs' errors on top
                    continue
                here.add(stmt.keyword)
                if stmt.keyword in ("k", "k1"):
                    if here >= {"k", "k1"}:
                        self.out.error("E103", "give either TINA's 'k' or OpenCV's 'k1', not both",
                                       stmt.keyword_span, "k1 = -k")
                    own.pop("k1" if stmt.keyword == "k" else "k", None)  # one parameter, two spellings
                own[stmt.keyword] = (sb.pos(0), sb.positional[0].span)
            if "_read" in own:
                self._rescaled(name, own)
            settings[name] = own
            return own

        for name, b in self.camera_stmts.items():
            s = resolve(name, (name,))
            if s is not None and "_read" in s:
                self.camera_reads[name] = s["_read"][0][:2]
            if s is not None and name not in failed:
                cam = self._camera(b, s)
                if cam is not None:
                    self.cameras[name] = cam

    def _calibration_file(self, sb: Bound, path_span: Span, path: str, fmt: str | None):
        """The cameras of a calibration file named in a statement, or None (reported)."""
        from wiredsl.io.calibration import CalibrationFileError, read

        cache = self.__dict__.setdefault("_calibration_files", {})  # a file read by two cameras and the rig
        try:
            target = FsPath(sb.stmt.span.file).parent / path
            if (target, fmt) in cache:
                return cache[target, fmt]
            cache[target, fmt] = None  # a file that fails is reported once, where it is first read
            sources.read_bytes(target, "calibration file", path_span)  # a regular file, not a FIFO (would block)
            cache[target, fmt] = read(target, fmt)
            return cache[target, fmt]
        except WiredslError as err:
            self.out.extend(err.diagnostics)
        except CalibrationFileError as exc:
            self.out.error("E141", f"calibration file {path}: {exc}", path_span)
        except ValueError as exc:  # e.g. a NUL byte in the path
            self.out.error("E010", f"cannot read calibration file {path!r}: {exc}", path_span)
        return None

    def _camera_file(self, sb: Bound) -> dict[str, tuple[object, Span]] | None:
        """A camera's settings from a calibration file, as if written as statements at `read`."""
        path, path_span = sb.pos(0), sb.positional[0].span
        cams = self._calibration_file(sb, path_span, path, sb.get("format"))
        if cams is None:
            return None
        entry = sb.get("entry", "first")
        i = ENTRIES.index(entry) if entry in ENTRIES else int(entry[3:])
        if i >= len(cams):
            have = ", ".join(c.name for c in cams)
            self.out.error("E104", f"calibration file {path} has {len(cams)} camera{'s' * (len(cams) > 1)} "
                                   f"({have}); there is no {entry}", sb.span("entry"))
            return None
        c, span = cams[i], sb.stmt.span
        if c.error is not None:
            self.out.error("E141", f"calibration file {path}: {c.error}", path_span)
            return None
        if not c.intrinsics:
            self.out.error("E141", f"calibration file {path} holds extrinsics only (R, T): no camera to read",
                           path_span, "read the cameras from the intrinsics file (stereo_calib's intrinsics.yml) "
                           "and give this one to the rig's 'relative'")
            return None
        if not all(math.isfinite(v) and abs(v) <= MAX_MAGNITUDE for v in (c.fx, c.fy, c.cx, c.cy, *c.dist)):
            self.out.error("E141", f"calibration file {path}: the camera matrix or distortion has a value beyond "
                                   f"{MAX_MAGNITUDE:g}", path_span)
            return None
        for note in c.notes:
            self.out.warning("W143", f"calibration file {path}: {note}", path_span)
        from wiredsl.engine.geometry import MODEL_KEYS

        coeffs = MODEL_KEYS[c.model]  # the order of a calibration's `dist`
        out = {"focal": ((c.fx, "image", "px"), span), "aspect": ((1.0, c.fy / c.fx), span),
               "centre": ((c.cx, c.cy), span), "distortion": (c.model, span)}
        out.update({k: (v, span) for k, v in zip(coeffs, c.dist, strict=True)})
        if c.width is not None:
            out["size"] = ((c.width, c.height), span)
        out["_read"] = ((FsPath(sb.stmt.span.file).parent / path, i, dict(out)), span)
        return out

    def _rescaled(self, name: str, own: dict) -> None:
        """A `size` beside `read` that differs from the file's: the file's K scaled to it (or refused).
        A size given for a file that has none is checked against the file's centre."""
        (_, _, read), _ = own["_read"]
        if "size" in own and "size" not in read and own.get("centre") is read["centre"]:
            (cx, cy), (w, h) = read["centre"][0], own["size"][0]
            if not (0 <= cx <= w and 0 <= cy <= h):
                self.out.warning("W143", f"camera '{name}': the calibration file's centre ({cx:.6g}, {cy:.6g}) is "
                                         f"outside the {w:g} x {h:g} image", own["size"][1],
                                 "give the size the camera was calibrated at")
            return
        if "size" not in read or own["size"] is read["size"]:
            return
        (W, H), (w, h) = read["size"][0], own["size"][0]
        if (W, H) == (w, h):
            return
        scaled = [k for k in ("focal", "aspect", "centre") if own.get(k) is read[k]]
        if not scaled:
            return  # the statements give the whole camera matrix for the new size
        sx, sy = w / W, h / H
        span = own["size"][1]
        if abs(sx - sy) > 1e-3 * max(sx, sy):
            self.out.error("E110", f"camera '{name}': size ({w:g}, {h:g}) is not the calibration file's "
                                   f"({W}, {H}) scaled: its camera matrix does not apply", span,
                           "a cropped or binned image needs its own 'focal', 'aspect' and 'centre'")
            return
        (f, kind, unit), fspan = read["focal"]
        ax, ay = read["aspect"][0]
        cx, cy = read["centre"][0]
        new = {"focal": ((f * sx, kind, unit), fspan), "aspect": ((ax, ay * sy / sx), read["aspect"][1]),
               "centre": ((cx * sx, cy * sy), read["centre"][1])}
        own.update({k: new[k] for k in scaled})
        self.out.warning("W143", f"camera '{name}': size ({w:g}, {h:g}) differs from the calibration file's "
                                 f"({W}, {H}): its {', '.join(scaled)} scaled by {sx:.6g}", span,
                         "if the image is cropped rather than scaled, give 'centre' for it")

    def _camera(self, b: Bound, s: dict[str, tuple[object, Span]]) -> Camera | None:
        n0 = self.out.n_errors
        where = b.name_span

        def need(key: str, what: str) -> None:
            if key not in s:
                self.out.error("E102", f"camera '{b.name}' needs '{key}' ({what})", where)

        need("focal", "focal length")
        need("size", "image size")
        if n0 != self.out.n_errors:
            return None
        (f, kind, unit), fspan = s["focal"]
        written = f
        if kind == "length":
            if "pixel" not in s:
                self.out.error("E102", f"camera '{b.name}' gives its focal length in {kind} units and needs 'pixel'",
                               fspan, "add e.g. 'pixel 0.01mm', or give the focal length in px")
                return None
            pixel, pspan = s["pixel"]
            self._positive(pixel, "pixel size", pspan)
            f = f / pixel if pixel > 0 else f
        self._positive(f, "focal length", fspan)
        (w, h), sspan = s["size"]
        for v in (w, h):
            if not (v > 0 and float(v).is_integer()):
                self.out.error("E110", f"image size must be whole pixels > 0, got {v:g}", sspan)
        ax, ay = s.get("aspect", ((1.0, 1.0), None))[0]
        for v in (ax, ay):
            self._positive(v, "aspect scale", s.get("aspect", (None, where))[1])
        if self.out.n_errors == n0:
            fx = f * max(ax, ay)
            if not fx <= MAX_MAGNITUDE:  # also catches inf from a huge focal over a tiny pixel
                self.out.error("E110", f"camera '{b.name}': focal length of {fx:.3g} px (with aspect) is beyond "
                                       f"the limit of {MAX_MAGNITUDE:g} px", fspan)
            else:
                bare_metres = unit is None and kind == "length" and self.units[fspan.file]["length"] == "m"
                hint = f"did you mean {written:g}mm?" if bare_metres else None
                if f < 1 or f > PLAUSIBLE_FOV * max(w, h):
                    fov = math.degrees(2 * math.atan(max(w, h) / (2 * f)))
                    self.out.warning("W111", f"camera '{b.name}': a focal length of {f:.4g} px gives a field of "
                                             f"view of {fov:.3g} deg over its {max(w, h):g} px image", fspan, hint)
                elif bare_metres and written >= BARE_FOCAL_METRES:  # a bare number is metres: 6 is a 6 m lens
                    self.out.warning("W111", f"camera '{b.name}': a bare focal length is in metres, so "
                                             f"{written:g} is a {written:g} m lens", fspan, hint)
        k1 = -s["k"][0] if "k" in s else s.get("k1", (0.0, None))[0]
        cx, cy = s.get("centre", ((w / 2, h / 2), None))[0]
        lens = self._lens(b, s)
        if self.out.n_errors != n0 or lens is None:
            return None
        motion = {}
        for key, what in (("readout", "a readout"), ("exposure", "an exposure")):
            if key not in s:
                continue
            (value, vspan) = s[key]
            if not 0 <= value <= MAX_READOUT:  # also NaN
                self.out.error("E110", f"{what} time must be in [0, {MAX_READOUT * 1e3:g}] ms, got "
                                       f"{value * 1e3:g} ms", vspan)
                return None
            if value > 0:
                motion[key] = float(value)
                self.motion_spans.append((f"the {key} of camera '{b.name}'", vspan))
        cam = checked(Camera, name=b.name, f=f, ax=ax, ay=ay, cx=cx, cy=cy, k1=k1, width=int(w), height=int(h),
                      **lens, **motion)
        span = next((s[k][1] for k in ("distortion", *LENS) if k in s), where)
        self._lens_reach(cam, span, s)
        return cam

    @staticmethod
    def _lens_culprit(cam: Camera, s: dict, span: Span, corner_radius: float | None = None) -> Span:
        """Where W147 points: the lens number most to blame among those written. For a fold, the one whose removal
        (set to 0) moves the fold farthest out (a k2 that bends a fisheye back, not the k1 written before it; a
        unified lens's xi); for a radtan scale, the radial term largest at the corner's unit-plane radius."""
        from wiredsl.engine import geometry

        written = [(key, "k1" if key == "k" else key) for key in LENS[1:] if key in s]  # 'k' is -k1
        if not written:
            return span
        if corner_radius is not None:
            powers = {"k1": 2, "k2": 4, "k3": 6, "k4": 2, "k5": 4, "k6": 6}

            def blame(name: str) -> float:  # log |k r^p| (a k3 of 1e300 at a large radius overflows a float)
                k = getattr(cam, name)
                return math.log(abs(k)) + powers[name] * math.log(corner_radius) if name in powers and k else -math.inf
        else:
            def blame(name: str) -> float:  # how far out the fold goes without it (nan: no lens without it)
                with np.errstate(all="ignore"):
                    limit = geometry.lens_limit(cam, bounded=False, **{name: 0.0})
                return -math.inf if math.isnan(limit) else limit
        return s[max(written, key=lambda kn: blame(kn[1]))[0]][1]

    def _lens_reach(self, cam: Camera, span: Span, s: dict) -> None:
        """W147, a lens that does not image its own image: its distortion folds back inside the image (a real
        calibration can, past where its target was seen; a sign error does), so the part beyond the fold is never
        reached; or (radtan) it scales the corner's radius by over 4x or under 1/4x (a k1 of 1e6 read from a
        file), so the image spans a sliver of the view its focal length gives. A fisheye bounded by its
        declared fov, or imaging to 180 deg, is left alone: its circular image is the lens's."""
        from wiredsl.engine import geometry

        k = (cam.k1, cam.k2, cam.k3, cam.k4)

        def radius_of(u, v):  # a pixel's distance from the principal point on the distorted unit plane
            return np.hypot((u - cam.cx) / (cam.f * cam.ax), (v - cam.cy) / (cam.f * cam.ay))

        corner = float(radius_of(np.array([0.0, cam.width, 0.0, cam.width]),
                                 np.array([0.0, 0.0, cam.height, cam.height])).max())
        if cam.distortion != "radtan":  # an angle-bounded lens: its own valid region, without the declared fov
            stop = geometry.lens_limit(cam, bounded=False)
            if stop >= math.pi or (cam.fov is not None and cam.fov / 2 <= stop):
                return
            unit = {**geometry.camera_table(cam), "f": 1.0, "ax": 1.0, "ay": 1.0, "cx": 0.0, "cy": 0.0,
                    "p1": 0.0, "p2": 0.0}
            with np.errstate(all="ignore"):  # the distorted radius at the limit (inf where the model's is)
                reach = abs(float(geometry.project(np.array([[math.sin(stop), 0.0, math.cos(stop)]]), unit)[0, 0]))
            reach, angle = (reach if math.isfinite(reach) else math.inf), stop
        else:
            def radius(r: float) -> float:  # the distorted radius of unit-plane radius r (radial terms; inf on
                # overflow or at the rational denominator's zero, which is where the limit can lie: past any corner)
                with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                    x = float(geometry.distort(np.array([r, 0.0]), cam.k1, cam.k2, 0.0, 0.0, *k[2:], cam.k5,
                                               cam.k6)[0])
                return x if math.isfinite(x) else math.inf

            angle = math.atan(geometry.lens_limit(cam))
            reach = radius(math.tan(angle)) if angle < math.pi / 2 else math.inf
            if corner <= reach:
                lo, hi = 0.0, math.tan(angle) if angle < math.pi / 2 else corner * 1e6
                for _ in range(64):  # the unit-plane radius imaged at the corner (radius rises to the fold)
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if radius(mid) < corner else (lo, mid)
                scale = corner / hi if hi > 0 else 1.0
                if not 0.25 <= scale <= 4.0:
                    seen, bare = (math.degrees(2 * math.atan(x)) for x in (hi, corner))
                    self.out.warning("W147", f"camera '{cam.name}': its distortion scales the image corner's "
                                             f"radius by {scale:.3g}, so its image spans {seen:.3g} deg across the "
                                             f"diagonal where its focal length alone gives {bare:.3g} deg",
                                     self._lens_culprit(cam, s, span, hi),
                                     "check the coefficients (their signs, a file's units)")
                return
        u, v = np.meshgrid(np.linspace(0.5, cam.width - 0.5, 64), np.linspace(0.5, cam.height - 0.5, 48))
        lost = float(np.mean(radius_of(u, v) > reach))
        if lost >= 0.01:
            self.out.warning("W147", f"camera '{cam.name}': its distortion folds back {math.degrees(angle):.3g} deg "
                                     f"from the optical axis, so {lost:.0%} of its image (farther than "
                                     f"{reach * cam.f:.4g} px from the centre) is never reached",
                             self._lens_culprit(cam, s, span),
                             "beyond the fold the lens model is not one-to-one: a calibration holds where its "
                             "target was seen; check the coefficients if this is not expected")

    def _lens(self, b: Bound, s: dict[str, tuple[object, Span]]) -> dict | None:
        """The lens model and its numbers beside k1; None after reporting a clause the model has not or numbers that
        define no lens of the model."""
        from wiredsl.engine import geometry

        model, mspan = s.get("distortion", ("radtan", b.name_span))
        own = geometry.MODEL_KEYS[model]
        ok = True
        for key in ("k", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2", "xi", "alpha", "beta", "w", "fov"):
            if key in s and key not in own and not (key == "k" and "k1" in own) and not (key == "fov"
                                                                                        and model != "radtan"):
                ok = False
                hint = (f"the {model} model's numbers are {', '.join(own)}" + (" and a fov" if model != "radtan"
                                                                                  else "")
                        + ("; a field of view bounds a wide-angle lens: choose its 'distortion' model"
                           if key == "fov" else ""))
                self.out.error("E103", f"camera '{b.name}': '{key}' does not belong to the {model} lens model",
                               s[key][1], hint)
        fov = s.get("fov", (None, None))
        if fov[0] is not None and not 0 < fov[0] <= 2 * math.pi:
            self.out.error("E110", f"a field of view must be in (0, 360] deg, got {math.degrees(fov[0]):g} deg",
                           fov[1])
            ok = False
        if not ok:
            return None
        out = {k: s.get(k, (0.0,))[0] for k in ("k2", "p1", "p2", "k3", "k4", "k5", "k6", "xi", "alpha", "w")}
        out["beta"] = s.get("beta", (1.0,))[0]
        if model not in ("radtan", "equidistant"):
            numbers = {**{k: 0.0 for k in geometry.CAMERA_KEYS[5:]}, **out,
                       "k1": -s["k"][0] if "k" in s else s.get("k1", (0.0,))[0]}
            if math.isnan(geometry.model_max_angle(model, numbers)):
                where = next((s[k][1] for k in own if k in s), mspan)
                self.out.error("E110", f"camera '{b.name}': these numbers define no {model} lens", where,
                               LENS_RANGES[model])
                return None
        return {**out, "distortion": model, "fov": fov[0]}

    def _positive(self, v: float, what: str, span: Span | None) -> None:
        if not v > 0:
            self.out.error("E110", f"{what} must be > 0, got {v:g}", span)

    def _rig(self, b: Bound) -> Rig | None:
        mounts: dict[str, Mount] = {}
        calibration = None
        extra: dict[str, float] = {}  # sync, when declared
        seen: dict[str, Span] = {}
        for stmt in b.stmt.block:
            sb = bind(stmt, "rig", self._units(stmt), self.out)
            if sb is None or not sb.ok:
                continue
            if stmt.keyword in seen:
                self.out.error("E105", f"'{stmt.keyword}' given twice in rig '{b.name}'", stmt.keyword_span)
                continue
            seen[stmt.keyword] = stmt.keyword_span
            if stmt.keyword == "calibration":
                calibration = self._calibration(sb)
            elif stmt.keyword == "sync":
                sync = sb.pos(0)
                if not abs(sync) <= MAX_READOUT:  # also NaN
                    self.out.error("E110", f"a sync offset must be within {MAX_READOUT * 1e3:g} ms, got "
                                           f"{sync * 1e3:g} ms", sb.positional[0].span)
                    return None
                if sync != 0:
                    extra["sync"] = float(sync)
                    self.motion_spans.append((f"the sync of rig '{b.name}'", sb.positional[0].span))
                if sb.has("jitter"):
                    jitter, jspan = sb.get("jitter"), sb.span("jitter")
                    if not 0 <= jitter <= MAX_READOUT:  # also NaN
                        self.out.error("E110", f"a sync jitter must be in [0, {MAX_READOUT * 1e3:g}] ms, got "
                                               f"{jitter * 1e3:g} ms", jspan)
                        return None
                    if jitter > 0:
                        extra["jitter"] = float(jitter)
                        self.motion_spans.append((f"the sync jitter of rig '{b.name}'", jspan))
            else:
                mount = self._mount(sb)
                if mount is not None:
                    mounts[stmt.keyword] = mount
        for side in ("left", "right"):
            if side not in seen:
                self.out.error("E102", f"rig '{b.name}' needs a '{side}' camera", b.name_span)
        self.rig_without_calibration = "calibration" not in seen and not any(
            s.keyword == "calibration" for s in b.stmt.block)  # a calibration with errors is reported already
        for side, other in (("left", "right"), ("right", "left")):
            if isinstance(mounts.get(side), Bound):
                mounts[side] = self._relative_mount(mounts[side], mounts.get(other), side)
        if len(mounts) != 2 or not all(isinstance(m, Mount) for m in mounts.values()):
            return None
        if calibration is not None and not self._calibration_fits_lenses(calibration, mounts, seen["calibration"]):
            return None
        rig = trusted(Rig, name=b.name, left=mounts["left"], right=mounts["right"], calibration=calibration, **extra)
        self._check_stereo(rig, seen["right"])
        return rig

    def _calibration_fits_lenses(self, calibration: Calibration, mounts: dict[str, Mount], span: Span) -> bool:
        """A calibration may not perturb a coefficient its camera's lens model has not (a fisheye's p1):
        such a draw would change nothing, silently."""
        for item in calibration.order:
            side, _, param = item.partition(".")
            cam = self.cameras.get(mounts[side].camera)
            if cam is not None and cam.distortion == "equidistant" and param in ("p1", "p2", "k5", "k6"):
                self.out.error("E104", f"calibration parameter '{item}' does not belong to the equidistant lens of "
                                       f"camera '{cam.name}'", span,
                               "a fisheye's coefficients are k1..k4 (as left.k, which is -k1, left.k2, left.k3, "
                               "left.k4)")
                return False
        return True

    def _mount(self, sb: Bound) -> Mount | Bound | None:
        """A mount, or its statement when it is `relative` to the other camera (resolved in `_rig`)."""
        cam = sb.pos(0)
        ok = self._ref(self.camera_stmts, "camera", cam, sb.positional[0].span)
        if sb.has("units") and not sb.has("relative"):
            self.out.error("E103", "'units' gives the unit of a 'relative' file's translation: it needs 'relative'",
                           sb.span("units"))
            return None
        if sb.has("relative"):
            for key in ("at", "looking", "roll"):
                if sb.has(key):
                    self.out.error("E103", f"'{key}' and 'relative' both give the mount's pose: keep one",
                                   sb.span(key))
                    return None
            return sb if ok else None
        for key in ("at", "looking"):
            if not sb.has(key):
                self.out.error("E102", f"'{sb.stmt.keyword}' needs '{key}' ({sb.sig.clauses[key].doc}), or "
                                       "'relative' with a stereo calibration file", sb.stmt.span,
                               f"e.g. {sb.sig.example}")
                return None
        look = _unit(np.array(sb.get("looking"), dtype=float))
        if np.linalg.norm(look) == 0:
            self.out.error("E121", "viewing direction is zero", sb.span("looking"))
            return None
        R = camera_rotation(look, sb.get("roll", 0.0))
        if R is None:
            self.out.error("E122", "viewing direction is vertical: the camera's image axes are undefined",
                           sb.span("looking"), "tilt it slightly, e.g. (0.01, 0, -1)")
            return None
        return trusted(Mount, camera=cam, position=sb.get("at"), rotation=_mat(R)) if ok else None

    def _relative_mount(self, sb: Bound, other: Mount | Bound | None, side: str) -> Mount | None:
        """A camera's mount from a calibration file's extrinsics and the other camera's mount. When both
        cameras `read` their entries from that file, the extrinsics between those entries (a Kalibr chain's
        cam1 and cam2...); otherwise the file's first pair, its second camera being the right one."""
        if not isinstance(other, Mount):
            if isinstance(other, Bound):
                self.out.error("E103", "only one camera of a rig can be 'relative' to the other", sb.span("relative"))
            return None
        path, span = sb.get("relative"), sb.span("relative")
        cams = self._calibration_file(sb, span, path, None)
        if cams is None:
            return None
        target = FsPath(sb.stmt.span.file).parent / path
        ends = [self.camera_reads.get(c) for c in (other.camera, sb.pos(0))]
        if all(e is not None and _same_file(e[0], target) for e in ends) and ends[0][1] != ends[1][1]:
            a, b = ends[0][1], ends[1][1]
        else:
            a, b = (0, 1) if side == "right" else (1, 0)
        lo, hi = min(a, b), max(a, b)
        M = np.eye(4)  # camera lo's frame -> camera hi's: each entry maps its predecessor's frame into its own
        for k in range(lo + 1, hi + 1):
            if k >= len(cams) or cams[k].R is None:
                self.out.error("E141", f"calibration file {path} has no extrinsics (R and T, or T_cn_cnm1) "
                                       f"between its cameras {lo} and {hi}", span)
                return None
            step = np.eye(4)
            step[:3, :3], step[:3, 3] = cams[k].R, cams[k].T
            M = step @ M
        for k in range(lo + 1, hi + 1):  # doubts about the extrinsics: at `relative`, where they are used
            for note in cams[k].pose_notes:
                self.out.warning("W143", f"calibration file {path}: {note}", span)
        if a > b:
            M = np.linalg.inv(M)
        R, T = M[:3, :3], M[:3, 3] * FILE_UNITS[sb.get("units", "m")]  # the other camera's frame -> this one's
        if not sb.has("units") and np.linalg.norm(T) > STEREO_BASELINE:
            self.out.error("E146", f"calibration file {path}: the cameras are {np.linalg.norm(T):.4g} m apart: did "
                                   "you mean millimetres?", span,
                           f"T is in the units of the calibration board (OpenCV's square size): say so with "
                           f"'relative \"{path}\" units mm' (or cm), or 'units m' if the rig is that wide")
            return None
        R_o, p_o = np.array(other.rotation), np.array(other.position)  # camera -> robot
        R_s = R_o @ R.T
        p_s = p_o - R_s @ T
        if not np.abs(p_s).max() <= MAX_MAGNITUDE:  # T near the float limit overflows here
            self.out.error("E141", f"calibration file {path}: the translation T is beyond {MAX_MAGNITUDE:g} m", span)
            return None
        self.relative_file = path
        self.relative_units = sb.has("units")
        return trusted(Mount, camera=sb.pos(0), position=tuple(float(x) for x in p_s), rotation=_mat(R_s))

    def _check_stereo(self, rig: Rig, span: Span) -> None:
        """Warnings for a rig that is probably not what was meant: a baseline in millimetres, sides swapped."""
        _, T = rig.stereo_extrinsics()
        relative = getattr(self, "relative_file", None)
        where = f" (from {relative})" if relative else ""
        if np.linalg.norm(T) > STEREO_BASELINE and not (relative and getattr(self, "relative_units", False)):
            self.out.warning("W144", f"rig '{rig.name}': the cameras are {np.linalg.norm(T):.4g} m apart{where}: "
                                     "did you mean millimetres?", span,
                             "T is in the units of the calibration board (OpenCV's square size): convert it to "
                             "metres, or calibrate with the square size in metres")
        elif T[0] > 0:
            self.out.warning("W144", f"rig '{rig.name}': the right camera is {T[0]:.4g} m to the left of the left "
                                     f"camera (along the left camera's x){where}", span,
                             "are left and right swapped? a file's second camera (M2, cam1) is the right one")

    def _calibration(self, sb: Bound) -> Calibration | None:
        kind = sb.pos(0)
        if sb.has("kalibr"):
            return self._kalibr_calibration(sb)
        if not sb.has("order"):
            self.out.error("E102", "'calibration' needs 'order' (the parameter of each row), or 'kalibr' with "
                                   "Kalibr's results-cam.txt", sb.stmt.span, f"e.g. {sb.sig.example}")
            return None
        order = sb.get("order")
        n0 = self.out.n_errors
        seen = set()
        for item in order:
            side, _, param = item.value.partition(".")
            if side not in ("left", "right") or param not in CALIBRATION_PARAMETERS:
                choices = [f"{s}.{p}" for s in ("left", "right") for p in CALIBRATION_PARAMETERS]
                self.out.error("E104", f"unknown calibration parameter '{item.value}'", item.span,
                               did_you_mean(item.value, choices) or "parameters are left.<p> or right.<p> with <p> "
                               "one of " + ", ".join(CALIBRATION_PARAMETERS))
            elif item.value in seen:
                self.out.error("E105", f"calibration parameter '{item.value}' listed twice", item.span)
            seen.add(item.value)
        if sb.has("matrix") == sb.has("file"):
            self.out.error("E102", "calibration needs exactly one of 'matrix' or 'file'", sb.stmt.span)
            return None
        if sb.has("matrix"):
            matrix, mspan = sb.get("matrix"), sb.span("matrix")
        else:
            mspan = sb.span("file")
            matrix = read_matrix_file(FsPath(sb.stmt.span.file).parent / sb.get("file"), len(order), mspan, self.out)
            if matrix is None:
                return None
        n = len(order)
        if n > MAX_MATRIX:
            self.out.error("E151", f"calibration of {n} parameters exceeds the limit of {MAX_MATRIX}", sb.span("order"))
            return None
        if len(matrix) != n or any(len(r) != n for r in matrix):
            shape = f"{len(matrix)} x {max((len(r) for r in matrix), default=0)}"
            self.out.error("E140", f"calibration matrix is {shape}, but 'order' names {n} parameters "
                                   f"(expected {n} x {n})", mspan)
            return None
        M = np.array(matrix, dtype=float)
        problem = matrix_problem(M)
        if problem:
            self.out.error("E140", f"calibration {kind} matrix {problem}", mspan)
        if self.out.n_errors != n0:
            return None
        return trusted(Calibration, kind=kind, order=[o.value for o in order], matrix=M.tolist())

    def _kalibr_calibration(self, sb: Bound) -> Calibration | None:
        """The rig's calibration uncertainty as Kalibr reports it: independent standard deviations
        (cam0 is the left camera, cam1 the right; the baseline's as the right mount's)."""
        for key in ("matrix", "file"):
            if sb.has(key):
                self.out.error("E103", f"'{key}' and 'kalibr' both give the matrix: keep one", sb.span(key))
                return None
        if sb.pos(0) != "covariance":
            self.out.error("E103", "Kalibr reports standard deviations: the calibration kind is 'covariance'",
                           sb.positional[0].span)
            return None
        cams = self._calibration_file(sb, sb.span("kalibr"), sb.get("kalibr"), "kalibr")
        if cams is None:
            return None
        sigma = {f"{side}.{k}": v for side, cam in zip(("left", "right"), cams, strict=False)
                 for k, v in cam.sigma.items() if v > 0 and k in CALIBRATION_PARAMETERS}
        names = [(o.value, o.span) for o in sb.get("order")] if sb.has("order") else [(k, None) for k in sigma]
        for name, span in names:
            if name not in sigma:
                self.out.error("E104", f"Kalibr's file gives no standard deviation for '{name}'", span,
                               did_you_mean(name, sigma) or "it has: " + ", ".join(sigma))
                return None
        return trusted(Calibration, kind="covariance", order=[n for n, _ in names],
                       matrix=np.diag([sigma[n] ** 2 for n, _ in names]).tolist())


def rotation(axis: str, angle: float) -> np.ndarray:
    """Right-handed rotation matrix about a coordinate axis."""
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def camera_rotation(look: np.ndarray, roll: float) -> np.ndarray | None:
    """robot_from_camera for an OpenCV camera frame (x right, y down, z along `look`); z is up."""
    z = look / np.linalg.norm(look)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-9:
        return None
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = math.cos(roll), math.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    return np.column_stack([x, y, z])


def _unit(v: np.ndarray) -> np.ndarray:
    """v scaled so its largest component is 1 (zero stays zero): norms of huge or tiny vectors stay finite."""
    big = float(np.abs(v).max())
    return v / big if big > 0 else v


def _mat(R: np.ndarray):
    return tuple(tuple(float(v) for v in row) for row in R)


def matrix_problem(M: np.ndarray) -> str | None:
    """Why a matrix is not a usable covariance or information matrix, or None."""
    if not np.all(np.isfinite(M)):
        return "has a value that is not finite"
    scale = float(np.abs(M).max()) if M.size else 0.0
    if scale > MAX_MATRIX_ENTRY:
        return f"has an entry of {scale:.3g}, beyond the limit of {MAX_MATRIX_ENTRY:g}"
    unit = scale if scale > 0 else 1.0
    M = M / unit  # judged at unit scale (differences and eigenvalues of huge entries overflow), reported unscaled
    asym = float(np.abs(M - M.T).max()) if M.size else 0.0
    if asym > 1e-9:
        i, j = np.unravel_index(np.argmax(np.abs(M - M.T)), M.shape)
        return f"is not symmetric (entry [{i + 1}, {j + 1}] differs from [{j + 1}, {i + 1}] by {asym * unit:.3g})"
    if M.size:
        low = float(np.linalg.eigvalsh((M + M.T) / 2).min())
        if low < -1e-9:
            return f"is not positive semi-definite (smallest eigenvalue {low * unit:.3g})"
    return None


def read_matrix_file(path: FsPath, n: int, span: Span, out: Collector) -> list[list[float]] | None:
    """A matrix from a file: plain rows of numbers, or TINA's covariance format
    (n, a label, the n x n matrix, then the n mean parameters)."""
    try:
        text = sources.read_bytes(path, "calibration file", span).decode("utf-8")
    except WiredslError as err:
        out.extend(err.diagnostics)
        return None
    except UnicodeDecodeError as exc:
        out.error("E010", f"calibration file {sources.display_path(path)} is not UTF-8 text ({exc.reason} at byte "
                          f"{exc.start})", span)
        return None
    words = [w for line in text.splitlines() for w in line.partition("#")[0].split()]
    try:
        if len(words) >= 2 and words[0].isdigit() and not _is_number(words[1]):
            size = int(words[0])
            nums = [float(w) for w in words[2:]]
            if len(nums) != size * size + size:
                raise ValueError(f"TINA covariance file of size {size} needs {size * size + size} numbers, "
                                 f"has {len(nums)}")
        else:
            nums = [float(w) for w in words]
            size = n
            if len(nums) != n * n:
                raise ValueError(f"expected {n} x {n} = {n * n} numbers for the {n} parameters of 'order', "
                                 f"found {len(nums)}")
    except ValueError as exc:
        out.error("E141", f"{sources.display_path(path)}: {exc}", span)
        return None
    return [nums[i * size:(i + 1) * size] for i in range(size)]


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _same_file(a: FsPath, b: FsPath) -> bool:
    return os.path.normcase(os.path.abspath(a)) == os.path.normcase(os.path.abspath(b))
