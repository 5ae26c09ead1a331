"""The packing box's upper bound: how far each face of the object can lie beyond the box's estimate.

A face of the box, with outward unit normal n (+-L, +-W along the box's yaw, +z for the top; the bottom is
the known table), is bounded from the ``1 - trim`` quantile along n of the object's measured points: the
trimmed box's face (``cell.packing.box``), where the estimate lies too unless the face was seen head on
(then the estimate is the plane its points scatter about, ``cell.packing.faces``, which changes nothing
here but the bound's floor, the estimate). The face's points are those beyond the ``1 - FACE_FRACTION``
quantile along n; each was seen from a sensor origin o at range r = |p - o| along the unit ray d, with
the sensor's image axes x (right) and y (down) in the base frame. The true face can lie beyond that
quantile by:

1. **Zone footprint** (bounded). A multizone ToF zone reports one range for a cone of angular width
   w = fov / resolution (45 deg / 8 = 5.625 deg for the VL53L8CX), placed on the zone's central ray; the
   surface that produced it is anywhere in the cone, up to half a footprint, r tan(w / 2), from the ray
   along each image axis. At the object's silhouette a zone ranges the object only when the object gives
   the dominant share of its returns (the sim takes the median of its sub-rays: over half of them), and
   the neighbouring zone outwards, which ranged the background, may still hold up to half its own width
   of the object. So a silhouette seen at a zone's centre can lie up to one zone footprint, r tan(w),
   beyond the point along each image axis (at least an eighth of one with the sim's 4 x 4 sub-rays, half
   of one on average: why an 8 x 8 box comes out small). How far that puts the face along n depends on
   what the point is:

   - a face some of whose points lie on it (a surface normal from the neighbouring zones within
     ``FACING_DEG`` of n) was ranged as a surface: it is where its points were ranged, anywhere in their
     zones' cones, r tan(w) (|n.x| + |n.y|) along n: the whole footprint for a face seen edge-on (n in
     the image plane; up to sqrt 2 of it along the zone's diagonal), nothing for one seen head-on;
   - a face none of whose points lies on it was seen only at its outline, where other surfaces end (a
     cone's tip, a dome's top seen from the side). Beyond a point whose zone straddles the outline on the
     side n points to in the image (the neighbour there saw past the object), the face was not ranged: a
     face moved out along n by D moves its outline in the image by D max(|n.x|, |n.y|) along the axis n
     points most along, so it can lie up to r tan(w) / max(|n.x|, |n.y|) beyond the point (at least the
     first form), the more, the more the view looks along n. A cone's top seen only at its outline from
     HEU's views, 0.35 m up and 0.22-0.3 m out (|n.y| 0.6): 1.7 footprints, where the first form gave
     0.6 and left the bound 4-10 mm under the 90 mm cone on all five seeds (its tip never fills half a
     zone, and the zones above the top's last ranged one saw the table beyond it).

   The term is the median of that over the face's points: a face defined by silhouettes seen from above
   gets about a footprint, a wall the sensor faced gets little. For a pinhole camera w is one pixel's
   angle and the term vanishes.
2. **Map resolution** (bounded). The box is measured on the points in the object's occupancy voxels or
   in the box of every ROI grown by half a voxel (:mod:`cell.packing.objects`), and on the centres of
   object voxels that hold no measured point: a silhouette point whose voxel a grazing ray carved free is
   kept only within half a voxel of the voxels that stayed, and a voxel centre is half a voxel inside its
   faces, so the face can lie res / 2 further out.
3. **Range noise** (Gaussian). Each range is off by N(0, sigma(r)^2), sigma(r) = sigma0 + k r^2 (the
   sensor's noise model), along d. The estimate is a high quantile of the face's K points, which the
   noise scatters both ways: it does not pull the face in, and what remains is the quantile's own
   spread, about sigma |n.d| / sqrt K.
4. **Range bias** (Gaussian). Each zone's constant offset left after calibration, std b, moves a point
   along d and does not average out over one zone's repeated views: b |n.d|.
5. **Pose** (Gaussian). The sensor pose the job believes is off the true one by the hand-eye residual and
   the arm's joint offsets, a translation of std t and a rotation of std theta, which move a point at
   range r by up to t + r theta in any direction, so along n too; the same for all of a view's points.

Bounded terms add (each is a worst case that can coincide with the others); the Gaussian ones, being
independent, add in quadrature and enter as ``coverage_factor`` c times their combined std. With r, |n.d|
and f the medians over the face's points:

    delta(n) = r tan(w) f + res / 2 + c sqrt(sigma(r)^2 |n.d|^2 / K + b^2 |n.d|^2 + (t + r theta)^2),

with f the footprints of item 1 (:meth:`Seen.footprints`).

The points are each capture's own (:class:`Sighting`, with the pose it was taken from); a planner that
keeps no sightings gets the estimate's own points seen from the configured stand-off range in the worst
way (sqrt 2 footprints sideways and the whole range error along n). Each dimension's upper bound is the
distance between its two faces' bounds (H: from the table up); its uncertainty is the difference to the
estimate.

All of this assumes that the face was inside some view: some view saw the object end along n inside
what it kept, its outermost point along n at least a zone and a filter voxel (the voxel filter moves a
point up to one inwards) inside its field of view's border. A view that the border cut has its
outermost point on the border, whatever it shows further in; when every view is so, the face may go on
beyond, where no zone looked, and has no upper bound (infinite): a scan that saw the object only from too
close gives no container rather than too small a one. The perception's crop box (sensor frame) cuts a
view as its border does, and tighter where it is narrower than the field of view (the camera cell's
+-15 cm, the visual-servoing paper's): the point must lie a zone footprint and a filter voxel inside it
too. (The camera cell's HEU views, from 23 cm up, saw its 25 cm tall box only up to their field of view's
top border, 19 cm up; with most of the highest points well inside the frame, the bound was 47-49 mm under
the box.)

A view's outermost point inside its frame shows the object end there only if the view looked past it.
Two ways it may not, both seen on boxes larger than the ToF cell's views (0.48-0.60 m long, where the
bound came out 24-175 mm under the box and a container too small was chosen):

- **Across a top from just above it.** On a side (n horizontal) seen from before it, the outermost point
  may be where the view's rays stop meeting a top that goes on: the next zone's ray passes over it and
  ranges something far behind, or nothing, so the zone straddles the outline, yet the top goes on under
  that ray. The view shows the side end only if the ray of the next zone outwards (along the image axis
  n points along most) comes down to the point's height past it along n within that next zone (at most
  ``NEXT_ZONE_REACH`` footprints, r tan(w) / max(|n.x|, |n.y|) each) and within a footprint of it across
  n: there a top, or the side, going on would have stopped that ray. A view from above meets the height
  a footprint past the edge; a view across the top from a few centimetres above it meets it far beyond,
  or never. A point whose zone does not straddle the outline towards n (a view looking along n at the
  object's near side, whose outermost point along n lies on that near side) shows nothing of the end.
- **Where the map carved the surface away.** Rays grazing a wide top carve its one-voxel layer, so the
  points kept as the object's (in its voxels or its ROIs' box) can end well before the surface does. A
  view shows the end only if none of its returns above the table's cut lies past the point along n in a
  zone next to the point's, no further than the outline's margin (a nearer or equal range: surface going
  on; further: background, seen past the object).

A view that shows a side end so also says how far the side may go on: no further than where its next
zone's ray comes down to the point's height (the top, or the side, going on to there would have stopped
that ray), plus the point's own Gaussian terms (those of delta(n) for one point). The face's bound is no
nearer than the least of those limits over the views that show the end. That matters when the face's
points are mostly other views': a view looking along n across a top from far (|n.x| + |n.y| 0.4 of a
footprint, its next zone's ray coming down 25 cm past its last point) shows the end, while views from
above whose frames cut the top supply most of the face's points, seen with a small footprint along n;
the quantile and delta(n) then put the face where those views' points end. On a 0.50 x 0.30 x 0.10 m box
on the ToF cell the bound had come out 19 mm short of its length so; it now lies 19 cm beyond.

It also assumes that every part of the object is at least half a zone footprint wide where it was seen
(15-20 mm at 0.3-0.4 m for the VL53L8CX), as the sim ranges a zone (the median of its sub-rays): a
narrower part is never ranged, and nothing in the captures shows it. The held-out lamp's 16 mm rod is
missed from HEU's and raster's views, 0.35-0.4 m away (the bound 50-84 mm under it); LR-NBV's and NBV's
views come closer and range it (the bound held on seeds 0-9 but for one NBV scan, 4 mm under). So is the
tip of a slender taper, beyond what the outline term allows: a taper of half-angle alpha is narrower than
half a footprint F over F / (4 tan alpha) from its tip, longer than the one footprint of item 1 when
alpha is under 14 deg. The held-out spire, 6 cm wide and 15 cm tall (11.3 deg), left the bound 23-81 mm
under on HEU, 29-45 mm on raster and, on seeds 5-9, 3-25 mm under on three LR-NBV scans and 13-16 mm on
two NBV ones (within it on seeds 0-4): the zones at its tip, from the side or from straight above (11 cm
away on one scan), range its flanks a few centimetres below it. A real
VL53L8CX reports up to four targets per zone, but only targets about 60 cm apart or more as separate
ones (nearer ones merge into one return, status 9: ST's support on its community forum), so a rod
10-20 cm before the table would not show as a target of its own either.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np
from numpy.typing import NDArray

from cell.config.models import CellConfig
from cell.packing.box import PackingBox
from cell.packing.zones import NEIGHBOURS, outline_sides, surface_normals, zone_grid
from drivers.depth.base import SensorModel
from drivers.depth.config import DepthNoiseConfig

Array = NDArray[np.float64]

# The share of the points, outermost along a face's normal, that the face's delta is taken over: a few
# zones' worth on each face of a scan of some thousand points, more than the estimate's trim.
FACE_FRACTION = 0.05
# A point faces the face when its surface normal is within this angle of the face's [deg]: twice the
# normal's error from the range noise at the scans' ranges, far from the 90 deg between adjacent faces.
FACING_DEG = 35.0
# A neighbour zone further than a zone by more than this many std of two ranges' difference saw past it.
OUTLINE_SIGMAS = 3.0
# How far past a view's outermost point along a side's normal the ray of its next zone outwards may come
# down to that point's height and still show the side end there [footprints along the normal]: within
# that next zone, whose cone reaches 1.5 footprints out from the point's central ray (Seen._end_shown).
NEXT_ZONE_REACH = 1.5
# The sim VL53L8CX's range noise, for a real sensor whose config carries none (BoxUncertaintyConfig).
DEFAULT_RANGE_NOISE = DepthNoiseConfig(sigma0_m=0.004, k_per_m=0.01)


@dataclass(frozen=True)
class Sighting:
    """One capture: the sensor pose it was taken from (``T_base_sensor``, 4x4), its points (K, 3) [m] and
    the ends (J, 3) [m] of the rays it carved free (``PerceptionUpdate.free_ends_base``), all base
    frame."""

    T_base_sensor: Array
    points: Array
    free_ends: Array = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass(frozen=True)
class ErrorModel:
    """The allowance delta(n) of the module docstring: ``zone_rad`` w [rad], range noise sigma(r) =
    ``sigma0_m`` + ``k_per_m`` r^2 [m] and bias std ``bias_m`` [m], ``voxel_m`` the map resolution [m],
    pose std ``pose_m`` [m] and ``pose_rad`` [rad], ``coverage`` the factor on the Gaussian terms;
    ``half_fov_rad`` half the field of view [rad] across (x) and down (y) the image; ``crop_m`` the
    perception's crop box, its (lower, upper) corners [m, sensor frame], and ``filter_voxel_m`` the voxel
    filter's edge [m] after it (None and 0: nothing cropped); ``capture_pose_m`` [m] and
    ``capture_pose_rad`` [rad] the std of the pose error's part that differs between captures (0: none)."""

    zone_rad: float
    sigma0_m: float
    k_per_m: float
    bias_m: float
    voxel_m: float
    pose_m: float
    pose_rad: float
    coverage: float
    half_fov_rad: tuple[float, float]
    crop_m: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    filter_voxel_m: float = 0.0
    capture_pose_m: float = 0.0
    capture_pose_rad: float = 0.0

    def delta(self, ranges: Array, along_ray: Array, footprints: Array) -> float:
        """delta(n) [m] of a face from its K >= 1 points: their ``ranges`` r (K,) [m], ``along_ray``
        |n.d| (K,) and ``footprints`` f (K,) (:meth:`Seen.footprints`; the module docstring, medians over
        the points)."""
        r, along = float(np.median(ranges)), float(np.median(along_ray))
        return (self.footprint(ranges, footprints) + self.voxel_m / 2.0
                + self.gaussian(r, along, ranges.shape[0]))

    def gaussian(self, r: float, along: float, k: int) -> float:
        """The Gaussian terms of delta(n) [m], ``coverage`` times their combined std, for a face's ``k``
        points at range ``r`` [m] and |n.d| ``along``: the range noise of their quantile, the range bias
        and the pose (the module docstring, items 3-5)."""
        sigma = self.range_sigma(r)
        pose = self.pose_m + r * self.pose_rad
        return self.coverage * math.sqrt(along**2 * (sigma**2 / k + self.bias_m**2) + pose**2)

    def range_sigma(self, ranges: Array | float) -> Array | float:
        """sigma(r) = sigma0 + k r^2 [m] of ranges r [m]."""
        return self.sigma0_m + self.k_per_m * ranges**2

    def footprint(self, ranges: Array, footprints: Array) -> float:
        """How far [m] a face may lie beyond its K >= 1 points by their zones' footprints, r tan(w) f, from
        their ``ranges`` r (K,) [m] and ``footprints`` f (K,) along the face's normal n (|n.x| + |n.y|
        of their views, or :meth:`Seen.footprints`; medians over the points)."""
        return float(np.median(ranges)) * math.tan(self.zone_rad) * float(np.median(footprints))


