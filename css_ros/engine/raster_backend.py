"""The backend contract: what SemanticMap needs from a rasteriser (numba, torch, cuda implement it).

Only :mod:`.backends` (the registry) knows every backend; each backend module imports this contract and nothing
of the others.
"""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from .final_form import FrameImages, RenderSettings, finalize_host, image_uncertainty
from .label_input import NUM_COUNTS

if TYPE_CHECKING:
    from .buffers import RenderBuffers
    from .camera import Camera
    from .info_gain import SelectedViews
    from .label_input import FrameLabels
    from .sensor_model import SoftLabels


class UpdateCounts:
    """Pixel counts of one update (used, ignored, out of range, no depth, transient, occluded:
    :data:`~css_ros.engine.label_input.NUM_COUNTS`) and, when asked for (``FrameLabels.want_surprise``), the (H, W)
    float32 surprise image, as a backend hands them over: the CPU's are ready; a device backend's may arrive with the
    next view's one copy (:meth:`get` then costs nothing) or are fetched by :meth:`get` (one synchronisation)."""

    def __init__(self, counts: "np.ndarray | None" = None, surprise: "np.ndarray | None" = None) -> None:
        self._counts = None if counts is None else tuple(int(v) for v in np.asarray(counts)[:NUM_COUNTS])
        self._surprise = surprise

    def get(self) -> tuple[int, int, int, int, int, int]:
        """(used, ignored, out_of_range, no_depth, transient, occluded)."""
        assert self._counts is not None and len(self._counts) == NUM_COUNTS
        return self._counts  # type: ignore[return-value]

    def surprise(self) -> "np.ndarray | None":
        """The (H, W) float32 surprise image (1 - E[theta_y] under the map before the update, NaN without a label),
        or None when it was not asked for (:mod:`css_ros.engine.change_rules`)."""
        return self._surprise


