"""Plain PyTorch twin of the numba rasteriser (same maths, SPEC §3-5), for other devices and as a
cross-check of the compiled path. Tiles are evaluated densely (tile pixels x tile list), so memory
stays bounded by the longest tile list, never pixels x Gaussians."""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterator, Sequence

import numpy as np
import torch

from ..label_input import count_votes
from ..raster_backend import RasterBackend, UpdateCounts
from ..buffers import RenderBuffers
from ..spec import ALPHA_MAX, ALPHA_MIN, COV2D_DILATION, FOV_CLAMP, NEAR_PLANE, T_MIN, TILE_SIZE
from ..sh import eval_sh

if TYPE_CHECKING:
    from ..camera import Camera
    from ..change_rules import ChangeRules
    from ..gaussians import GaussianModel
    from ..label_input import FrameLabels
    from ..sensor_model import SoftLabels


@dataclass
class TorchFrame:
    """Per-view state: depth-sorted visible Gaussians (M) and their tile lists (CSR)."""

    camera: "Camera"
    ids: np.ndarray            # (M,) int64 model ids, front to back
    means2d: torch.Tensor      # [M, 2]
    conics: torch.Tensor       # [M, 3]
    opacities: torch.Tensor    # [M]
    colors: torch.Tensor       # [M, 3]
    depths: torch.Tensor       # [M] camera z (splat units)
    offsets: np.ndarray        # (T + 1,) int64
    lists: torch.Tensor        # [P] int64 indices into the M arrays
    tiles_x: int
    tile_size: int