def error_model(config: CellConfig, sensor: SensorModel) -> ErrorModel:
    """The error model of a cell with this sensor: its zone (or pixel) angle, its range noise (the
    packing config's, else the sensor config's ``noise``, else :data:`DEFAULT_RANGE_NOISE`), the map
    resolution and the packing config's bias, pose and coverage factor."""
    u = config.packing.uncertainty
    noise = u.range_noise or getattr(config.sensor, "noise", None) or DEFAULT_RANGE_NOISE
    crop = config.perception.crop_box
    return ErrorModel(zone_rad=math.radians(sensor.fov_x_deg) / sensor.width, sigma0_m=noise.sigma0_m,
                      k_per_m=noise.k_per_m, bias_m=u.range_bias_m,
                      voxel_m=config.perception.occupancy.resolution_m, pose_m=u.pose_translation_m,
                      pose_rad=u.pose_rotation_rad, coverage=u.coverage_factor,
                      half_fov_rad=(math.radians(sensor.fov_x_deg) / 2.0,
                                    math.radians(sensor.fov_y_deg) / 2.0),
                      crop_m=((crop.x_m[0], crop.y_m[0], crop.z_m[0]),
                              (crop.x_m[1], crop.y_m[1], crop.z_m[1])),
                      filter_voxel_m=config.perception.voxel_m, capture_pose_m=u.capture_pose_translation_m,
                      capture_pose_rad=u.capture_pose_rotation_rad)