class RasterBackend(ABC):
    """What SemanticMap needs from a rasteriser (the backend contract). ``frame`` is the backend's own
    per-view state (projection + tile bins), computed once by :meth:`prepare` and reused by update and
    render. The concentrations are SemanticMap's host array (N, C) float64; a backend that keeps a copy
    on a device (cuda) overrides :meth:`host_read` / :meth:`host_write` to keep the two coherent.

    :meth:`render_view` (final outputs), :meth:`score_views` and :meth:`select_views` have host defaults built on
    :meth:`render` and :meth:`score_images`; a backend overrides them where it can do better (cuda: on the device).
    """

    @abstractmethod
    def prepare(self, camera: "Camera") -> Any: ...

    @abstractmethod
    def update(self, frame: Any, inputs: "FrameLabels", concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> "UpdateCounts":
        """concentrations[n, c] += sum_i kappa_in y_i^c, each pixel's vote given by
        :func:`~css_ros.engine.label_input.pixel_vote` of its label and confidence as they came in (``inputs``).

        With ``soft`` (a sensor model, docs/spec.md "Sensor model"), y_i^c = weight_i * table[label_i * B + b_i, c]
        with b_i the depth bin of the pixel's expected depth sum kappa z / sum kappa. ``inputs.depth`` and
        ``inputs.rules`` (transient classes, measured depth, forgetting) and ``inputs.want_surprise`` as
        :mod:`css_ros.engine.change_rules` defines them. Returns the pixel counts (used, ignored, out of range, with
        ``soft`` labelled pixels without any contribution, transient, occluded) and the surprise image when asked
        for, possibly still on a device until :meth:`UpdateCounts.get`."""

    @abstractmethod
    def render(self, frame: Any, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> "RenderBuffers":
        """Raw float64 buffers: colour, E, Var (argmax class), kappa_b, evidence and the expected depth (splat
        units) from the current concentrations."""

    def render_view(self, frame: Any, concentrations: np.ndarray, settings: RenderSettings) -> FrameImages:
        """The view's requested outputs in final form (:mod:`.final_form`); default: :meth:`render`, then numpy."""
        buf = self.render(frame, concentrations, settings.e_bg, settings.v_bg, settings.s_bg,
                          np.asarray(settings.bg_rgb, dtype=np.float64), settings.probabilities)
        return finalize_host(buf, settings)

    def observe_view(self, camera: "Camera", inputs: "FrameLabels", concentrations: np.ndarray,
                     soft: "SoftLabels | None", settings: RenderSettings) -> tuple[FrameImages, UpdateCounts]:
        """One observed frame (SPEC §7): rasterise once, update, render at the same pose; a backend may do it in
        fewer steps (cuda: one synchronisation)."""
        frame = self.prepare(camera)
        counts = self.update(frame, inputs, concentrations, soft)
        return self.render_view(frame, concentrations, settings), counts

    def render_query(self, camera: "Camera", concentrations: np.ndarray, settings: RenderSettings) -> FrameImages:
        """A query view's outputs (the map unchanged)."""
        return self.render_view(self.prepare(camera), concentrations, settings)

    @abstractmethod
    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]]:
        """(expectation, variance, mass) of several query views of one map state, in order: the inputs of U_var,
        U_exp and the info gain. E and Var are exactly what ``render`` gives for them, possibly computed faster.
        With ``mass_weights`` (depth-bin edges in splat units (B + 1,), net vote weight per (label, bin) (C * B,)),
        mass = (model ids (M,), evidence (M,)): what observing the view would add to each visible Gaussian,
        sum_i kappa_in * weight[label_i * B + bin_i] with label_i the rendered argmax; else None."""

    def score_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None",
                    importance: np.ndarray | None, pixel_scale: float) -> np.ndarray:
        """(V, 3) float64 (U_var, U_exp, info_gain) per view (SPEC §6; docs/spec.md "Information gain of a view");
        info_gain NaN without ``mass_weights``."""
        from .info_gain import MomentSums, view_gain

        out = np.full((len(cameras), 3), np.nan)
        moments = MomentSums.of(self.host_read(concentrations)) if mass_weights is not None else None
        for i, (expectation, variance, mass) in enumerate(self.score_images(cameras, concentrations, e_bg, v_bg,
                                                                            s_bg, mass_weights)):
            out[i, :2] = self.uncertainty(expectation, variance)
            if mass is not None and moments is not None:
                out[i, 2] = view_gain(moments, mass[0], pixel_scale * mass[1], importance)
        return out

    def uncertainty(self, expectation: np.ndarray, variance: np.ndarray) -> tuple[float, float]:
        """(U_var, U_exp) of a scored view's (H, W) float64 E and Var, the same reduction :meth:`render_view` uses."""
        return image_uncertainty(expectation, variance)

    def view_masses(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray]"
                    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Per view, (model ids (M,), evidence mass (M,)) of its visible Gaussians (from :meth:`score_images`)."""
        for _, _, mass in self.score_images(cameras, concentrations, e_bg, v_bg, s_bg, mass_weights):
            assert mass is not None  # score_images returns it when asked
            yield mass

    def select_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray]", importance: np.ndarray | None,
                     pixel_scale: float, k: int) -> "SelectedViews":
        """A greedy batch of ``k`` views (SemanticMap.select_views): each pick the largest info gain given the
        picks before it were observed (their expected evidence added to the moments)."""
        from .info_gain import MomentSums, SelectedViews, view_gain

        masses = [(ids, pixel_scale * mass) for ids, mass in self.view_masses(cameras, concentrations, e_bg, v_bg,
                                                                               s_bg, mass_weights)]
        moments = MomentSums.of(self.host_read(concentrations))
        scores = np.array([view_gain(moments, ids, mass, importance) for ids, mass in masses])
        touched = np.zeros(concentrations.shape[0], dtype=bool)
        chosen: list[int] = []
        gains: list[float] = []
        for _ in range(min(int(k), len(masses))):
            best = int(np.argmax(scores))
            chosen.append(best)
            gains.append(float(scores[best]))
            scores[best] = -np.inf
            ids_best, mass_best = masses[best]
            moments.observe_expected(ids_best, mass_best)
            # a view's gain depends only on the moments of its own Gaussians: re-score the views sharing one with
            # the pick (the others keep their gains exactly)
            touched[ids_best] = True
            for i, (ids, mass) in enumerate(masses):
                if scores[i] != -np.inf and touched[ids].any():
                    scores[i] = view_gain(moments, ids, mass, importance)
            touched[ids_best] = False
        return SelectedViews(np.array(chosen, dtype=np.int64), np.array(gains))

    def host_read(self, host: np.ndarray) -> np.ndarray:
        """``host`` up to date, for reading only (reading never forces a re-upload). Host-resident
        backends hand out the array itself (a read-only view would make numba compile a second
        specialisation of every kernel it reaches)."""
        return host

    def host_write(self, host: np.ndarray) -> np.ndarray:
        """``host`` up to date and writable; a device copy is refreshed from it before the next kernel."""
        return host
