"""Where the packing box's faces lie: a face the sensor saw head on at the plane its points scatter about,
not at the tail of their range noise; a face seen only at the object's outline where its points end, beyond
that by the zone footprint's expected share.

The trimmed box (:func:`cell.packing.box.box_from_points`) puts each face at the ``1 - trim`` quantile of
all points along its outward normal n. On a face the sensor faced, the points scatter along their rays
with the range noise, sigma(r) = sigma0 + k r^2 (the sensor's noise model: about 5 mm at 0.35 m for the
VL53L8CX), so that quantile lands in the noise's tail, about 2-2.5 sigma |n.d| beyond the face: the
horizontal box's top came out 4.6-12.5 mm high on all 15 scans of the packing paper's grid. Here such a
face is put where its points say the plane is:

1. **Facing points.** The points whose local surface normal (from their capture's neighbouring zones,
   :func:`cell.packing.zones.surface_normals`) lies within ``FACING_DEG`` of n, among those no more than
   ``BAND_SIGMAS`` of their own noise std inside the box's face: on a box, the face's own points (a top
   and a side meet at 90 deg; the normal's own error is 10-20 deg). Not the view ray: a view 40 deg
   above the table meets a top and a side both at 40-50 deg. The plane (steps 2-3) is fitted to those
   of them inside the object's outline in their capture (:func:`cell.packing.zones.outline_sides`): a
   zone straddling the outline ranges the part of its footprint on the face, but its point lies on the
   zone's central ray, which may pass beside the object, and so beyond the face's plane (the sim
   VL53L8CX's vertical box seen 50-70 deg off a side's normal: 1-1.7 mm out on average, the plane 2.6 mm
   out with them and within 1 mm without). A face with fewer than ``MIN_FACING_POINTS`` zones inside the
   outline (a small part's) is fitted to all its facing points.
2. **Noise taken out.** Each facing point's coordinate x along n is the plane's X plus its range error
   along n, sigma(r) |n.d| e with e standard normal, so x - z_q sigma(r) |n.d| has its q quantile at X
   for any mix of ranges and incidences: q = ``QUANTILE`` (0.9) rather than the median, so that a face
   is not pulled in by the points of a rounded edge or of a part of the face set back from it.
3. **Only where it is a plane.** If that puts the face more than ``ACCEPT_SIGMAS`` scatter std (median
   over the plane's points; the std of step 4, whose pose terms scatter a plane's points about it as the
   range noise does) inside the box's own face, the points beyond it are not a plane's noise but
   surface the facing points missed (a protrusion smaller than a zone, a rounded part); if the plane's
   points' median lies more than ``ONE_PLANE_SIGMAS`` below it, they lie on more than one level (a
   flange's hub over its rim, both within the band); either way the box's face stays.
4. **Only where it is flat.** A rounded side seen head on (a gripper's flank, curving away over its
   height) has facing points too, but those whose normal is tilted from n by up to ``FACING_DEG`` lie up
   to R (1 - cos 35 deg), a fifth of its radius, inside its extreme, and the corrected quantile comes out
   inside by a part of that (4-7 mm on the gripper's flanks on LR-NBV and NBV scans at placements the
   code was not tuned on). On a plane a facing point lies more than ``DEEP_SIGMAS`` of its std inside it
   with probability Phi(-2) = 2.3 %, its std here sqrt(sigma(r)^2 |n.d|^2 + b^2 |n.d|^2 + (t + r theta)^2)
   (the error model's range noise, range offset and pose terms: the views' pose errors scatter a plane's
   points about it as well), counted over all the facing points, those on the outline too (a flank's
   widest part is at its foot); when so many lie that deep that a plane gives as many with probability
   below ``ROUNDED_ALPHA`` (binomial), the surface turns at the face rather than being flat there, its
   points crowd at its extreme, and the face is the box's own (the trimmed quantile; no outline gap: the
   face was seen head on, not at a silhouette).
5. **Only where it stands upright.** A side that leans over its height (a flank narrowing upwards, as
   the gripper's narrow by 16 mm over 65 mm, 14 deg, widest near the foot; an overhang) is not a plane
   perpendicular to n: the plane of steps 2-3 lies mid-slope, and when its foot's zones lie on the
   outline it is fitted to the points up the flank alone, too far in for step 4 to find many deeper
   still (the gripper's flanks up to 9 mm inside on the grids' LR-NBV and NBV scans). On a side standing
   upright the facing points' coordinate along n does not trend with their height: the weighted
   least-squares slope of x against z (weights 1 / their std of step 4), over all the facing points, is
   zero up to its standard error, from the residuals' own scatter but no less than that std (on
   noise-free points any trend would be significant). When an upright side gives a slope as steep with
   probability below ``ROUNDED_ALPHA`` (two-sided t test), the side leans, and its face is the box's own
   as in step 4: the trimmed quantile lies at the outermost strip of the samples, where a leaning side
   has its extreme. Not the fitted line's extreme over the points' heights: the slope's error times a
   side's height moves a flat side out by millimetres, and the boxes' sides read 1-4 deg from the
   outline zones at their foot (so placed, one vertical box side came out 17 mm out). Those slopes are
   at times significant, and such a flat side gets the box's face, 1-5 mm out, rather than its plane.
   The top has no height across it and no such test.

The assumption (the simulated sensor's behaviour; expected of a real VL53L8CX, not measured on one here):
a zone that a plane fills reports the plane's range on the zone's central ray, up to zero-mean noise of
std sigma(r) (the sim takes the median of its sub-rays' ranges; a real zone's histogram peak from a
surface filling it is that surface's range near the zone's centre); a common range offset left after
calibration, and the hand-eye error, shift the faces and are not taken out (the upper bound allows for
them: on the grid's scans they leave the head-on faces 2-6 mm inside on some seeds).

**Faces seen at the outline.** A face with no plane of facing points (a 15 mm rim seen from above, a top seen
only from the side, a rounded part) is put where the object's samples along n end, moved out by the part of a
zone footprint that the outline is expected to lie beyond them:

1. **Where the samples end.** The box's face is the ``1 - trim`` quantile of its points along n, so k = trim N
   points lie beyond it. On a surface that runs out at the face (a top up to its edge, a rim seen from above)
   they are the last strip of it, and the quantile lies inside the samples' end by the width that a share
   ``trim`` of all the object's points covers, which grows with the object: 2 % of a 30 cm top's points are
   its last 6 mm, the 2 % segment of a 12 cm disc is 6 mm deep (the horizontal box's far face came out 2.2 cm
   in on two LR-NBV scans of the packing paper's grid, the flange 1-2.4 cm narrow on all five NBV scans). A
   surface sampled evenly up to its end has as many points in every strip of equal width, so the k points
   beyond the quantile span as much as the k inside it: the samples end at q + (q - x_2k) (x_2k the 2k-th
   outermost point), never beyond the outermost point. On a surface that turns at the face (a wall, a
   curved or rounded side at its extreme) the points crowd at the face and the quantile is already there.
   The local normals tell the two apart: a surface that runs out along n has its normals across n (a top's
   are 90 deg from a side's n), one that turns at the face has them towards n; a normal counts as across
   when it lies within ``FACING_DEG`` of the plane perpendicular to n (twice the normals' own error, as
   for facing). The outermost 2k points can hold both (a side wall and the top's edge above it), so the
   step out is q - x_2k times the share of them with a known normal across n (:func:`sample_end`); with
   no normal known there is no step. The points beyond the quantile count by their number only, so a few
   gross outliers among them (what the trim is for) move it no further than their number of points inside
   the quantile.
2. **The outline beyond the samples.** At the silhouette a zone ranges the object only when the object gives
   most of its return (the sim: the median of its sub-rays' ranges, so over half of them on the object; a real
   zone with a background close behind the object merges the two into one range between them, nearer the
   object the larger its share, so its point falls in the object's voxels rather than being cut as background
   about when the object gives most of the return: the assumption), and the next zone outwards, which ranged
   the background, holds less than half: the outline lies between the outermost object zone's centre and one
   footprint, r tan(w) (|n.x| + |n.y|) along n (``ErrorModel.footprint``), beyond it, anywhere in between as
   the zone grid falls on the object. An edge crosses a view's zone grid at a different offset in each zone
   it passes unless the grid's rows run along it, so each point on the outline is a draw of its own: the
   outermost of Z draws lies on average 1 / (Z + 1) of a footprint inside the outline (the gap below the
   largest of Z uniform draws), Z the number of the face's points (the share
   ``cell.packing.uncertainty.FACE_FRACTION`` outermost along n) and the footprint their median; a grid
   aligned with the edge gives one draw per view, and the gap is then larger (half a footprint for one view).
   A face seen head on has |n.x| + |n.y| near 0 and moves little. This takes the order statistics' mean, not
   a bound: the upper bound allows for the whole footprint. Where the background is out of range (a view over
   the object into nothing), the sim ranges a zone from a quarter of its sub-rays on the object
   (``min_hit_fraction``) and the outline lies closer than assumed; with few views (2-3) the face's few points
   are noisy, so one face can come out 1-2 cm either way.

A face that a view never showed (a face only grazed by a few zones from far, a part of the object lost
to the segmentation) stays where its few points put it; the upper bound is what covers it.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.special import bdtrc, ndtr, ndtri, stdtr

from cell.packing.box import PackingBox, box_from_faces
from cell.packing.uncertainty import FACING_DEG, ErrorModel, Seen

# The share of the noise-corrected facing points below the face (module docstring, step 2).
QUANTILE = 0.9
# Fewer facing points than this cannot place a 0.9 quantile between two of them.
MIN_FACING_POINTS = 10
# The facing points are taken from this many noise std inside the box's face outwards: that face lies
# up to ~3 std beyond the plane (the quantile of all points is a higher one of the face's own), and 3
# more hold all but 0.13 % of the plane's points.
BAND_SIGMAS = 6.0
# A face further inside the box's own than this many scatter std is not a plane's (step 3).
ACCEPT_SIGMAS = 3.0
# On one plane the facing points' median and their noise-corrected quantile both estimate it: their
# difference has a std of about 0.7 scatter std at the fewest (10) facing points, less with more. Further
# apart than twice that, the facing points lie on two levels (a hub on a rim) and the face stays (step 3).
ONE_PLANE_SIGMAS = 1.5
# A facing point further inside the plane than this many of its std is deep (step 4): 2.3 % of a plane's.
DEEP_SIGMAS = 2.0
# A plane is taken for a rounded surface, or a side for a leaning one, this rarely (steps 4 and 5): once
# in a thousand faces.
ROUNDED_ALPHA = 0.001


def face_at(model: ErrorModel, seen: Seen, n: np.ndarray, face_m: float) -> float:
    """Where the face with outward unit normal ``n`` (3,) lies [m, coordinate along n], the box's own at
    ``face_m``: the plane of its facing points (:func:`head_on_plane`), else where the samples end
    (:func:`sample_end`) plus the outline's expected gap (:func:`outline_gap`)."""
    plane = head_on_plane(model, seen, n, face_m)
    return sample_end(seen, n, face_m) + outline_gap(model, seen, n) if plane is None else plane