def _outward_side(image: Array) -> NDArray[np.intp]:
    """The side of a zone that a face normal with components ``image`` (K, 2) along its view's image axes
    x and y points to, as a column of :attr:`Seen.straddles` (``cell.packing.zones.NEIGHBOURS``: +x, -x,
    +y, -y): the axis it points along most."""
    across = np.abs(image[:, 0]) >= np.abs(image[:, 1])
    return np.where(across, np.where(image[:, 0] > 0, 0, 1), np.where(image[:, 1] > 0, 2, 3))


def _comes_down_beyond(start: Array, ray: Array, n: Array, reach: float, width: float) -> float | None:
    """How far [m] beyond a point on a side of the object, along the side's horizontal unit normal ``n``
    (3,), the ray from ``start`` (3,) [m, relative to the point] along ``ray`` (3,) first comes down to the
    point's height within ``width`` [m] of it across (along the horizontal perpendicular to n), if it does
    so more than 0 and at most ``reach`` [m] beyond it: where the side, or a top at the point's height,
    going on past the point would have stopped the ray; None when it does not."""
    across = np.array([-n[1], n[0], 0.0])
    lo, hi = 0.0, math.inf
    # each bound is a + b t <= c on the ray's parameter t >= 0
    bounds = ((-(start @ n), -(ray @ n), 0.0), (start @ n, ray @ n, reach), (start[2], ray[2], 0.0),
              (start @ across, ray @ across, width), (-(start @ across), -(ray @ across), width))
    for a, b, c in ((float(a), float(b), c) for a, b, c in bounds):
        if abs(b) < 1e-12:
            if a > c:
                return None
        elif b > 0.0:
            hi = min(hi, (c - a) / b)
        else:
            lo = max(lo, (c - a) / b)
    return float((start + lo * ray) @ n) if lo < hi else None


