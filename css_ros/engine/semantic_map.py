"""The CSS semantic map: Dirichlet concentrations per Gaussian, closed-form update (SPEC §4),
probabilistic rendering (SPEC §5), image-level uncertainty (SPEC §6) and atomic persistence."""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Literal, Mapping, Sequence

import numpy as np

from ..errors import MapError, SensorModelError
from .backends import make_backend
from .final_form import RenderSettings, check_outputs
from .label_input import FrameLabels, check_frame_labels
from .change_rules import (DEFAULT_DEPTH_TOLERANCE, DEFAULT_DEPTH_TOLERANCE_RELATIVE, check_half_life,
                           make_rules)
from .sensor_model import NO_SENSOR_MODEL
from .field3d import FieldIndex, FieldQuery, GaussianSemantics, gaussian_semantics, query_field
from .spec import (DEFAULT_BACKGROUND, DEFAULT_IGNORE_LABEL, DEFAULT_MIN_EVIDENCE, DEFAULT_PRIOR,
                   DEFAULT_QUERY_BACKGROUND_WEIGHT, DEFAULT_UNKNOWN_THRESHOLD)
from .spec import MAX_FRAMES
from . import map_args, view_args
from .map_args import MAX_CONCENTRATION
from .map_file import MapContents, SourceEvidence, read_map_file, write_map_file

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel
    from .info_gain import SelectedViews
    from .final_form import FrameImages
    from .raster_backend import UpdateCounts
    from .sensor_model import SensorModel, SoftLabels


def _update_name(fingerprint: str) -> str:
    """How logs name the update a map was fused with."""
    return f"sensor model {fingerprint[:12]}" if fingerprint else "the paper's update (no sensor model)"


BackendName = Literal["numba", "torch", "cuda"]


@dataclass
class RenderedView:
    """Everything rendered for one camera view (H, W = the camera's image size).

    The image fields hold numpy arrays in their final dtypes, made by the backend (on the GPU for backend cuda)
    and copied to the host once per view. An image not asked for (``outputs`` of :meth:`SemanticMap.observe` /
    :meth:`SemanticMap.render`) is None and costs no copy; u_var and u_exp are always there. The arrays belong
    to the view: later frames never change them.

    Attributes:
        labels: (H, W) int32 argmax class per pixel; ``ignore_label`` where the background weight
            kappa_b exceeds ``unknown_threshold``.
        expectation: (H, W) float32 E_i of the argmax class (SPEC §5).
        variance: (H, W) float32 Var_i of the argmax class (SPEC §5).
        background: (H, W) float32 kappa_b, the weight of the background Dirichlet.
        evidence: (H, W) float32 kappa-weighted Dirichlet total sum_n kappa_in S_n + kappa_b S_b
            (the paper's observation-count confidence baseline; larger = more observed).
        rgb: (H, W, 3) uint8 colour render.
        u_var: geometric mean of the variance image (SPEC §6).
        u_exp: one minus the mean of the expectation image (SPEC §6).
        probabilities: (H, W, C) float32 full per-class E_i^c, only when requested.
        depth: (H, W) float32 expected depth sum_n kappa_in z_n / sum_n kappa_in of the rendered Gaussians
            (camera z, metres: splat units times the map's ``depth_scale``); NaN where nothing is rendered.
        confidence: (H, W) float32 calibrated probability that ``labels`` is right (the sensor model's
            :class:`~css_ros.engine.sensor_model.ConfidenceMap` of E and evidence; 0 where the label is
            ``ignore_label``), or None when the map has no calibrated confidence.
        surprise: (H, W) float32, only from :meth:`SemanticMap.observe` with ``"surprise"`` among its ``outputs``
            (not a default output): 1 - E[theta_y] of the observed label y under
            the map before this frame's update (0 = the map was sure of it, near 1 = the map expected something else:
            a segmentation error or a changed world); NaN where the pixel has no label
            (:mod:`css_ros.engine.change_rules`). None otherwise (query renders, default outputs).
    """

    labels: np.ndarray
    expectation: np.ndarray
    variance: np.ndarray
    background: np.ndarray
    evidence: np.ndarray
    rgb: np.ndarray
    u_var: float
    u_exp: float
    probabilities: np.ndarray | None = None
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None
    surprise: np.ndarray | None = None


