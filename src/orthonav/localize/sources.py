"""Fix sources by name: the one place every driver, benchmark and command gets a ``FixSource``.

A fix source is asked for by name (:data:`FIX_SOURCES`): the cascade (correlation, keypoints
near it, verification, a calibrated acceptance), the map's keypoints alone, or dense gradient
correlation alone. Unnamed, it is the cascade, the one that is right across dates, where the
map's orthophoto is there, else keypoints, saying why; the cascade's keypoints are the backend
the map was built with. Maps given as fallbacks are asked in turn where the one before rejects
the frame; a flight warms each up before its first frame. What the user should be told (the
source that runs, why not the default, how each warm-up went) is returned as lines, never
printed: the caller shows them where its user reads.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from orthonav.camera import Camera
from orthonav.errors import OrthonavError
from orthonav.features import FeatureBackend, Runtime
from orthonav.frames import TruePose, render_frame
from orthonav.geo import GeoRaster
from orthonav.localize.cascade import CASCADE, Cascade, cascade_config
from orthonav.localize.dense import BACKBONES, GRADIENT, ORIENTATION, CorrectionConfig, Corrector
from orthonav.localize.fallback import FALLBACK, Fallback, parse_chain
from orthonav.localize.keypoint import Localizer
from orthonav.localize.keypoint_config import LocalizerConfig
from orthonav.localize.stages import FineConfig
from orthonav.mapdb import MapPackage, TilingConfig, build_map
from orthonav.types import Fix, FixSource, Pose, Prior

KEYPOINTS = "keypoints"
CORRELATION = "correlation"
# Every fix source a driver, a benchmark or a command can be asked for by name.
FIX_SOURCES = (CASCADE, KEYPOINTS, CORRELATION)
# The cascade's coarse correlations unless asked otherwise: the gradient magnitude's, then the
# gradients' orientation on the frames it rejects (more fixes on every dataset measured, no new
# false fix: docs/benchmarks/localize.md).
DEFAULT_COARSE_BACKBONE = f"{GRADIENT}{FALLBACK}{ORIENTATION}"


def map_orthophoto(package: MapPackage) -> Path:
    """The orthophoto ``package`` was built from, where its manifest records it, checked to be
    that raster (size and georeference as recorded); raises :class:`OrthonavError` saying why
    it cannot serve. Its checksum is not recomputed: hashing a large orthophoto at every start
    of a flight would cost more than a changed file that kept its size and georeference."""
    path, recorded = package.source_path, package.manifest["source"]
    if not path.is_file():
        raise OrthonavError(f"the map's orthophoto {path} (recorded in {package.path}) is not there")
    with GeoRaster(path) as raster:
        found = (raster.width, raster.height, [round(v, 6) for v in list(raster.transform)[:6]])
    expected = (recorded["width"], recorded["height"], [round(v, 6) for v in recorded["transform"]])
    if found != expected:
        raise OrthonavError(
            f"{path} is not the orthophoto {package.path} was built from: size and georeference "
            f"{found[:2]} {found[2]}, the map recorded {expected[:2]} {expected[2]}"
        )
    return path


@dataclass(frozen=True)
class ChosenFixSource:
    """The fix source a driver runs, its name, and what it should say once about it."""

    source: FixSource
    name: str
    # Why it is not the one asked for (the default's fallback), else "".
    fallback: str = ""
    # What the user should know about how it searches (e.g. frames without a position prior).
    note: str = ""
    # The orthophoto it reads (None for keypoints alone): what :func:`warm_up` renders from.
    raster: GeoRaster | None = None


def open_fix_source(
    stack: ExitStack,
    package: MapPackage,
    camera: Camera,
    name: str | None = None,
    orthophoto: Path | None = None,
    localizer: LocalizerConfig | None = None,
    backend: FeatureBackend | None = None,
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    rasters: dict[Path, GeoRaster] | None = None,
    trunk_check: bool | None = None,
    frame_budget_ms: float | None = None,
) -> ChosenFixSource:
    """The fix source ``name`` over ``package``: the cascade, the keypoint localizer alone, or
    dense gradient correlation; None: the cascade where the map's orthophoto is there, else
    keypoints (``fallback`` says why). Correlation and the cascade read ``orthophoto`` (default:
    the map's own, :func:`map_orthophoto`), opened on ``stack``; ``localizer`` configures the
    keypoint matching (alone or as the cascade's fine stage), ``coarse_backbone`` the cascade's
    correlation, ``trunk_check`` its :attr:`CascadeConfig.trunk_check` and ``frame_budget_ms``
    its :attr:`CascadeConfig.frame_budget_ms` (None: unbounded). ``rasters``:
    orthophotos already open, by resolved path, shared by the maps of one flight (their
    in-memory views are built once); one opened here is added."""
    if name is not None and name not in FIX_SOURCES:
        raise OrthonavError(f"fix source {name!r}: expected one of {', '.join(FIX_SOURCES)}")
    fallback = ""
    if name != KEYPOINTS and orthophoto is None:
        try:
            orthophoto = map_orthophoto(package)
        except OrthonavError as exc:
            if name is not None:
                raise OrthonavError(f"fix source {name}: {exc}") from None
            fallback = f"fix source keypoints instead of the cascade: {exc}"
    if name is None:
        name = CASCADE if not fallback else KEYPOINTS
    raster = None if name == KEYPOINTS else _open_shared(stack, orthophoto, rasters)
    source = make_fix_source(
        name, package, camera, raster, localizer, backend, coarse_backbone, trunk_check, frame_budget_ms
    )
    if name == KEYPOINTS:
        return ChosenFixSource(source, name, fallback)
    return ChosenFixSource(source, name, note=_lost_note(package, name), raster=raster)


@dataclass
class OpenedFixSource:
    """A fix source opened by name over a map, with its fallback maps, and what to say of it."""

    source: FixSource
    name: str
    # Each map's own fix source, the first map's first: what :func:`warm_up_maps` warms.
    maps: list[tuple[MapPackage, ChosenFixSource]]
    # Orthophotos open, by resolved path, shared by the maps (their in-memory views built once).
    rasters: dict[Path, GeoRaster] = field(default_factory=dict)

    @property
    def fallback(self) -> str:
        """Why the default fix source does not run (a warning for the user), else ""."""
        return self.maps[0][1].fallback

    @property
    def description(self) -> str:
        """One line: which fix source runs, the fallback maps' order, how it treats frames
        without a position prior."""
        chain = ""
        if isinstance(self.source, Fallback):
            chain = f" ({', then '.join(self.source.names)} where the one before rejects)"
        note = self.maps[0][1].note
        return f"fix source: {self.name}{chain}{f'; {note}' if note else ''}"


def open_fix_sources(
    stack: ExitStack,
    package: MapPackage,
    camera: Camera,
    name: str | None = None,
    fallbacks: Sequence[Path] = (),
    orthophoto: Path | None = None,
    localizer: LocalizerConfig | None = None,
    backend: FeatureBackend | None = None,
    runtime: Runtime | None = None,
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    trunk_check: bool | None = None,
    frame_budget_ms: float | None = None,
) -> OpenedFixSource:
    """The fix source ``name`` over ``package`` (:func:`open_fix_source`; None: the default),
    and where ``fallbacks`` name more map packages of the same area, a :class:`Fallback` asking
    the same kind of source on each in turn. ``backend`` serves the first map; a fallback map's
    keypoints run on ``runtime`` (None: the default). Maps of one orthophoto share it, opened
    once on ``stack``. ``frame_budget_ms``: each map's cascades' frame budget (None: unbounded)."""
    rasters: dict[Path, GeoRaster] = {}
    maps: list[tuple[MapPackage, ChosenFixSource]] = []

    def open_one(
        map_package: MapPackage, source_name: str | None, map_backend: FeatureBackend | None
    ) -> FixSource:
        chosen = open_fix_source(
            stack,
            map_package,
            camera,
            name,
            orthophoto,
            localizer,
            map_backend,
            coarse_backbone,
            rasters,
            trunk_check,
            frame_budget_ms,
        )
        maps.append((map_package, chosen))
        return chosen.source

    source = open_one(package, name, backend)
    chosen_name = maps[0][1].name
    if fallbacks:
        if chosen_name == CORRELATION:
            raise OrthonavError(
                "fallback maps: correlation matches the orthophoto, not a map's features; "
                "use them with the keypoints or the cascade"
            )
        packages = [MapPackage(path) for path in fallbacks]
        more = [open_one(each, chosen_name, _runtime_backend(each, runtime)) for each in packages]
        source = Fallback([source, *more], [each.backend_name for each in (package, *packages)])
    return OpenedFixSource(source, chosen_name, maps, rasters)


def _runtime_backend(package: MapPackage, runtime: Runtime | None) -> FeatureBackend | None:
    """The map's own backend on ``runtime``; None (each source makes the default) without one."""
    return None if runtime is None else package.create_backend(runtime)


def warm_up_maps(opened: OpenedFixSource, camera: Camera) -> list[str]:
    """Warm each map's fix source up on the map's own picture (:func:`warm_up`), rendered from
    the orthophoto it reads, or for keypoints alone from the map's orthophoto where it is there
    (one the flight holds open already, else opened for this only); the lines say how it went,
    and where its learned parts run (:func:`learned_parts`). A fallback map is warmed too: it is
    asked when the first map fails, and should not then pay for its first frame; so is the
    network of its global index, which the first lost frame would load (and, the first time on
    a machine, export for ONNX Runtime). A warm-up that cannot run does not stop the flight."""
    return [
        line for package, chosen in opened.maps for line in _warmed(chosen, camera, package, opened.rasters)
    ]


def _warmed(
    chosen: ChosenFixSource, camera: Camera, package: MapPackage, rasters: dict[Path, GeoRaster]
) -> list[str]:
    """One map's warm-up (see :func:`warm_up_maps`), said in lines."""
    start = time.perf_counter()
    try:
        with ExitStack() as stack:
            raster = chosen.raster
            if raster is None:  # keypoints alone: the orthophoto if the flight holds it open
                path = map_orthophoto(package).resolve()
                raster = rasters[path] if path in rasters else stack.enter_context(GeoRaster(path))
            fix = warm_up(chosen.source, raster, camera, package.tiling.nominal_alt_m)
            if package.global_index is not None:
                package.global_index.prepare()
            parts = learned_parts(chosen.source)
    except OrthonavError as exc:
        return [f"{package.path.name}: not warmed up, its first frame will be slower ({exc})"]
    outcome = "fixed" if fix.accepted else f"not fixed: {fix.reason}"
    warmed = (
        f"{package.path.name}: warmed up in {time.perf_counter() - start:.1f} s on the map's own picture "
        f"at its centre ({outcome})"
    )
    return [warmed, *parts]


def _open_shared(stack: ExitStack, path: Path, rasters: dict[Path, GeoRaster] | None) -> GeoRaster:
    """The orthophoto at ``path``: the one in ``rasters`` already open there, else opened on
    ``stack`` (and added to ``rasters`` where given)."""
    if rasters is None:
        return stack.enter_context(GeoRaster(path))
    key = Path(path).resolve()
    if key not in rasters:
        rasters[key] = stack.enter_context(GeoRaster(path))
    return rasters[key]


def warm_up(source: FixSource, raster: GeoRaster, camera: Camera, alt_agl_m: float) -> Fix:
    """``source``'s fix of a frame rendered from ``raster`` at its centre, straight down from
    ``alt_agl_m``, heading north: what the first frame of a flight would otherwise pay for is
    paid at start-up instead (the map's in-memory views, its tiles and terrain, a learned
    backend's sessions: the first frame costs several times the next, the more so with a learned
    backend). The fix is of the map's own picture: information, not a check of the flight's
    camera. Every source of a :class:`Fallback` is warmed (the later ones answer only
    frames the first rejects, and the first such frame should not pay for them); the first
    source's fix is returned."""
    lat, lon = raster.center_latlon
    frame = render_frame(raster, camera, TruePose(lat, lon, alt_agl_m, 0.0))
    prior = Prior(lat, lon, alt_agl_m, 0.0, sigma_m=10.0, heading_sigma_deg=5.0)
    sources = _leaves(source)
    with ExitStack() as unbounded:  # the warm-up pays every stage's first load, whatever the budget
        for each in sources:
            if isinstance(each, Cascade):
                unbounded.enter_context(each.clock.unbounded())
        fixes = [each.localize(frame, prior) for each in sources]
    for each in sources:
        if isinstance(each, Cascade):
            _warm_matcher(each, frame)
            each.verifier.warm(Pose(lat, lon, alt_agl_m, 0.0, 0.0, 0.0, lat, lon))
    return fixes[0]


def _leaves(source: FixSource) -> list[FixSource]:
    """The fix sources a :class:`Fallback` asks in turn, through nested ones (``fly --fallback``
    over maps whose fix source is itself a chain of cascades)."""
    if isinstance(source, Fallback):
        return [leaf for each in source.sources for leaf in _leaves(each)]
    return [source]


def _warm_matcher(cascade: Cascade, frame: np.ndarray) -> None:
    """A LightGlue-type matcher loads on its first match (torch and its weights: several times
    what a match costs). The warm-up frame, placed surely enough for guided matching, never asks
    for it; the first frame with a wide prior (a flight's start, a window split into regions)
    would. Matched once here, a corner of the frame with itself (the load is the cost). Where it
    cannot load (no torch), such frames go without a keypoint pose and say why;
    ``cascade.matcher_failure`` says it at start-up."""
    backend = cascade.fine.localizer.backend
    if not backend.padded_batching:
        return
    features = backend.extract(cv2.cvtColor(frame[:256, :256], cv2.COLOR_BGR2GRAY))
    try:
        backend.match(features, features)
    except OrthonavError as exc:
        cascade.matcher_failure = str(exc)


def learned_parts(source: FixSource) -> list[str]:
    """Where each cascade of a flight's fix source computes what, after :func:`warm_up`: its
    keypoints, its LightGlue, the trained CNN's frame-to-map check and the global index's network, and
    what a part that cannot load costs. A companion without torch learns it at start-up, not
    from its first rejected frames."""
    lines = [line for each in _leaves(source) if isinstance(each, Cascade) for line in _parts(each)]
    return list(dict.fromkeys(lines))  # the cascades of a chain share their parts: said once


def _parts(cascade: Cascade) -> list[str]:
    backend = cascade.fine.localizer.backend
    lines = [f"{cascade.method}: keypoints on {backend.engine}"]
    if backend.matcher_engine is not None:
        lines.append(f"{cascade.method}: LightGlue on {backend.matcher_engine}")
    if backend.padded_batching and cascade.matcher_failure is not None:
        fallback = "get no keypoint pose"
        if cascade.fine.localizer.descriptors_first:
            fallback = "are matched by mutual nearest descriptors alone (no keypoint pose where rejected)"
        lines.append(
            f"{cascade.method}: no LightGlue ({cascade.matcher_failure}); frames whose search "
            f"splits into regions, or whose placement is too loose for guided matching, {fallback}"
        )
    lines.append(f"{cascade.method}: frame-to-map check by the trained CNN {_trunk_part(cascade)}")
    index = cascade.candidates.package.global_index
    if index is not None and index.method == "cnn":
        lines.append(f"{cascade.method}: global index's network on {_runs_on(index.network)}")
    return lines


def _trunk_part(cascade: Cascade) -> str:
    config = cascade.config
    if not cascade.checks_trunk:
        if config.trunk_check is False:
            return "off (turned off)"
        if config.acceptance_path is not None:
            return "off (the acceptance model given does not weigh it)"
        gsd_m = cascade.verifier.raster.gsd_m
        if gsd_m < config.trunk_min_map_gsd_m:
            return f"off (the map's {gsd_m:.2f} m pixels: finer than its models were fitted on)"
    failure = cascade.trunk_failure()
    if failure is not None:
        return f"off: the CNN does not load ({failure})"
    return f"on {_runs_on(cascade.trunk)}"


def _runs_on(network: object) -> str:
    """ONNX Runtime and the graph's file, or torch."""
    path = getattr(network, "path", None)
    return f"ONNX Runtime ({path.name})" if isinstance(path, Path) else "torch"


def make_fix_source(
    name: str,
    package: MapPackage,
    camera: Camera,
    raster: GeoRaster | None = None,
    localizer: LocalizerConfig | None = None,
    backend: FeatureBackend | None = None,
    coarse_backbone: str = DEFAULT_COARSE_BACKBONE,
    trunk_check: bool | None = None,
    frame_budget_ms: float | None = None,
) -> FixSource:
    """The fix source ``name`` over ``package``, built the one way every driver and benchmark
    builds it: the keypoint localizer, gradient correlation (a lost frame searched around the
    map's global index) or the cascade with ``localizer`` as its fine stage and
    ``coarse_backbone`` as its correlation's (``trained``: the CNN trunk shipped with
    orthonav; ``gradient>trained``: a cascade with each, the second asked only where the first
    rejects the frame, :class:`Fallback`) and ``trunk_check`` as its
    :attr:`CascadeConfig.trunk_check`, ``frame_budget_ms`` as the frame budget a cascade's
    chain keeps to together (None: unbounded; keypoints and correlation alone have none).
    Correlation and the cascade read ``raster``, the map's orthophoto opened by the caller."""
    if name == KEYPOINTS:
        return Localizer(package, camera, localizer, backend)
    if name not in FIX_SOURCES:
        raise OrthonavError(f"fix source {name!r}: expected one of {', '.join(FIX_SOURCES)}")
    if raster is None:
        raise OrthonavError(f"fix source {name}: needs the map's orthophoto")
    if name == CORRELATION:
        use_terrain = (localizer or LocalizerConfig()).use_terrain
        correction = CorrectionConfig(backbone="gradient", use_terrain=use_terrain)
        return Corrector(raster, camera, correction, package=package)
    backbones = coarse_backbones(coarse_backbone)
    fine = FineConfig(localizer=localizer or LocalizerConfig())
    backend = backend or package.create_backend()  # one for every cascade of a chain
    cascades: list[Cascade] = []
    for backbone in backbones:  # one candidates stage: a lost frame described for the index once
        first = cascades[0] if cascades else None
        config = cascade_config(backbone, trunk_check, fine, frame_budget_ms)
        shared = {"candidates": first.candidates, "clock": first.clock} if first else {}
        cascades.append(Cascade(package, raster, camera, config, backend=backend, **shared))
    failure = cascades[0].trunk_failure() if trunk_check else None
    if failure:
        # Asked to measure it on every proposal: fail now rather than on a flight's first frame.
        raise OrthonavError(
            f"trunk check on: the trained CNN does not load ({failure}); the trunk check auto "
            "measures it only where it loads"
        )
    if len(cascades) == 1:
        return cascades[0]
    return Fallback(cascades, [f"{CASCADE}-{backbone}" for backbone in backbones])


def coarse_backbones(spec: str) -> list[str]:
    """``"gradient>trained"`` -> ``["gradient", "trained"]``: the cascade's coarse correlations,
    tried in order on the frames the one before rejects; each name checked."""
    backbones = parse_chain(spec, "coarse backbone")
    unknown = [name for name in backbones if name not in BACKBONES]
    if unknown:
        raise OrthonavError(
            f"coarse backbone {spec!r}: expected one of {', '.join(BACKBONES)}, or several joined "
            f"by '{FALLBACK}' (e.g. gradient{FALLBACK}trained)"
        )
    return backbones


def _lost_note(package: MapPackage, name: str) -> str:
    """How the fix source ``name`` answers a frame without a position prior on this map."""
    if package.manifest.get("global_index") is not None:
        return "frames without a position prior are searched around the map's global index"
    how = "searched by keypoints over every tile" if name == CASCADE else "rejected"
    return (
        f"the map has no global index: frames without a position prior are {how} "
        "(orthonav map index --method cnn: fast, and robust across dates)"
    )


def orthophoto_fix_source(
    name: str, orthophoto: GeoRaster, camera: Camera, work_dir: Path, alt_agl_m: float
) -> FixSource:
    """A fix source over an orthophoto alone, as a simulation without a map package asks for
    one: dense gradient correlation against it, or keypoints on a map package built from it in
    ``work_dir`` for ``alt_agl_m``."""
    if name == CORRELATION:
        return Corrector(orthophoto, camera, CorrectionConfig(backbone=GRADIENT))
    if name != KEYPOINTS:
        raise OrthonavError(f"fix source {name!r} over an orthophoto: expected {KEYPOINTS} or {CORRELATION}")
    tiling = TilingConfig(nominal_alt_m=alt_agl_m)
    package = build_map(orthophoto.path, work_dir / "map", camera, tiling, progress=False)
    return Localizer(package, camera)