def outline_margin(model: ErrorModel, ranges: Array | float) -> Array:
    """How far [m] a neighbouring zone may range beyond zones at ``ranges`` [m] and not have seen past the
    object: ``OUTLINE_SIGMAS`` std of two ranges' difference."""
    return OUTLINE_SIGMAS * math.sqrt(2.0) * np.asarray(model.range_sigma(ranges))


@dataclass(frozen=True)
class Seen:
    """Object points (K, 3) [m, base frame] with what the allowance needs of the view each came from:
    ``origins`` (K, 3) the sensor position [m] and ``axes`` (K, 3, 3) R_base_sensor (columns x, y, z);
    both None when the views are unknown, and then every point counts as seen from ``range_m`` [m] in
    the worst way for every face (sqrt 2 footprints sideways and the whole range error along n).
    ``normals`` (K, 3) the local surface normal at each point from its capture's neighbouring zones
    (:func:`cell.packing.zones.surface_normals`, NaN where unknown), None when not computed; ``straddles``
    (K, 4) on which sides (``cell.packing.zones.NEIGHBOURS``) each point's zone straddles the object's
    outline in its capture, its neighbour there having seen past the object
    (:func:`cell.packing.zones.outline_sides`), None when not computed (then :attr:`inside` is too).
    ``views`` (K,) the index of each point's capture, None when not known (the views are then told apart
    by their poses); ``loose`` (J, 3) [m] the captures' returns above the table that are not the
    object's points (not in its voxels or in its ROIs' box) and ``loose_views`` (J,) their captures'
    indices: surface that a capture saw beside what the map kept of the object (:meth:`end_limit`)."""

    points: Array
    origins: Array | None = None
    axes: Array | None = None
    range_m: float = 0.0
    normals: Array | None = None
    straddles: NDArray[np.bool_] | None = None
    views: NDArray[np.intp] | None = None
    loose: Array | None = None
    loose_views: NDArray[np.intp] | None = None

    @staticmethod
    def of(sightings: list[Sighting], keep: NDArray[np.bool_], model: ErrorModel | None = None,
           loose: NDArray[np.bool_] | None = None) -> Seen:
        """The points of ``sightings`` (at least one), in order, where ``keep`` (over all of them,
        concatenated), with the points where ``loose`` (likewise; None: none) as :attr:`loose`; with
        ``model``, each point's surface normal from the kept points of its own capture on the model's
        zone grid, and whether it lies inside its capture's outline."""
        counts = [s.points.shape[0] for s in sightings]
        points = np.vstack([s.points for s in sightings])
        origins = np.repeat(np.array([s.T_base_sensor[:3, 3] for s in sightings]), counts, axis=0)
        axes = np.repeat(np.array([s.T_base_sensor[:3, :3] for s in sightings]), counts, axis=0)
        views = np.repeat(np.arange(len(sightings)), counts)
        loose = np.zeros(points.shape[0], dtype=bool) if loose is None else loose & ~keep
        known = Seen(points[keep], origins[keep], axes[keep], views=views[keep], loose=points[loose],
                     loose_views=views[loose])
        if model is None:
            return known
        starts = np.cumsum([0, *counts])

        normals, sides = [], []
        for s, a, b in zip(sightings, starts[:-1], starts[1:], strict=True):
            kept = s.points[keep[a:b]]
            normals.append(surface_normals(s.T_base_sensor, kept, model.zone_rad, model.half_fov_rad))
            returns = np.vstack([s.points, s.free_ends])
            on_object = np.concatenate([keep[a:b], np.zeros(s.free_ends.shape[0], dtype=bool)])
            sides.append(outline_sides(s.T_base_sensor, returns, on_object, partial(outline_margin, model),
                                       model.zone_rad, model.half_fov_rad)[:s.points.shape[0]][keep[a:b]])
        return replace(known, normals=np.vstack(normals), straddles=np.vstack(sides))

    @property
    def inside(self) -> NDArray[np.bool_] | None:
        """Mask (K,) of the points whose zone straddles the outline on no side (inside the object's outline
        in its capture); None when ``straddles`` is."""
        return None if self.straddles is None else np.asarray(~self.straddles.any(axis=1))

    def face(self, n: Array) -> tuple[Array, NDArray[np.bool_]]:
        """The points' coordinates x (K,) [m] along the unit normal ``n`` (3,), and which of them are the
        face's: those beyond the ``1 - FACE_FRACTION`` quantile of x."""
        x = self.points @ n
        return x, x >= np.quantile(x, 1.0 - FACE_FRACTION)

    def geometry(self, n: Array) -> tuple[Array, Array, Array]:
        """Per point: range r [m], |n.d| and |n.x| + |n.y| of its view, for the face normal ``n`` (3,)."""
        k = self.points.shape[0]
        if self.origins is None or self.axes is None:
            return np.full(k, self.range_m), np.ones(k), np.full(k, math.sqrt(2.0))
        offset = self.points - self.origins
        ranges = np.linalg.norm(offset, axis=1)
        along = np.abs(offset @ n) / np.maximum(ranges, 1e-9)
        return ranges, along, np.abs(self._image(n)).sum(axis=1)

    def _image(self, n: Array) -> Array:
        """The components (K, 2) of the unit normal ``n`` (3,) along each point's view's image axes x
        (right) and y (down); the views must be known."""
        assert self.axes is not None
        return np.asarray(np.einsum("kaj,a->kj", self.axes[:, :, :2], n))

    def footprints(self, n: Array, face: NDArray[np.bool_]) -> Array:
        """Per point (K,): how many zone footprints along the face normal ``n`` (3,) the face may lie
        beyond it (module docstring, item 1): |n.x| + |n.y| of its view; for a face none of whose points
        ``face`` (K,) lies on it (a surface normal within ``FACING_DEG`` of n), 1 / max(|n.x|, |n.y|)
        where the point's zone straddles the outline on the side n points to in the image, if more;
        sqrt 2 when the views are unknown."""
        k = self.points.shape[0]
        if self.origins is None or self.axes is None:
            return np.full(k, math.sqrt(2.0))
        image = self._image(n)
        sideways = np.abs(image).sum(axis=1)
        if self.straddles is None or self.normals is None:
            return sideways
        with np.errstate(invalid="ignore"):  # NaN normals: not known to lie on the face
            ranged = bool(np.any(self.normals[face] @ n >= math.cos(math.radians(FACING_DEG))))
        if ranged:
            return sideways
        outward = self.straddles[np.arange(k), _outward_side(image)]
        steepest = np.maximum(np.abs(image).max(axis=1), 1e-9)
        return np.where(outward, np.maximum(1.0 / steepest, sideways), sideways)

    def framed(self, model: ErrorModel) -> NDArray[np.bool_]:
        """Mask (K,) of the points seen at least a zone and a filter voxel inside their view's field of
        view and, when ``model`` has a crop box, inside it (module docstring; all True when the views are
        unknown)."""
        if self.origins is None or self.axes is None:
            return np.ones(self.points.shape[0], dtype=bool)
        local = np.einsum("kaj,ka->kj", self.axes, self.points - self.origins)  # sensor frame
        ranges = np.maximum(np.linalg.norm(local, axis=1), 1e-9)
        inset = model.zone_rad + model.filter_voxel_m / ranges  # [rad]
        across = np.abs(np.arctan2(local[:, 0], local[:, 2]))
        down = np.abs(np.arctan2(local[:, 1], local[:, 2]))
        framed = (across < model.half_fov_rad[0] - inset) & (down < model.half_fov_rad[1] - inset)
        if model.crop_m is not None:
            margin = ranges[:, None] * math.tan(model.zone_rad) + model.filter_voxel_m
            lower, upper = np.array(model.crop_m[0]), np.array(model.crop_m[1])
            framed &= np.all((local > lower + margin) & (local < upper - margin), axis=1)
        return np.asarray(framed)

    def end_limit(self, model: ErrorModel, n: Array) -> float:
        """How far [m, coordinate along the unit normal ``n`` (3,)] the views that saw the object end
        along n inside what they kept let it lie: over the views whose outermost point along n is
        :meth:`framed` (a view that the frame's border cut has its outermost point on that border) and
        shows the object end there (:meth:`_end_shown`), the least of their limits; infinite when no view
        does, -infinite when one shows it with no limit of its own (then the face's delta(n) alone bounds
        it); -infinite when the views are unknown."""
        if self.origins is None or self.axes is None:
            return -math.inf
        if self.views is None:
            poses = np.hstack([self.origins, self.axes.reshape(-1, 9)])
            view = np.unique(poses, axis=0, return_inverse=True)[1].ravel()
        else:
            view = self.views
        order = np.lexsort((-(self.points @ n), view))  # by view, each view's outermost first
        outermost = order[np.r_[True, view[order][1:] != view[order][:-1]]]
        limits = [self._end_shown(model, n, int(end)) for end in outermost[self.framed(model)[outermost]]]
        return min((limit for limit in limits if limit is not None), default=math.inf)

    def _end_shown(self, model: ErrorModel, n: Array, end: int) -> float | None:
        """Whether the view of point ``end``, its outermost along the unit normal ``n`` (3,), shows the
        object end there (the module docstring), and how far along n it lets the end lie [m, coordinate
        along n]; None when it does not show it. On a side (n horizontal) seen from before it, its zone
        straddles the outline towards n and the ray of the next zone that way comes down to its height
        within ``NEXT_ZONE_REACH`` footprints past it along n (a ray that passes over the object, or
        meets that height far beyond, does not show where the object ends under it): the end lies no
        further than where that ray comes down, plus the point's Gaussian terms (delta(n)'s, of one
        point). A view that shows the end otherwise (from beyond the side, or of the top) sets no limit
        of its own (-infinite). Either way no :attr:`loose` return of the view lies past it along n in a
        zone next to its own, nearer than the outline's margin (the surface going on where the map kept
        none of it)."""
        assert self.origins is not None and self.axes is not None
        origin, axes, point = self.origins[end], self.axes[end], self.points[end]
        image = axes[:, :2].T @ n
        local = (point - origin) @ axes
        row, col = zone_grid(local[None, :], model.zone_rad, model.half_fov_rad)
        r = float(np.linalg.norm(local))
        limit = -math.inf
        if n[2] == 0.0 and origin @ n < point @ n:
            side = int(_outward_side(image[None, :])[0])
            if self.straddles is not None and not self.straddles[end, side]:
                return None
            step = np.array(NEIGHBOURS[side])
            down, across = (np.array([row[0], col[0]]) + step + 0.5) * model.zone_rad \
                - np.array(model.half_fov_rad[::-1])
            ray = axes @ np.array([math.tan(across), math.tan(down), 1.0])
            ray /= np.linalg.norm(ray)
            footprint = r * math.tan(model.zone_rad)
            reach = NEXT_ZONE_REACH * footprint / max(float(np.abs(image).max()), 1e-9)
            beyond = _comes_down_beyond(origin - point, ray, n, reach, footprint)
            if beyond is None:
                return None
            limit = float(point @ n) + beyond + model.gaussian(r, abs(float((point - origin) @ n)) / r, 1)
        if self.loose is None or self.loose_views is None or self.views is None:
            return limit
        beside = self.loose[(self.loose_views == self.views[end]) & (self.loose @ n > point @ n)]
        if beside.shape[0] == 0:
            return limit
        near = (beside - origin) @ axes
        rows, cols = zone_grid(near, model.zone_rad, model.half_fov_rad)
        nearer = np.linalg.norm(near, axis=1) - r <= outline_margin(model, r)
        return None if np.any((np.abs(rows - row[0]) <= 1) & (np.abs(cols - col[0]) <= 1) & nearer) else limit