@dataclass(frozen=True)
class UpdateStats:
    """Pixel counts of one update: used (labelled, weight > 0, voted), ignored (ignore value or zero
    confidence), out_of_range (ids >= C or negative, treated as ignored), with a sensor model no_depth (used
    pixels that no Gaussian covers: they have no rendered depth and add nothing), transient (labelled with a
    transient class: no evidence) and occluded (measured depth nearer than the map's rendered depth by more than the
    tolerance: no evidence; :mod:`css_ros.engine.change_rules`). used + ignored + out_of_range + transient +
    occluded = the image's pixels."""

    used: int
    ignored: int
    out_of_range: int
    no_depth: int = 0
    transient: int = 0
    occluded: int = 0


class SemanticMap:
    """Dirichlet semantic state over the Gaussians of a pretrained splat model.

    Concentrations are float64: a long run adds many small kappa-weighted counts (often < 1e-3) to
    totals that reach 1e4 and more, which float32 would round away (its spacing at 1e4 is ~1e-3).
    The (N, C) array costs 8 N C bytes (152 MB for 1M Gaussians x 19 classes).

    Args:
        model: the pretrained splat (map frame).
        num_classes: C.
        prior: alpha_0, initial concentration of every class of every Gaussian (> 0).
        background: alpha_b, concentration per class of the background Dirichlet (> 0).
        ignore_label: label value meaning "no label" in inputs and "unknown" in rendered labels.
        unknown_threshold: rendered pixels whose background weight kappa_b exceeds this get
            ``ignore_label`` (default 0.5: the pixel is mostly empty space). Use 1.0 to never do so.
        backend: "numba" (compiled CPU kernels, default), "torch" (plain PyTorch twin) or "cuda"
            (numba-cuda kernels, concentrations kept on the GPU; docs/cuda.md).
        background_rgb: colour behind all Gaussians, RGB in [0, 1].
        device: GPU index for backend "cuda" (default: the current device).
        sensor_model: the segmenter's sensor model (docs/spec.md "Sensor model"): each labelled pixel adds
            kappa * confidence * w(y, d) * p(. | y, d) instead of kappa * confidence * onehot(y). None (default):
            the paper's update, bit for bit.
        depth_scale: metres per splat unit (the scale of ``splat_to_map``): the sensor model's depth bins
            and ``RenderedView.depth`` are in metres.
        transient_classes: class ids whose pixels never add evidence (people, animals, vehicles in motion); they still
            count in the input statistics (``UpdateStats.transient``).
        evidence_half_life: None (default: the paper's update, evidence adds up forever) or h > 0 observations: each
            Gaussian that receives evidence from a frame first has its accumulated evidence alpha - alpha_0 multiplied
            by 2^(-1/h). Such a map's evidence is not additive: merges and evidence exchange refuse it.
        depth_tolerance, depth_tolerance_relative: the measured-depth tolerance max(depth_tolerance m,
            depth_tolerance_relative x depth) of ``observe(..., depth=...)`` (:mod:`css_ros.engine.change_rules`).
    Raises:
        MapError: an argument of the wrong type or outside its bounds (:mod:`css_ros.engine.map_args`: C in
            1..MAX_CLASSES, prior and background in (0, MAX_CONCENTRATION], the bounds a map file is loaded with).
    """

    def __init__(self, model: "GaussianModel", num_classes: int, prior: float = DEFAULT_PRIOR,
                 background: float = DEFAULT_BACKGROUND, ignore_label: int = DEFAULT_IGNORE_LABEL,
                 unknown_threshold: float = DEFAULT_UNKNOWN_THRESHOLD,
                 backend: BackendName = "numba", background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 device: int | None = None, sensor_model: "SensorModel | None" = None,
                 depth_scale: float = 1.0, transient_classes: Sequence[int] | None = None,
                 evidence_half_life: float | None = None, depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE,
                 depth_tolerance_relative: float = DEFAULT_DEPTH_TOLERANCE_RELATIVE) -> None:
        self.model = map_args.check_model(model)
        self.num_classes = map_args.check_num_classes(num_classes)
        self.prior = map_args.check_concentration(prior, "prior")
        self.background = map_args.check_concentration(background, "background")
        self.ignore_label = map_args.check_ignore_label(ignore_label)
        self.unknown_threshold = map_args.check_unknown_threshold(unknown_threshold)
        self.background_rgb = map_args.check_background_rgb(background_rgb)
        depth_scale = map_args.check_depth_scale(depth_scale)
        if not isinstance(backend, str):
            raise MapError(f"backend must be a name (numba, torch or cuda), got {type(backend).__name__}")
        cuda_index = isinstance(device, (int, np.integer)) and not isinstance(device, bool) and device >= 0
        if device is not None and not (backend == "cuda" and cuda_index):
            raise MapError(f"device must be None or, with backend 'cuda', a GPU index >= 0; got {device!r} with "
                           f"backend {backend!r}")
        self.backend_name = backend
        self._backend = make_backend(backend, model, **({} if device is None else {"device": int(device)}))
        self._concentrations = np.full((model.num_gaussians, self.num_classes), self.prior, dtype=np.float64)
        self.depth_scale = float(depth_scale)
        self.evidence_half_life = check_half_life(evidence_half_life)
        #: the rules for a changing world the backends apply (:mod:`css_ros.engine.change_rules`)
        self.change_rules = make_rules(self.num_classes, transient_classes, self.evidence_half_life, depth_tolerance,
                                       depth_tolerance_relative, self.depth_scale, self.prior)
        #: pixel counts of the latest update (``observe`` returns the view, this keeps its counts); None before
        self.last_update: UpdateStats | None = None
        self._sensor_model: SensorModel | None = None
        self._soft: SoftLabels | None = None
        self.frames_observed = 0
        #: fingerprint of the sensor model the evidence was fused with ("" = the paper's update); kept from the
        #: file by :meth:`load`, compared by merges (maps fused with different sensor models are not merged)
        self.fused_sensor_model = NO_SENSOR_MODEL
        self.sensor_model = sensor_model
        #: origin ids of the sources whose evidence this map holds (css_node's own and received ones), sorted
        self.sources: list[str] = []
        #: origin id under which css_node publishes this map's own evidence ("": none / not known)
        self.evidence_origin = ""
        #: epoch under which css_node published the own evidence when this map was saved (0: none / not known)
        self.evidence_epoch = 0
        #: evidence of other nodes held in ``concentrations``, per origin id (css_node's evidence ledger keeps it)
        self.received: Mapping[str, SourceEvidence] = {}
        self._field_index: FieldIndex | None = None  # SPEC §9 spatial index, built on first query

    def __repr__(self) -> str:
        """One line: size, backend, frames fused and the update's sensor model; never the arrays."""
        fp = self.sensor_fingerprint
        return (f"SemanticMap({self.model.num_gaussians} Gaussians x {self.num_classes} classes, "
                f"backend {self.backend_name}, {self.frames_observed} frames observed, prior {self.prior:g}, "
                f"{'sensor model ' + fp[:12] if fp else 'paper update'})")

    # ------------------------------------------------------------------ state
    @property
    def sensor_model(self) -> "SensorModel | None":
        """The active sensor model (None: the paper's update)."""
        return self._sensor_model

    @sensor_model.setter
    def sensor_model(self, model: "SensorModel | None") -> None:
        from .sensor_model import SensorModel

        if model is not None and not isinstance(model, SensorModel):
            raise SensorModelError(f"sensor_model must be a SensorModel (SensorModel.load(path)) or None, got "
                                   f"{type(model).__name__}")
        if model is not None and model.num_classes != self.num_classes:
            raise SensorModelError(f"{model.source or 'sensor model'} is for {model.num_classes} classes, the map "
                                   f"has {self.num_classes}")
        self._sensor_model = model
        self._soft = None if model is None else model.soft_labels(self.depth_scale)
        if self.frames_observed == 0:
            self.fused_sensor_model = self.sensor_fingerprint

    @property
    def sensor_fingerprint(self) -> str:
        """Fingerprint of the update's sensor model ("" = the paper's update), as stored in map files."""
        return NO_SENSOR_MODEL if self._sensor_model is None else self._sensor_model.fingerprint

    @property
    def concentrations(self) -> np.ndarray:
        """(N, C) float64 alpha, for writing: a backend that keeps them on a device brings this host
        array up to date first and treats it as modified afterwards (re-uploads it). Read through
        :attr:`concentrations_readonly` when not writing."""
        return self._backend.host_write(self._concentrations)

    @concentrations.setter
    def concentrations(self, value: np.ndarray) -> None:
        self._concentrations = value

    @property
    def concentrations_readonly(self) -> np.ndarray:
        """(N, C) float64 alpha, up to date, read-only (no re-upload to a device afterwards)."""
        return self._backend.host_read(self._concentrations)

    def reset(self) -> None:
        """Forget every observation: all concentrations back to the prior."""
        self.concentrations[...] = self.prior
        self.frames_observed = 0
        for src in self.received.values():   # their evidence is gone too; each must re-state it by a snapshot
            src.evidence[...] = 0.0
            src.in_step = False
        self.fused_sensor_model = self.sensor_fingerprint

    def _background_moments(self) -> tuple[float, float, float]:
        c = self.num_classes
        s_b = c * self.background
        e_b = 1.0 / c
        return e_b, e_b * (1.0 - e_b) / (1.0 + s_b), s_b

    # ------------------------------------------------------------------ inputs
    @property
    def transient_classes(self) -> list[int]:
        """Class ids whose pixels never add evidence."""
        return self.change_rules.transient_ids()

    def _frame_labels(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None,
                      depth: np.ndarray | None = None, want_surprise: bool = False) -> FrameLabels:
        """The frame's labels, confidence and measured depth checked (shape, dtype) and handed on as they came
        (:mod:`css_ros.engine.label_input`): the backend's compiled pass applies the label rule and counts."""
        return check_frame_labels(labels, confidence, (camera.height, camera.width), self.num_classes,
                                  self.ignore_label, depth, self.change_rules, want_surprise)

    # ------------------------------------------------------------------ engine
    def _update_frame(self, frame: Any, camera: "Camera", labels: np.ndarray,
                      confidence: np.ndarray | None, depth: np.ndarray | None = None) -> "UpdateCounts":
        """Update with one frame; the counts may still be on a device (:meth:`_finish_update` reads them)."""
        inputs = self._frame_labels(camera, labels, confidence, depth)
        pending = self._backend.update(frame, inputs, self._concentrations, self._soft)
        self.frames_observed += 1
        return pending

    def _finish_update(self, pending: "UpdateCounts") -> UpdateStats:
        used, ignored, out_of_range, no_depth, transient, occluded = pending.get()
        stats = UpdateStats(used, ignored, out_of_range, no_depth if self._soft is not None else 0, transient,
                            occluded)
        self.last_update = stats
        return stats

    def render_settings(self, outputs: Iterable[str] | None = None, probabilities: bool = False) -> RenderSettings:
        """What a backend needs to deliver a view's outputs in final form (:mod:`css_ros.engine.final_form`).

        Raises:
            InputError: an unknown output name."""
        e_b, v_b, s_b = self._background_moments()
        bg = self.background_rgb
        return RenderSettings(e_b, v_b, s_b, (float(bg[0]), float(bg[1]), float(bg[2])), self.unknown_threshold,
                              self.ignore_label, self.depth_scale,
                              None if self._sensor_model is None else self._sensor_model.confidence,
                              check_outputs(outputs), bool(probabilities))

    @staticmethod
    def _view(img: "FrameImages", surprise: np.ndarray | None = None) -> RenderedView:
        return RenderedView(labels=img.labels, expectation=img.expectation, variance=img.variance,  # type: ignore[arg-type]
                            background=img.background, evidence=img.evidence, rgb=img.rgb,  # type: ignore[arg-type]
                            u_var=img.u_var, u_exp=img.u_exp, probabilities=img.probabilities, depth=img.depth,
                            confidence=img.confidence, surprise=surprise)

    # ------------------------------------------------------------------ public API
    def update(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None = None,
               depth: np.ndarray | None = None) -> UpdateStats:
        """Fuse one segmentation (SPEC §4): alpha_n^c += sum_i kappa_in y_i^c at ``camera``'s pose.

        Args:
            camera: pose (T_map_cam of the optical frame) and intrinsics of the segmented image.
            labels: (H, W) integer class ids; ``ignore_label`` and ids >= C (or < 0) add nothing.
            confidence: optional (H, W) float weights in [0, 1] (NaN counts as 0); y_i = conf_i * onehot.
            depth: optional (H, W) measured depth in metres along the optical axis, registered to the labels (NaN, 0
                or inf: no measurement): pixels nearer than the map's surface and Gaussians in front of the measured
                surface add no evidence (:mod:`css_ros.engine.change_rules`).
        Raises:
            InputError: wrong shape or dtype (confidence: real numbers; masked arrays refused).
            CameraError: ``camera`` is not a Camera.
        """
        frame = self._backend.prepare(map_args.check_camera(camera, "update"))
        return self._finish_update(self._update_frame(frame, camera, labels, confidence, depth))

    def observe(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None = None,
                probabilities: bool = False, outputs: Iterable[str] | None = None,
                depth: np.ndarray | None = None) -> RenderedView:
        """SPEC §7 per observed frame: rasterise once, update, then render at the same pose.

        ``outputs``: the images to deliver (names of :data:`css_ros.engine.final_form.IMAGE_OUTPUTS`; None = all but
        ``surprise``); the others are None in the view and cost no copy from the device. ``surprise`` is made by the
        update (before it changes the map), only when named. ``depth``: the measured depth as in :meth:`update`."""
        settings = self.render_settings(outputs, probabilities)
        camera = map_args.check_camera(camera, "observe")
        inputs = self._frame_labels(camera, labels, confidence, depth, "surprise" in settings.outputs)
        img, pending = self._backend.observe_view(camera, inputs, self._concentrations, self._soft, settings)
        self.frames_observed += 1
        self._finish_update(pending)  # a device backend's counts came with the view's one copy
        return self._view(img, pending.surprise())

    def render(self, camera: "Camera", probabilities: bool = False,
               outputs: Iterable[str] | None = None) -> RenderedView:
        """Render labels, E, Var, colour and U at ``camera`` without changing the map (query view); ``outputs`` as
        in :meth:`observe`."""
        settings = self.render_settings(outputs, probabilities)
        camera = map_args.check_camera(camera, "render")
        return self._view(self._backend.render_query(camera, self._concentrations, settings))

    def score_views(self, cameras: Sequence["Camera"], importance: np.ndarray | None = None,
                    pixel_scale: float = 1.0) -> np.ndarray:
        """U_var, U_exp (SPEC §6) and the information gain of many query views, e.g. the candidates of an
        active-perception planner: U_var and U_exp are the same numbers as ``render(cam).u_var`` / ``.u_exp``, without
        building the images, with the Dirichlet moments computed once per batch of views.

        info_gain (docs/spec.md "Information gain of a view") is the expected drop of the map's summed class variance
        if the view were observed: each Gaussian's evidence from the view (kappa mass, times the sensor model's net
        vote weight at the pixel's label and depth when one is set) through the closed form of
        :mod:`css_ros.engine.info_gain`, weighted by ``importance`` ((N,) >= 0 per Gaussian; None = 1, see
        :meth:`task_importance`, :meth:`class_importance`). ``pixel_scale``: pixels of the image that would be
        observed per scored pixel (1 / f**2 for candidates rendered at ``cam.scaled(f)``): the evidence counts as the
        full-resolution observation would add it. Every backend computes the gain (cuda on the device).

        Returns:
            (len(cameras), 3) float64, columns (U_var, U_exp, info_gain), in the order of ``cameras`` (columns 0 and
            1 are what earlier versions returned).
        """
        cameras = view_args.check_cameras(cameras, "score_views")
        imp = self._check_importance(importance)
        scale = self._check_pixel_scale(pixel_scale)
        e_b, v_b, s_b = self._background_moments()
        return self._backend.score_views(list(cameras), self._concentrations, e_b, v_b, s_b, self._mass_weights(),
                                         imp, scale)

    @staticmethod
    def _check_pixel_scale(pixel_scale: float) -> float:
        return view_args.check_pixel_scale(pixel_scale)

    def select_views(self, cameras: Sequence["Camera"], k: int, importance: np.ndarray | None = None,
                     pixel_scale: float = 1.0) -> "SelectedViews":
        """A greedy batch of ``k`` views for a planner that will visit several: the first has the largest info gain;
        each next one the largest gain given the views before it were observed (their evidence added to the map's
        moments as the expected observation would add it: alpha_n += m_n E[theta_n]), so views that see the same
        surfaces as an earlier pick lose their shared gain. The map is not changed. ``pixel_scale`` as in
        :meth:`score_views`. At most ``view_args.MAX_SELECT_CANDIDATES`` (1024) cameras per call: each candidate's
        visible Gaussians and evidence are kept for the greedy re-scoring (memory linear in the candidates); more are
        refused (CameraError).

        Returns:
            :class:`~css_ros.engine.info_gain.SelectedViews` (indices into ``cameras`` in the order chosen, and each
            one's gain when chosen). Fewer than ``k`` when there are fewer cameras.
        Raises:
            MapError: bad k, importance or pixel_scale, or more than view_args.MAX_SELECT_CANDIDATES cameras (named).
        """
        cameras = view_args.check_cameras(cameras, "select_views", view_args.MAX_SELECT_CANDIDATES)
        k = view_args.check_k(k)
        imp = self._check_importance(importance)
        scale = self._check_pixel_scale(pixel_scale)
        e_b, v_b, s_b = self._background_moments()
        return self._backend.select_views(list(cameras), self._concentrations, e_b, v_b, s_b, self._mass_weights(),
                                          imp, scale, int(k))

    def task_importance(self, task_cameras: Sequence["Camera"]) -> np.ndarray:
        """(N,) float64 per-Gaussian importance = its kappa mass summed over ``task_cameras`` (the views a robot
        will later take or act from), for ``score_views`` / ``select_views``: surfaces no task view sees count 0."""
        task_cameras = view_args.check_cameras(task_cameras, "task_importance")
        imp = np.zeros(self.model.num_gaussians)
        unit = (np.array([0.0, 1.0]), np.ones(self.num_classes))
        e_b, v_b, s_b = self._background_moments()
        for ids, mass in self._backend.view_masses(list(task_cameras), self._concentrations, e_b, v_b, s_b, unit):
            np.add.at(imp, ids, mass)
        return imp

    def class_importance(self, class_id: int) -> np.ndarray:
        """(N,) float64 per-Gaussian importance = E[theta_n^c], the map's probability that Gaussian n is of class
        ``class_id`` (views of surfaces likely to be that class score higher)."""
        class_id = view_args.check_class_id(class_id, self.num_classes)
        conc = self.concentrations_readonly
        return conc[:, int(class_id)] / conc.sum(axis=1)

    def _check_importance(self, importance: np.ndarray | None) -> np.ndarray | None:
        return view_args.check_importance(importance, self.model.num_gaussians)

    def _mass_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(depth-bin edges in splat units, net vote weight per (label, bin)) of one more observation: without a
        sensor model one bin and weight 1 (a pixel's kappa); with one, the row's share on the label minus its mean
        share on the other classes (w p - w (1 - p) / (C - 1) for a symmetric vote; w for a one-hot one)."""
        if self._soft is None:
            return np.array([0.0, 1.0]), np.ones(self.num_classes)
        table = self._soft.table
        c, nb = self.num_classes, self._soft.num_bins
        labels = np.repeat(np.arange(c), nb)
        own = table[np.arange(c * nb), labels]
        others = (table.sum(axis=1) - own) / max(c - 1, 1)
        return self._soft.edges, np.ascontiguousarray(np.maximum(own - others, 0.0))

    # ------------------------------------------------------------------ the map in 3D (SPEC §9)
    def gaussian_semantics(self, min_evidence: float = DEFAULT_MIN_EVIDENCE) -> GaussianSemantics:
        """Label, E and Var of the label, S_n and the observed flag of every Gaussian (SPEC §9).

        Unobserved Gaussians (S_n - C α_0 < ``min_evidence``) get ``ignore_label``.
        """
        min_evidence = map_args.check_real(min_evidence, "min_evidence")
        return gaussian_semantics(self.concentrations_readonly, self.prior, min_evidence, self.ignore_label)

    def query_points(self, xyz: np.ndarray,
                     background_weight: float = DEFAULT_QUERY_BACKGROUND_WEIGHT) -> FieldQuery:
        """The continuous semantic field at points (SPEC §9), without changing the map.

        Args:
            xyz: (M, 3) points in the map frame, metres.
            background_weight: w_b of the background Dirichlet.
        Returns:
            :class:`FieldQuery` (labels (M,) int32 with ``ignore_label`` where κ_b > ``unknown_threshold``,
            expectation and variance (M, C) float32, background κ_b (M,) float32).
            The spatial index of the model is built on the first call (O(N)) and reused.
        Raises:
            InputError: points not an (M, 3) array of real numbers, more than ``map_args.MAX_QUERY_VALUES`` / C
                points, or a background weight that is not a positive finite number.
        """
        xyz = map_args.check_query_points(xyz, self.num_classes)
        background_weight = map_args.check_background_weight(background_weight)
        if self._field_index is None:
            self._field_index = FieldIndex.from_model(self.model)
        e_b, v_b, _ = self._background_moments()
        return query_field(self._field_index, self.concentrations_readonly, xyz, background_weight, (e_b, v_b),
                           self.unknown_threshold, self.ignore_label)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the map as a versioned ``.npz`` of plain arrays, atomically.

        The file is written to a temporary name in the same directory, flushed and fsync'ed, then
        renamed over ``path``: a crash at any moment leaves either the old or the new file intact. The file gets the
        mode a plain ``open()`` gives (0666 less the umask).

        Raises:
            MapError (naming ``path``): a path that is no str/PathLike, holds NUL or is a directory; a map that
                :meth:`load` would refuse (concentrations not finite or outside (0, MAX_CONCENTRATION], frames
                beyond MAX_FRAMES: nothing is written); the file system's refusal (permission, name too long, disk
                full: the old file stays).
        """
        path = map_args.check_map_path(path, reading=False)
        conc = self.concentrations_readonly
        if not (np.all(np.isfinite(conc)) and np.all(conc > 0) and np.all(conc <= MAX_CONCENTRATION)):
            raise MapError(f"cannot save the map to {path}: its concentrations are not all finite and in (0, "
                           f"{MAX_CONCENTRATION:g}] (a map file must be loadable)")
        if not 0 <= self.frames_observed <= MAX_FRAMES:
            raise MapError(f"cannot save the map to {path}: frames_observed={self.frames_observed} outside "
                           f"[0, {MAX_FRAMES}]")
        try:
            write_map_file(path, MapContents(
                fingerprint=self.model.fingerprint, concentrations=conc, prior=self.prior, background=self.background,
                frames_observed=self.frames_observed, sources=self.sources, sensor_model=self.fused_sensor_model,
                evidence_origin=self.evidence_origin, evidence_epoch=self.evidence_epoch, received=self.received,
                evidence_half_life=self.evidence_half_life))
        except OSError as exc:
            raise MapError(f"cannot save the map to {path}: {exc.strerror or exc}") from exc
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str], model: "GaussianModel", expected_classes: int | None = None,
             **kwargs: Any) -> "SemanticMap":
        """Load a map saved by :meth:`save` onto ``model``.

        Every member's declared dtype, shape and size is checked from the npy headers before any data
        is read (no pickles, no decompression bombs, no huge allocations). ``expected_classes``: refuse
        a map with another number of classes before reading it. Extra keyword arguments
        (ignore_label, unknown_threshold, backend, ...) go to the constructor; prior, background and
        num_classes come from the file, and so does ``evidence_half_life`` unless given (a map keeps forgetting at
        the rate it was fused with; passing another one changes it from now on).
        Raises:
            MapError (naming ``path``): a path that does not exist or is not a regular file, prior /
                background / num_classes passed as arguments (they come from the file), a bad
                ``expected_classes``; unreadable/corrupt/crafted file (also a corrupt compressed
                stream), unknown format version, a map of another model ("this map belongs to model
                <fingerprint>, not <model file>"), or invalid values.
        """
        path = map_args.check_map_path(path, reading=True)
        map_args.check_model(model)
        if expected_classes is not None:
            expected_classes = map_args.check_num_classes(expected_classes, "expected_classes")
        fixed = sorted({"prior", "background", "num_classes"} & set(kwargs))
        if fixed:
            raise MapError(f"load takes {', '.join(fixed)} from the map file, not as an argument")
        f = read_map_file(path, model, expected_classes)
        kwargs.setdefault("evidence_half_life", f.evidence_half_life)
        smap = cls(model, f.num_classes, prior=f.prior, background=f.background, **kwargs)
        has_evidence = bool(np.any(f.concentrations != f.prior))
        if "sensor_model" in kwargs and f.sensor_model != smap.sensor_fingerprint and has_evidence:
            raise MapError(f"map file {path} was fused with {_update_name(f.sensor_model)}, this map uses "
                           f"{_update_name(smap.sensor_fingerprint)}: their evidence is not in the same units (start a new "
                           "map, or use the sensor model it was made with)")
        smap.concentrations[...] = f.concentrations
        smap.frames_observed = f.frames_observed
        smap.sources = f.sources
        smap.evidence_origin = f.evidence_origin
        smap.evidence_epoch = f.evidence_epoch
        smap.received = f.received
        # a map holding only the prior carries no evidence of any update: it takes the sensor model the caller names
        empty = "sensor_model" in kwargs and not has_evidence
        smap.fused_sensor_model = smap.sensor_fingerprint if empty else f.sensor_model
        return smap
