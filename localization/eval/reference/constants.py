"""The yardstick's fixed settings (package doc): search windows, gates, the scoring checks' thresholds
and the smoothing's priors."""
from __future__ import annotations

LAG_SEARCH_S = 0.25  # ± seconds searched for the best lag
LAG_STEP_S = 0.002
STANDSTILL_SPEED = 0.1  # m/s: below, the direction of travel is the reference heading
STANDSTILL_TURN = 0.1  # rad/s: odometry below this and STANDSTILL_SPEED reports the wheels standing

START_WINDOW = (1.0, 0.5)  # m, rad: the first scan is searched this far around a given start pose
MIN_WINDOW = (0.25, 0.1)  # m, rad: the tracking search window is never smaller ...
MAX_WINDOW = (1.5, 0.6)  # m, rad: ... nor larger
CHI2_3_999 = 16.27  # χ² (3 dof) exceeded with probability 0.001: a match inconsistent with the track
CHI2_MEDIANS = {1: 0.4549, 2: 1.3863, 3: 2.3660}  # medians of χ² with 1, 2, 3 dof
GLOBAL_FOLLOW_S = 4.0  # s: a global hypothesis is followed at least this long ...
GLOBAL_TRAVEL_M = 3.0  # m: ... and until the odometry has moved this far (unless it is the last one left)
GLOBAL_HYPOTHESES = 8
RELOCALIZE_SCANS = 5  # after a gap, matches away from the prediction are followed only when this many agree ...
RELOCALIZE_GAP_S = 0.5  # s: ... a gap: this long without a match used
RELOCALIZE_NOISE = 3.0  # ... with each other through the odometry, its σ × this
FIT_TOLERANCE_M = 0.10  # m: a return "fits" when it ends this close to the map's free-space edge (as the agreement)
FIT_SHARE = 0.5  # a scan is scored only where its smoothed pose fits at least this share of the bag's normal fit
FIT_NORMAL_PERCENTILE = 90  # the bag's normal fit: this percentile over its accepted matches
CONSISTENCY_WINDOW_S = 4.0  # s: the smoothed track must follow the odometry over windows this long ...
CONSISTENCY_SIGMAS = 3.0  # ... within this many σ of the nominal odometry noise model plus a map cell,
CONSISTENCY_FIT_SHARE = 0.85  # ... unless the odometry covered less and the scan fits this share of the normal fit
ELSEWHERE_WINDOW = (2.5, 0.4)  # m, rad: every ELSEWHERE_EVERY_S the map is searched this far around the track ...
ELSEWHERE_EVERY_S = 0.5  # s
ELSEWHERE_MARGIN = 0.15  # ... and a pose that fits this much better than the track's leaves its scans unscored
ELSEWHERE_BEAMS = 120  # beams (evenly decimated) of that search
PARAM_NAMES = ("speed_scale", "time_offset_s")  # the odometry's unknowns (a, δ)
NP = 1  # of them solved with the poses (a); δ by its profile (package doc, step 3)
SCALE_PRIOR, SCALE_BOUNDS = 0.3, (0.5, 2.0)  # σ of the prior on a − 1; beyond the bounds the smoothing failed
OFFSET_PRIOR = 0.2  # s: σ of the prior on δ
OFFSET_RANGE, OFFSET_STEP_S, OFFSET_FIT_S = 0.3, 0.002, 0.05  # s: δ searched in ± range, fitted ± fit around the best