def sample_end(seen: Seen, n: np.ndarray, face_m: float) -> float:
    """Where the points of ``seen`` along the unit normal ``n`` (3,) end [m], the box's quantile face at
    ``face_m``: face_m + s (face_m - x_2k) for the k points beyond it, x_2k the 2k-th outermost and s the
    share of the 2k outermost points with a known normal across n, at most the outermost point
    (module docstring, step 1); ``face_m`` when no point lies beyond it, fewer than 2k points lie on the
    object or no normal is known."""
    x = seen.points @ n
    order = np.argsort(-x)
    k = int(np.count_nonzero(x > face_m))
    if seen.normals is None or k == 0 or 2 * k >= x.size:
        return face_m
    with np.errstate(invalid="ignore"):  # NaN normals: unknown
        cosines = seen.normals[order[:2 * k]] @ n
    known = np.isfinite(cosines)
    if not known.any():
        return face_m
    across = math.sin(math.radians(FACING_DEG))
    running_out = np.count_nonzero(np.abs(cosines[known]) < across) / np.count_nonzero(known)
    end = face_m + running_out * (face_m - float(x[order[2 * k]]))
    return min(end, float(x[order[0]]))


def outline_gap(model: ErrorModel, seen: Seen, n: np.ndarray) -> float:
    """How far [m] the outline of the face with outward unit normal ``n`` (3,) lies beyond its outermost
    points on average: a zone footprint along n over the number of the face's points plus one (module
    docstring, step 2); 0 when the views are unknown."""
    if seen.origins is None:
        return 0.0
    _, face = seen.face(n)
    ranges, _, sideways = seen.geometry(n)
    return model.footprint(ranges[face], sideways[face]) / (np.count_nonzero(face) + 1)