class TorchBackend(RasterBackend):
    """Rasteriser backend in plain PyTorch (float64 on ``device``)."""

    def __init__(self, model: "GaussianModel", device: str = "cpu", tile_size: int = TILE_SIZE) -> None:
        self.device = torch.device(device)
        self.dtype = torch.float64
        self.tile_size = tile_size
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=self.dtype, device=self.device)  # noqa: E731
        self.means = t(model.means)
        self.opacities = t(model.opacities)
        self.cov3d = t(model.covariances())          # [N, 3, 3]
        self.sh = torch.as_tensor(np.asarray(model.sh), dtype=torch.float32, device=self.device)

    # ------------------------------------------------------------------ projection + binning
    def prepare(self, camera: "Camera") -> TorchFrame:
        dev, dt = self.device, self.dtype
        w2c = torch.as_tensor(np.asarray(camera.world_to_cam), dtype=dt, device=dev)
        rot, trans = w2c[:3, :3], w2c[:3, 3]
        fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
        width, height = camera.width, camera.height
        p = self.means @ rot.T + trans
        x, y, z = p.unbind(1)
        keep = (z > NEAR_PLANE) & (self.opacities >= ALPHA_MIN)
        zs = torch.where(keep, z, torch.ones_like(z))
        u = fx * x / zs + cx
        v = fy * y / zs + cy
        tan_x, tan_y = width / (2 * fx), height / (2 * fy)
        txz = (x / zs).clamp(-(cx + 0.5) / fx - FOV_CLAMP * tan_x, (width - 0.5 - cx) / fx + FOV_CLAMP * tan_x)
        tyz = (y / zs).clamp(-(cy + 0.5) / fy - FOV_CLAMP * tan_y, (height - 0.5 - cy) / fy + FOV_CLAMP * tan_y)
        zero = torch.zeros_like(zs)
        jac = torch.stack([fx / zs, zero, -fx * txz / zs, zero, fy / zs, -fy * tyz / zs], 1).reshape(-1, 2, 3)
        mm = jac @ rot
        cov2d = mm @ self.cov3d @ mm.transpose(1, 2)
        a = cov2d[:, 0, 0] + COV2D_DILATION
        b = cov2d[:, 0, 1]
        c = cov2d[:, 1, 1] + COV2D_DILATION
        det = a * c - b * b
        keep &= det > 0
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=0.0))
        r = torch.ceil(3.0 * torch.sqrt(lam))
        keep &= ~((u + r < -0.5) | (u - r > width - 0.5) | (v + r < -0.5) | (v - r > height - 0.5))
        qmax = 2.0 * torch.log(255.0 * self.opacities.clamp(min=ALPHA_MIN))
        hx = torch.sqrt(qmax * a) * (1 + 1e-9) + 1e-9
        hy = torch.sqrt(qmax * c) * (1 + 1e-9) + 1e-9
        umin = torch.ceil(u - hx).clamp(min=0)
        umax = torch.floor(u + hx).clamp(max=width - 1)
        vmin = torch.ceil(v - hy).clamp(min=0)
        vmax = torch.floor(v + hy).clamp(max=height - 1)
        keep &= (umin <= umax) & (vmin <= vmax)
        idx = torch.nonzero(keep).squeeze(1)
        idx = idx[torch.sort(z[idx], stable=True).indices]
        conics = torch.stack([c / det, -b / det, a / det], 1)[idx]
        # colours
        sh = self.sh[idx]
        if sh.shape[1] == 1:
            rgb = eval_sh(sh, None)
        else:
            cam_pos = torch.as_tensor(np.asarray(camera.position), dtype=dt, device=dev)
            dirs = self.means[idx] - cam_pos
            dirs = (dirs / dirs.norm(dim=1, keepdim=True).clamp(min=1e-12)).float()
            rgb = eval_sh(sh, dirs)
        colors = torch.clamp(rgb + 0.5, min=0.0).to(dt)
        # tile binning: (tile, depth-rank) pairs, stable-sorted by tile keeps depth order
        ts = self.tile_size
        tiles_x = (width + ts - 1) // ts
        tiles_y = (height + ts - 1) // ts
        tx0 = (umin[idx] // ts).long()
        tx1 = (umax[idx] // ts).long()
        ty0 = (vmin[idx] // ts).long()
        ty1 = (vmax[idx] // ts).long()
        nx, ny = tx1 - tx0 + 1, ty1 - ty0 + 1
        per = nx * ny
        rank = torch.repeat_interleave(torch.arange(len(idx), device=dev), per)
        start = torch.cumsum(per, 0) - per
        local = torch.arange(int(per.sum()), device=dev) - torch.repeat_interleave(start, per)
        nxr = torch.repeat_interleave(nx, per)
        tile_id = (torch.repeat_interleave(ty0, per) + local // nxr) * tiles_x + torch.repeat_interleave(tx0, per) + local % nxr
        order = torch.sort(tile_id, stable=True).indices
        lists = rank[order]
        counts = torch.bincount(tile_id, minlength=tiles_x * tiles_y).cpu().numpy()
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        return TorchFrame(camera, idx.cpu().numpy(), torch.stack([u, v], 1)[idx], conics,
                          self.opacities[idx], colors, z[idx], offsets, lists, tiles_x, ts)

    # ------------------------------------------------------------------ per-tile compositing
    def _tiles(self, frame: TorchFrame):
        """Yield (pixel rows, pixel cols, list indices, kappa [P, L], final transmittance [P])."""
        ts, cam = frame.tile_size, frame.camera
        for t in range(len(frame.offsets) - 1):
            s, e = int(frame.offsets[t]), int(frame.offsets[t + 1])
            ty, tx = divmod(t, frame.tiles_x)
            vs = torch.arange(ty * ts, min(cam.height, ty * ts + ts), device=self.device)
            us = torch.arange(tx * ts, min(cam.width, tx * ts + ts), device=self.device)
            vv, uu = torch.meshgrid(vs, us, indexing="ij")
            vv, uu = vv.reshape(-1), uu.reshape(-1)
            if s == e:
                yield vv, uu, None, None, torch.ones(len(vv), dtype=self.dtype, device=self.device)
                continue
            lst = frame.lists[s:e]
            dx = uu[:, None].to(self.dtype) - frame.means2d[lst, 0][None, :]
            dy = vv[:, None].to(self.dtype) - frame.means2d[lst, 1][None, :]
            con = frame.conics[lst]
            q = con[:, 0] * dx * dx + 2.0 * con[:, 1] * dx * dy + con[:, 2] * dy * dy
            alpha = torch.clamp(frame.opacities[lst] * torch.exp(-0.5 * q), max=ALPHA_MAX)
            alpha = torch.where(alpha >= ALPHA_MIN, alpha, torch.zeros_like(alpha))
            one_minus = 1.0 - alpha
            t_incl = torch.cumprod(one_minus, dim=1)
            t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
            stop = (t_incl < T_MIN) & (alpha > 0)
            keep = torch.cumsum(stop.to(torch.int32), dim=1) == 0
            kappa = torch.where(keep, alpha * t_excl, torch.zeros_like(alpha))
            final_t = torch.prod(torch.where(keep, one_minus, torch.ones_like(one_minus)), dim=1)
            yield vv, uu, lst, kappa, final_t

    def update(self, frame: TorchFrame, inputs: "FrameLabels", concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> UpdateCounts:
        """The paper's update with the changing-world rules (:mod:`css_ros.engine.change_rules`), per tile:
        a pixel's vote (:func:`~css_ros.engine.label_input.pixel_vote`, vectorised by ``count_votes``), then its
        transient class, then the measured-depth gate; forgetting when the increments are added."""
        rules, num_classes = inputs.rules, concentrations.shape[1]
        labels, weights, counts = count_votes(inputs.labels, inputs.confidence, inputs.num_classes,
                                              inputs.ignore_label)
        lab = torch.as_tensor(labels, device=self.device).long()
        wts = torch.as_tensor(weights, device=self.device, dtype=self.dtype)
        transient = self._transient_pixels(lab, rules, num_classes)   # [H, W] voted pixels of a transient class
        depth = None if inputs.depth is None else torch.as_tensor(inputs.depth, dtype=self.dtype, device=self.device)
        surprise = None
        if inputs.want_surprise:
            alpha = torch.as_tensor(concentrations[frame.ids], dtype=self.dtype, device=self.device)
            expect = alpha / alpha.sum(dim=1, keepdim=True)          # [M, C] E[theta] before the update
            surprise = torch.full(lab.shape, float("nan"), dtype=self.dtype, device=self.device)
        acc = torch.zeros((len(frame.ids), num_classes), dtype=self.dtype, device=self.device)
        if soft is not None:
            edges = torch.as_tensor(soft.edges, dtype=self.dtype, device=self.device)
            table = torch.as_tensor(soft.table, dtype=self.dtype, device=self.device)
        no_depth = occluded = 0
        for vv, uu, lst, kappa, final_t in self._tiles(frame):
            pl = lab[vv, uu]
            if surprise is not None:
                surprise[vv, uu] = self._surprise(pl, lst, kappa, final_t, expect, num_classes)
            gets = (pl >= 0) & ~transient[vv, uu]   # pixels that add evidence unless the depth gate stops them
            if lst is None:
                no_depth += int(gets.sum())
                continue
            if not bool(gets.any()):
                continue
            ksum = kappa.sum(dim=1)
            mean_z = (kappa @ frame.depths[lst]) / ksum.clamp(min=1e-300)   # splat units (0 where ksum = 0)
            if depth is not None:
                blocked, kappa = self._depth_gate(depth[vv, uu], kappa, frame.depths[lst], ksum, mean_z, rules)
                occluded += int((gets & blocked).sum())
                gets &= ~blocked
            w = torch.where(gets, wts[vv, uu], torch.zeros_like(ksum))
            if soft is None:
                y = torch.zeros((len(vv), num_classes), dtype=self.dtype, device=self.device)
                y[gets, pl[gets]] = w[gets]
            else:  # soft label of (label, depth bin of the expected depth over all contributions)
                b = (torch.searchsorted(edges[1:-1].contiguous(), mean_z, right=True)).clamp(max=soft.num_bins - 1)
                y = table[pl.clamp(min=0) * soft.num_bins + b] * w[:, None]
                no_depth += int((gets & (ksum <= 0)).sum())
            acc.index_add_(0, lst, kappa.T @ y)
        self._add_evidence(concentrations, frame.ids, acc.cpu().numpy(), rules)
        n_transient = int(transient.sum())
        used = int(counts[0]) - n_transient - occluded
        out = np.array([used, counts[1], counts[2], no_depth if soft is not None else 0, n_transient, occluded],
                       dtype=np.int64)
        return UpdateCounts(out, None if surprise is None else surprise.cpu().numpy().astype(np.float32))

    def _transient_pixels(self, lab: torch.Tensor, rules: "ChangeRules", num_classes: int) -> torch.Tensor:
        """[H, W] bool: voted pixels (class >= 0) whose class is marked transient (``rules.transient`` may be
        shorter than C, or empty: the classes beyond it are not transient)."""
        mask = np.zeros(num_classes, dtype=np.bool_)
        k = min(num_classes, rules.transient.shape[0])
        mask[:k] = rules.transient[:k]
        marked = torch.as_tensor(mask, device=self.device)
        return (lab >= 0) & marked[lab.clamp(min=0)]

    @staticmethod
    def _depth_gate(measured: torch.Tensor, kappa: torch.Tensor, z: torch.Tensor, ksum: torch.Tensor,
                    mean_z: torch.Tensor, rules: "ChangeRules") -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`~css_ros.engine.change_rules.depth_gate` over a tile's pixels.

        Args:
            measured: [P] measured depth (metres; not finite or <= 0: none).
            kappa: [P, L] the pixels' contributions; z: [L] the Gaussians' camera z (splat units).
            ksum: [P] sum of kappa; mean_z: [P] sum kappa z / sum kappa (splat units; meaningless where ksum = 0).
        Returns:
            (occluded [P] bool, kappa with the contributions in front of the measured surface zeroed)."""
        has = (measured > 0.0) & (measured < float("inf"))           # NaN compares False
        tol = torch.clamp(rules.tol_rel * measured, min=rules.tol_abs)
        rendered = mean_z * rules.depth_scale                          # metres
        occluded = has & (ksum > 0) & (measured < rendered - tol)
        gone = has & (ksum > 0) & (rendered < measured - tol)          # the splat's surface in front of the measured
        front = torch.where(gone, measured - tol, torch.full_like(measured, float("-inf")))
        in_front = (z * rules.depth_scale)[None, :] < front[:, None]
        return occluded, torch.where(in_front, torch.zeros_like(kappa), kappa)

    @staticmethod
    def _surprise(pl: torch.Tensor, lst: torch.Tensor | None, kappa: torch.Tensor | None, final_t: torch.Tensor,
                  expect: torch.Tensor, num_classes: int) -> torch.Tensor:
        """[P] 1 - E^y of the pixels' labels y under the map before the update, E^y = sum kappa E[theta^y] +
        kappa_b / C; NaN where the pixel has no vote (``pl`` < 0)."""
        e_y = final_t / num_classes
        if lst is not None and kappa is not None:
            e_y = e_y + (kappa @ expect[lst]).gather(1, pl.clamp(min=0)[:, None])[:, 0]
        return torch.where(pl >= 0, 1.0 - e_y, torch.full_like(e_y, float("nan")))

    @staticmethod
    def _add_evidence(concentrations: np.ndarray, ids: np.ndarray, increment: np.ndarray, rules: "ChangeRules") -> None:
        """concentrations[ids] += increment (M, C); with forgetting (decay < 1) the Gaussians whose increment is
        non-zero first have alpha - alpha_0 multiplied by the decay, the others are untouched."""
        if rules.decay == 1.0:
            concentrations[ids] += increment
            return
        touched = (increment != 0.0).any(axis=1)
        rows = ids[touched]
        concentrations[rows] = rules.prior + (concentrations[rows] - rules.prior) * rules.decay + increment[touched]

    def render(self, frame: TorchFrame, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> RenderBuffers:
        cam, dev, dt = frame.camera, self.device, self.dtype
        h, w, c = cam.height, cam.width, concentrations.shape[1]
        alpha = torch.as_tensor(concentrations[frame.ids], dtype=dt, device=dev)
        tot = alpha.sum(dim=1)
        ex = alpha / tot[:, None]
        va = ex * (1.0 - ex) / (1.0 + tot[:, None])
        bg = torch.as_tensor(np.asarray(bg_rgb), dtype=dt, device=dev)
        probs = torch.empty((h, w, c), dtype=dt, device=dev)
        out_label = torch.empty((h, w), dtype=torch.int64, device=dev)
        out_v = torch.empty((h, w), dtype=dt, device=dev)
        out_bg = torch.empty((h, w), dtype=dt, device=dev)
        out_ev = torch.empty((h, w), dtype=dt, device=dev)
        out_rgb = torch.empty((h, w, 3), dtype=dt, device=dev)
        out_depth = torch.empty((h, w), dtype=dt, device=dev)
        for vv, uu, lst, kappa, final_t in self._tiles(frame):
            if lst is None:
                e_pix = torch.zeros((len(vv), c), dtype=dt, device=dev)
                v_all = torch.zeros((len(vv), c), dtype=dt, device=dev)
                ev = torch.zeros(len(vv), dtype=dt, device=dev)
                rgb = torch.zeros((len(vv), 3), dtype=dt, device=dev)
                depth = torch.full((len(vv),), float("nan"), dtype=dt, device=dev)
            else:
                e_pix = kappa @ ex[lst]
                v_all = (kappa * kappa) @ va[lst]
                ev = kappa @ tot[lst]
                rgb = kappa @ frame.colors[lst]
                ksum = kappa.sum(dim=1)
                depth = torch.where(ksum > 0, (kappa @ frame.depths[lst]) / ksum.clamp(min=1e-300),
                                    torch.full_like(ksum, float("nan")))
            out_depth[vv, uu] = depth
            best = torch.argmax(e_pix, dim=1)
            out_label[vv, uu] = best
            probs[vv, uu] = e_pix + final_t[:, None] * e_bg
            out_v[vv, uu] = v_all.gather(1, best[:, None])[:, 0] + final_t * final_t * v_bg
            out_bg[vv, uu] = final_t
            out_ev[vv, uu] = ev + final_t * s_bg
            out_rgb[vv, uu] = rgb + final_t[:, None] * bg
        probs_np = probs.cpu().numpy()
        labels = out_label.cpu().numpy().astype(np.int32)
        exp_img = np.take_along_axis(probs_np, labels[:, :, None], axis=2)[:, :, 0]
        return RenderBuffers(labels, exp_img, out_v.cpu().numpy(), out_bg.cpu().numpy(), out_ev.cpu().numpy(),
                             out_rgb.cpu().numpy(), probs_np if want_probs else None, out_depth.cpu().numpy())

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]]:
        """One ``render`` per view (the reference path has no batch shortcut); the evidence mass from the same
        per-tile kappa (see RasterBackend.score_images)."""
        for cam in cameras:
            frame = self.prepare(cam)
            buf = self.render(frame, concentrations, e_bg, v_bg, s_bg, np.zeros(3), False)
            mass = None
            if mass_weights is not None:
                mass = (np.asarray(frame.ids, dtype=np.int64), self._mass(frame, buf, mass_weights))
            yield buf.expectation, buf.variance, mass

    def _mass(self, frame: TorchFrame, buf: RenderBuffers, mass_weights: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """(M,) sum_i kappa_in * weight[label_i * B + bin_i] over the view's pixels."""
        from ..sensor_model import depth_bins

        edges, weights = mass_weights
        nb = edges.size - 1
        b = depth_bins(edges, np.nan_to_num(np.asarray(buf.depth), nan=0.0))
        w_pix = torch.as_tensor(weights[buf.labels * nb + b], dtype=self.dtype, device=self.device)
        mass = torch.zeros(len(frame.ids), dtype=self.dtype, device=self.device)
        for vv, uu, lst, kappa, _ in self._tiles(frame):
            if lst is not None:
                mass.index_add_(0, lst, kappa.T @ w_pix[vv, uu])
        return mass.cpu().numpy()
