"""css_node start-up: load the model, classes, sensor model and (resumed or fresh) map; stale temp files;
kernel warm-up.

Fatal problems raise CssError (ModelError, ConfigError, SensorModelError, ...) for main() to report; a checkpoint
that cannot be used (also one fused with another sensor model than ``sensor_model``) is renamed aside
(``<name>.rejected-<time>``) and the map starts fresh; for another sensor model the warning says why and how to
keep both maps (a checkpoint per update).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..engine.classes import ClassSet, class_ids
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import SemanticMap
from ..engine.map_file import check_map_headers, read_map_info
from ..engine.sensor_model import NO_SENSOR_MODEL, SensorModel, shorten
from ..engine.similarity import Similarity
from ..engine.warmup import warm_up_kernels
from ..errors import ConfigError, CssError, MapError, ModelError, SensorModelError
from ..io.paths import resolve_data_path
from .params import DEFAULT_CLASSES, NodeParams, checkpoint_file, half_life


@dataclass
class Engine:
    """What the node maps with."""

    smap: SemanticMap
    classes: ClassSet
    model_path: Path
    checkpoint_path: Path | None
    resume_status: str


def checkpoint_path(params: NodeParams, fingerprint: str) -> Path | None:
    """Absolute checkpoint file for this model (None: checkpoints disabled)."""
    if not params.checkpoint_path:
        return None
    return Path(os.path.expanduser(checkpoint_file(params.checkpoint_path, fingerprint))).absolute()


def remove_stale_temp_files(path: Path) -> list[Path]:
    """Delete ``.<name>.*.tmp`` files left next to ``path`` by saves that were killed; returns them."""
    removed = []
    if path.parent.is_dir():
        for tmp in path.parent.glob(f".{path.name}.*.tmp"):
            try:
                tmp.unlink()
                removed.append(tmp)
            except OSError:
                pass
    return removed


def reject_aside(path: Path) -> Path | None:
    """Rename a refused checkpoint to ``<name>.rejected-<YYYYmmdd-HHMMSS>`` (None if that failed)."""
    aside = path.with_name(path.name + f".rejected-{time.strftime('%Y%m%d-%H%M%S')}")
    try:
        os.replace(path, aside)
        return aside
    except OSError:
        return None


def _fused_sensor_model(path: Path) -> str | None:
    """The sensor-model fingerprint a map file records ("" = the paper's update; None: unreadable)."""
    try:
        return read_map_info(path).sensor_model
    except (CssError, OSError):
        return None


def _fingerprint_of(model: SensorModel | None) -> str:
    return NO_SENSOR_MODEL if model is None else model.fingerprint


def keep_both_hint(params: NodeParams, ckpt: Path, aside: Path, fused_with: str, sensor_model: SensorModel | None) -> str:
    """Why a checkpoint of another update is set aside, and how to keep both maps (appended to the warning)."""
    old = f"sensor model {fused_with[:12]}" if fused_with else "the paper's update (no sensor model)"
    new = f"sensor model {sensor_model.fingerprint[:12]}" if sensor_model is not None else "the paper's update"
    tag = f"sm-{sensor_model.fingerprint[:12]}" if sensor_model is not None else "paper"
    template = Path(params.checkpoint_path)
    suggestion = template.with_name(f"{template.stem}_{tag}{template.suffix or '.npz'}")
    resume_old = f"with the sensor_model of fingerprint {fused_with[:12]}" if fused_with \
        else "with sensor_model:=''"
    return (f". Why: that map was fused with {old} and this node fuses with {new}; their evidence is in different "
            "units, so one map cannot continue the other. To keep both: give this update its own checkpoint "
            f"(-p checkpoint_path:={suggestion}) and rename {aside.name} back to {ckpt.name}; that map resumes "
            f"when the node runs {resume_old}")


def load_classes(params: NodeParams, log_warning: Callable[[str], None]) -> ClassSet:
    """The class set: num_classes > 0 with class_file left at its default (the demo's file) gives
    num_classes anonymous classes (another model must not get the demo's classes); a class_file that is
    set and a num_classes that contradicts it are a ConfigError naming both."""
    if params.class_file and params.num_classes > 0 and params.class_file == DEFAULT_CLASSES:
        log_warning(f"num_classes={params.num_classes} given and class_file left at the demo's default "
                    f"{DEFAULT_CLASSES}: using {params.num_classes} anonymous classes")
        return ClassSet.default(params.num_classes)
    if params.class_file:
        class_path = resolve_data_path(params.class_file)
        classes = ClassSet.from_yaml(class_path)
        if params.num_classes and params.num_classes != classes.num_classes:
            raise ConfigError(f"num_classes={params.num_classes} contradicts class_file={params.class_file} "
                              f"({class_path} defines {classes.num_classes} classes): drop one of them")
        return classes
    if params.num_classes > 0:
        return ClassSet.default(params.num_classes)
    raise ConfigError("set class_file or num_classes > 0")


def transient_class_ids(entries: list[str], classes: ClassSet) -> list[int]:
    """The class ids of ``transient_classes`` (:func:`css_ros.engine.classes.class_ids`).

    Raises:
        ConfigError: an entry that is no class name or id (naming it and the classes)."""
    return class_ids(entries, classes.names, "parameter transient_classes")


def change_kwargs(params: NodeParams, classes: ClassSet) -> dict[str, Any]:
    """The map's rules for a changing world (SemanticMap keyword arguments) from the parameters. evidence_half_life
    only when set (> 0): a fresh map then forgets at that rate, a resumed one from now on; when not set a fresh map
    does not forget and a resumed one keeps the half-life its file holds."""
    out: dict[str, Any] = dict(transient_classes=transient_class_ids(params.transient_classes, classes),
                               depth_tolerance=params.depth_tolerance,
                               depth_tolerance_relative=params.depth_tolerance_relative)
    if half_life(params) is not None:   # not given: a resumed map keeps its file's half-life (SemanticMap.load)
        out["evidence_half_life"] = half_life(params)
    return out


def check_exchange(params: NodeParams, smap: SemanticMap) -> None:
    """Refuse a map whose evidence decays (a half-life, from the parameter or its file) with the evidence exchange
    on: exchanged evidence must add up.

    Raises:
        ConfigError: naming the half-life and the exchange parameters."""
    exchange = params.publish_evidence or bool(params.evidence_in.strip())
    if smap.evidence_half_life is not None and exchange:
        raise ConfigError(f"the map has an evidence half-life ({smap.evidence_half_life:g} observations): its "
                          "evidence is no longer additive and cannot be exchanged; turn the evidence exchange off "
                          "(publish_evidence:=false, evidence_in:='') or start a map without a half-life")


def describe_changing_world(smap: SemanticMap, names: tuple[str, ...], params: NodeParams) -> str:
    """One start-up line: measured depth, transient classes, forgetting."""
    transient = ", ".join(f"{i}:{names[i]}" for i in smap.transient_classes) or "none"
    rules = smap.change_rules
    depth = (f"depth from {params.depth_topic} (tolerance max({rules.tol_abs:g} m, {rules.tol_rel:g} x depth))"
             if params.depth_topic else "no depth_topic")
    forget = "no forgetting"
    if smap.evidence_half_life is not None:
        forget = (f"evidence half-life {smap.evidence_half_life:g} observations"
                  + ("" if params.evidence_half_life > 0 else " (the checkpoint's)"))
    return f"changing world: {depth}; transient classes {transient}; {forget}"


def load_sensor_model(params: NodeParams, classes: ClassSet) -> SensorModel | None:
    """The ``sensor_model`` file checked against the class set (None: parameter empty, the paper's update).

    Raises:
        SensorModelError: one line naming the file and the parameter (missing, not a sensor model, other classes,
            invalid values, fingerprint mismatch); fatal for the node.
    """
    if not params.sensor_model:
        return None
    try:
        return SensorModel.load(resolve_data_path(params.sensor_model), classes.names)
    except SensorModelError as exc:
        raise SensorModelError(f"{exc} (parameter sensor_model={shorten(repr(params.sensor_model), 1024)})") from None


def describe_sensor_model(model: SensorModel | None) -> str:
    """One line naming the update in use, for the start-up log and diagnostics."""
    if model is None:
        return "sensor model: none (paper update)"
    return model.describe()


def checkpoint_fingerprint(path: Path) -> str | None:
    """The model fingerprint a checkpoint file records (None: no such file, or not a readable map file).

    Reads the members' headers and scalars only (:func:`~css_ros.engine.map_file.check_map_headers`); the full
    checks are SemanticMap.load's."""
    try:
        return check_map_headers(path).fingerprint
    except (CssError, OSError):
        return None


def newest_watched_model(params: NodeParams, model_path: Path, log_info: Callable[[str], None],
                         log_warning: Callable[[str], None]) -> tuple[Path, GaussianModel] | None:
    """The splat to start on instead of ``model_path`` after earlier swaps (docs/maps.md, "Live").

    With ``model_watch_dir``, ``resume`` and checkpoints on: the newest ``*.ply`` of the folder that is newer
    than ``model_path`` (modification time, the swap's own rule) and has a checkpoint recording its fingerprint,
    i.e. the splat an earlier run swapped to, whose map holds every frame fused since. Files are read newest
    first until one matches; unreadable ones are skipped. None: no such file (start on ``model_path``; a newer
    splat without a checkpoint is then swapped to by the running node as usual).
    """
    p = params
    if not (p.model_watch_dir and p.resume and p.checkpoint_path):
        return None
    folder = Path(p.model_watch_dir).expanduser()
    try:
        since = model_path.stat().st_mtime_ns
        files = sorted(((f.stat().st_mtime_ns, f) for f in folder.glob("*.ply") if f.is_file()), reverse=True)
    except OSError as exc:
        log_warning(f"model_watch_dir {folder} unreadable at start: {exc}; starting on model_path")
        return None
    for mtime, path in files:
        if mtime <= since or path.resolve() == model_path.resolve():
            continue
        try:
            model = GaussianModel.from_ply(path)
        except (CssError, OSError) as exc:
            log_warning(f"model_watch_dir: {path} unreadable at start ({exc}); skipped")
            continue
        ckpt = checkpoint_path(p, model.fingerprint)
        if ckpt is not None and checkpoint_fingerprint(ckpt) == model.fingerprint:
            log_info(f"starting on {path} (model_watch_dir, newer than model_path {model_path}): the map was "
                     f"moved to it by an earlier run and its checkpoint {ckpt} holds it")
            return path, model
    return None


def load_engine(params: NodeParams, log_info: Callable[[str], None],
                log_warning: Callable[[str], None]) -> Engine:
    """Model, classes and map (resumed from the checkpoint when it matches, else fresh). With
    ``model_watch_dir``, the model may be a newer splat of that folder (:func:`newest_watched_model`)."""
    p = params
    model_path = resolve_data_path(p.model_path)
    try:
        found = model_path.is_file()
    except OSError as exc:  # e.g. a file name too long
        raise ModelError(f"model file {shorten(str(model_path), 1024)} cannot be read: {exc.strerror or exc} "
                         f"(parameter model_path={shorten(repr(p.model_path), 1024)})") from None
    if not found:
        raise ModelError(f"model file not found: {shorten(str(model_path), 1024)} (parameter model_path="
                         f"{shorten(repr(p.model_path), 1024)})")
    model = GaussianModel.from_ply(model_path)
    watched = newest_watched_model(p, model_path, log_info, log_warning)
    if watched is not None:
        model_path, model = watched
    classes = load_classes(p, log_warning)
    C = classes.num_classes
    sensor_model = load_sensor_model(p, classes)   # before the checkpoint: a bad file never renames it aside
    # sensor_model is always passed (None included): SemanticMap.load then refuses a checkpoint fused with another
    # update, and a prior-only checkpoint takes this node's sensor model
    kwargs: dict[str, Any] = dict(ignore_label=p.ignore_label, unknown_threshold=p.unknown_threshold,
                                  backend=p.backend, sensor_model=sensor_model,
                                  depth_scale=Similarity.from_params(p.splat_to_map).scale,
                                  **change_kwargs(p, classes))
    ckpt = checkpoint_path(p, model.fingerprint)
    smap = None
    status = "fresh map"
    if ckpt is not None:
        removed = remove_stale_temp_files(ckpt)
        if removed:
            log_info(f"removed {len(removed)} temporary file(s) of interrupted saves next to {ckpt}")
    if ckpt is not None and p.resume and ckpt.exists():
        try:
            smap = SemanticMap.load(ckpt, model, expected_classes=C, **kwargs)
            if smap.num_classes != C:
                raise MapError(f"it has {smap.num_classes} classes, the class setup has {C}")
            status = f"resumed from {ckpt} ({smap.frames_observed} frames observed)"
            if (smap.prior, smap.background) != (p.prior, p.background):
                log_warning(f"checkpoint prior/background ({smap.prior:g}, {smap.background:g}) override the "
                            f"parameters ({p.prior:g}, {p.background:g})")
        except MapError as exc:
            smap = None
            fused_with = _fused_sensor_model(ckpt)
            aside = reject_aside(ckpt)
            status = f"starting fresh: checkpoint refused: {exc}" + (f"; kept it as {aside}" if aside else "")
            hint = ""
            if aside is not None and fused_with is not None and fused_with != _fingerprint_of(sensor_model):
                hint = keep_both_hint(p, ckpt, aside, fused_with, sensor_model)
            log_warning(status + hint)
    elif ckpt is not None and p.resume:
        status = f"fresh map (no checkpoint at {ckpt} yet)"
    if smap is None:
        smap = SemanticMap(model, num_classes=C, prior=p.prior, background=p.background, **kwargs)
    check_exchange(p, smap)
    return Engine(smap, classes, model_path, ckpt, status)


def warm_up(smap: SemanticMap, params: NodeParams, log_info: Callable[[str], None]) -> None:
    """Compile the kernels on a tiny throwaway map (the node's map is not touched) so that the first real
    frame is not slowed by JIT compilation.

    Raises:
        CssError: the warm-up failed (one line naming cause and fix). Fatal for the node (``cannot start``):
            every frame would fail the same way, so running on would only drop them one by one; start with
            ``warmup: false`` to skip the check.
    """
    seconds = warm_up_kernels(params.backend, smap.num_classes)
    log_info(f"rasteriser warm-up ({params.backend}) took {seconds:.2f} s")