def head_on_plane(model: ErrorModel, seen: Seen, n: np.ndarray, face_m: float) -> float | None:
    """The plane [m, coordinate along n] that the points facing the face with outward unit normal ``n``
    (3,) and inside their capture's outline scatter about (module docstring; all the facing points when
    too few are inside), the box's face lying at ``face_m``; ``face_m`` when the facing points lie
    deeper than one plane's (a rounded side, step 4) or, on a side, trend with height (a leaning side,
    step 5); None when it has too few facing points, or they do not make a plane, or ``seen`` carries
    no normals."""
    if seen.normals is None or seen.origins is None:
        return None
    ranges, along, _ = seen.geometry(n)
    sigma = model.range_sigma(ranges) * along
    x = seen.points @ n
    with np.errstate(invalid="ignore"):  # NaN normals: not facing
        facing = seen.normals @ n >= math.cos(math.radians(FACING_DEG))
    facing &= x >= face_m - BAND_SIGMAS * sigma
    if np.count_nonzero(facing) < MIN_FACING_POINTS:
        return None
    inside = seen.inside
    inner = facing & inside if inside is not None else facing
    if np.count_nonzero(inner) < MIN_FACING_POINTS:
        inner = facing
    plane = float(np.quantile(x[inner] - ndtri(QUANTILE) * sigma[inner], QUANTILE))
    scatter = _scatter_std(model, sigma[facing], ranges[facing], along[facing])
    spread = float(np.median(scatter[inner[facing]]))
    set_back = plane < face_m - ACCEPT_SIGMAS * spread
    two_levels = plane - float(np.median(x[inner])) > ONE_PLANE_SIGMAS * spread
    if set_back or two_levels:
        return None
    if _rounded(x[facing] - plane, scatter) or (n[2] == 0.0 and _leaning(x[facing], seen.points[facing, 2],
                                                                          scatter)):
        return face_m
    return plane


