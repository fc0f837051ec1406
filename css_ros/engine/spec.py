"""The SPEC constants and engine defaults, defined once (docs/spec.md; every backend imports them here).

Units: metres for lengths, pixels for image quantities, seconds at interfaces.
"""
from __future__ import annotations

# --- Projection and compositing (SPEC §3) -------------------------------------------------------
NEAR_PLANE = 0.01           # m; Gaussians with camera depth z <= this are culled
COV2D_DILATION = 0.3        # px^2 added to the screen covariance diagonal
ALPHA_MIN = 1.0 / 255.0     # smaller per-pixel alphas are skipped
ALPHA_MAX = 0.99            # per-pixel alpha clamp
T_MIN = 1e-4                # compositing stops before transmittance would drop below this
FOV_CLAMP = 0.3             # J is evaluated at the view ray clamped to 1.3 x the half field of view
TILE_SIZE = 8               # px; tile edge of the binning (results do not depend on it: exact support)
RENDER_CLASS_CHUNK = 40     # classes per pass of the CUDA render walk (2 x 40 x 64 x 4 B = 20 KiB of per-pixel sums)

# --- Semantic state (SPEC §4-6) -----------------------------------------------------------------
DEFAULT_PRIOR = 1e-3              # alpha_0: initial concentration of every class of every Gaussian
DEFAULT_BACKGROUND = 1e-3         # alpha_b: background Dirichlet concentration per class
DEFAULT_IGNORE_LABEL = 255        # "no label" in inputs, "unknown" in rendered labels
DEFAULT_UNKNOWN_THRESHOLD = 0.5   # rendered label is ignore_label where kappa_b exceeds this
VAR_FLOOR = 1e-30                 # variances are floored here before the log of U_var
# Most frames a map (its frames_observed) or a source of evidence may count: 2^48 is ~89,000 years at 100 frames/s,
# and sums of thousands of such counts still fit the int64 / uint64 fields of map files and evidence packets.
MAX_FRAMES = 2**48

# The information gain of a view values evidence on the Dirichlet with this total pseudo-count added, spread evenly
# over the classes (docs/spec.md "Information gain of a view"): with the map's own tiny prior a Gaussian looks
# certain as soon as its first few hundredths of a vote agree, and a view that grazes many Gaussians would look as
# valuable as one that sees them well.
INFO_GAIN_PRIOR = 1.0

# --- The map in 3D (SPEC §9) --------------------------------------------------------------------
DEFAULT_MIN_EVIDENCE = 0.5              # a Gaussian is observed when S_n - C alpha_0 >= this
DEFAULT_QUERY_BACKGROUND_WEIGHT = 0.01  # w_b of the continuous field at a point
QUERY_MAHALANOBIS_CUTOFF = 3.0          # w_n(x) = 0 beyond this Mahalanobis distance

# --- Moving a map to a retrained splat (docs/spec.md "Transfer") ----------------------------------
DEFAULT_TRANSFER_TOLERANCE = 0.01   # m; τ added in quadrature to every old standard deviation (retraining jitter)
MAX_TRANSFER_TOLERANCE = 100.0     # m; a larger τ is no tolerance but a mistake (and overflows the widened scales)
TRANSFER_CUTOFF = 3.0               # Mahalanobis distance of an old/new pair beyond which the overlap is 0