def face_bound(model: ErrorModel, seen: Seen, n: Array, trim: float) -> float:
    """The upper bound [m] of the face with outward unit normal ``n`` (3,), as a coordinate along n: the
    ``1 - trim`` quantile of n.p over the points plus delta(n) of the face's points (those beyond the
    ``1 - FACE_FRACTION`` quantile), and no nearer than the views that showed the object end along n let
    it lie (:meth:`Seen.end_limit`); infinite when no view saw the object end along n inside its
    frame."""
    x, face = seen.face(n)
    limit = seen.end_limit(model, n)
    if limit == math.inf:
        return math.inf
    ranges, along, _ = seen.geometry(n)
    footprints = seen.footprints(n, face)
    bound = float(np.quantile(x, 1.0 - trim)) + model.delta(ranges[face], along[face], footprints[face])
    return max(bound, limit)


def upper_dims(box: PackingBox, model: ErrorModel, seen: Seen, trim: float) -> Array:
    """Upper bounds (L, W, H) [m] of the box's dimensions from the object's points ``seen``: the
    distance between the bounds of the two faces of L and of W (along the box's yaw), and from the
    box's floor (``z_min``) to the top's bound; each at least the box's own dimension, infinite when a
    face has no bound (:func:`face_bound`)."""
    bounds = [face_bound(model, seen, n, trim) for n in box.face_normals()]
    dims = np.array([bounds[0] + bounds[1], bounds[2] + bounds[3], bounds[4] - box.z_min])
    return np.maximum(dims, box.dims)