def _scatter_std(model: ErrorModel, sigma: np.ndarray, ranges: np.ndarray, along: np.ndarray) -> np.ndarray:
    """The std (K,) [m] of points about the plane they were seen on, along its normal n: range noise std
    ``sigma`` (K,) [m] along n, the range offset over |n.d| ``along`` (K,) and the pose terms at ``ranges``
    (K,) [m] (module docstring, step 4)."""
    pose = model.pose_m + ranges * model.pose_rad
    return np.asarray(np.sqrt(sigma**2 + (model.bias_m * along) ** 2 + pose**2))


def _rounded(depth: np.ndarray, scatter: np.ndarray) -> bool:
    """Whether facing points at ``depth`` (K,) [m] outside their plane (negative: inside), scattered
    about a plane with std ``scatter`` (K,) [m], lie deeper inside it than a plane's points do (module
    docstring, step 4)."""
    deep = int(np.count_nonzero(depth < -DEEP_SIGMAS * scatter))
    # P(at least ``deep`` of them that deep), binomial with the normal tail below -DEEP_SIGMAS
    return bool(bdtrc(deep - 1, depth.size, ndtr(-DEEP_SIGMAS)) < ROUNDED_ALPHA)


def _leaning(x: np.ndarray, height: np.ndarray, scatter: np.ndarray) -> bool:
    """Whether a side's facing points at ``x`` (K,) [m] along its normal, at ``height`` (K,) [m, base z],
    with std ``scatter`` (K,) [m], trend with height more steeply than a side perpendicular to the table
    gives them with probability ``ROUNDED_ALPHA`` (module docstring, step 5)."""
    weight = 1.0 / scatter
    design = np.column_stack([weight, weight * (height - height.mean())])
    coefficients, *_ = np.linalg.lstsq(design, weight * x, rcond=None)
    residual = weight * x - design @ coefficients
    dof = x.size - 2
    covariance = np.linalg.inv(design.T @ design) * max(float(residual @ residual) / dof, 1.0)
    t_slope = abs(float(coefficients[1])) / math.sqrt(float(covariance[1, 1]))
    return bool(2.0 * stdtr(dof, -t_slope) < ROUNDED_ALPHA)  # two-sided, Student's t with dof


def faced_box(box: PackingBox, model: ErrorModel, seen: Seen) -> PackingBox:
    """``box`` with each of its four sides and its top at :func:`face_at` (same yaw and floor)."""
    return box_from_faces(box, np.array([face_at(model, seen, n, float(f))
                                         for n, f in zip(box.face_normals(), box.faces(), strict=True)]))
