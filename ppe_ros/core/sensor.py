"""Sensor models: the range noise of each ray, and the extraction profile of each kind of sensor.

Pure numpy/numba; no ROS import. A :class:`NoiseModel` gives every ray k a standard deviation sigma_k (m) of
its measured length r_k; the extractor then minimises the sum of squared *normalised* residuals
((r_k - rhat_k) / sigma_k)^2, so that its error increments are dimensionless (chi^2 units). The
paper's model is the special case sigma_k = 1 m: the increments are the paper's m^2, bit for bit.

The noise model (all terms independent, added in quadrature)::

    sigma_k^2 = constant^2 + (proportional * r_k)^2 + (depth_quadratic * z_k^2 * r_k / z_k)^2

``z_k`` is the depth of the endpoint along ``optical_axis`` (a depth camera's z; its axial noise
``depth_quadratic * z^2`` turned into ray-length noise by the ray's obliquity ``r / z``).

The coefficients of a device family are not those of every device (a simulated or a newer camera
is far less noisy than a Kinect v1), so a profile may *scale* its model to the scan at hand
(:func:`estimate_noise_scale`): the random part of the noise is measured from second differences
of the ranges along each grid row, which cancel every smooth or per-beam error and keep the
independent noise, and the model is multiplied by its ratio to the model's prediction.

A :class:`SensorProfile` bundles a noise model with the extraction settings chosen for that kind of
sensor (the greedy's stop, the surface tolerance of the consolidation, the smallest plane); see
docs/algorithm.md ("Sensor models and whole surfaces").
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, replace

import numba as nb
import numpy as np

from ppe_ros.core.scan import ray_spacing_deg

#: The depth cameras' optical axis in their optical frame (x right, y down, z forward).
OPTICAL_AXIS = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class NoiseModel:
    """Standard deviation of a ray's measured length, sigma(r, z) in metres (see the module docstring).

    Attributes:
        constant: range noise independent of range (m).
        proportional: range noise per metre of range (dimensionless).
        depth_quadratic: axial noise coefficient c of sigma_z = c z^2 (1/m), for depth cameras.
        optical_axis: the axis along which z is measured (unit vector, the input frame).
        minimum: a floor on sigma (m), so that no ray gets an infinite weight.
    """

    constant: float = 0.0
    proportional: float = 0.0
    depth_quadratic: float = 0.0
    optical_axis: tuple[float, float, float] = OPTICAL_AXIS
    minimum: float = 1e-4

    def __post_init__(self) -> None:
        for name in ('constant', 'proportional', 'depth_quadratic', 'minimum'):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0.0):
                raise ValueError(f'noise model {name} must be finite and >= 0; got {value!r}')
        if not self.minimum > 0.0:
            raise ValueError(f'noise model minimum must be > 0 m; got {self.minimum!r}')
        axis = np.asarray(self.optical_axis, dtype=np.float64)
        if axis.shape != (3,) or not np.all(np.isfinite(axis)) or not np.linalg.norm(axis) > 0:
            raise ValueError(f'optical_axis must be a non-zero 3-vector; got {self.optical_axis!r}')
        if self.constant == 0.0 and self.proportional == 0.0 and self.depth_quadratic == 0.0:
            raise ValueError('a noise model needs at least one of constant, proportional, depth_quadratic > 0')

    def sigmas(self, ranges: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """sigma_k (m) of rays with lengths ``ranges`` (n,) and unit ``directions`` (n, 3).

        Invalid rays (NaN range) get NaN.
        """
        r = np.asarray(ranges, dtype=np.float64)
        variance = np.full(r.shape, self.constant**2)
        if self.proportional:
            variance += (self.proportional * r) ** 2
        if self.depth_quadratic:
            axis = np.asarray(self.optical_axis, dtype=np.float64)
            axis = axis / np.linalg.norm(axis)
            cos = np.abs(directions @ axis)
            z = r * cos
            # sigma_r = c z^2 / cos: the axial noise along the ray; rays at 90 deg to the axis get
            # the noise of their range as depth
            with np.errstate(divide='ignore', invalid='ignore'):
                along_ray = np.where(cos > 1e-3, self.depth_quadratic * z * z / cos, self.depth_quadratic * r * r)
            variance += along_ray**2
        return np.maximum(np.sqrt(variance), self.minimum)

    def ray_sigmas(
        self, ranges: np.ndarray, directions: np.ndarray, valid: np.ndarray, scaled_directions: np.ndarray | None = None
    ) -> np.ndarray:
        """:meth:`sigmas` (m) of the ``valid`` rays of lengths ``ranges`` ((n,), m) and unit ``directions``
        (n, 3), NaN for the others, in one parallel pass (the same values: bit for bit with an optical axis
        along x, y or z).

        scaled_directions: None, or a C-contiguous (n, 3) float64 array that receives
        ``directions * sigma_k`` (times 0 for the rays that are not valid): a scan's rays scaled to unit noise.
        """
        r = np.ascontiguousarray(ranges, dtype=np.float64)
        d = np.ascontiguousarray(directions, dtype=np.float64)
        ok = np.ascontiguousarray(valid, dtype=np.bool_)
        if r.ndim != 1 or d.shape != (len(r), 3) or ok.shape != r.shape:
            raise ValueError(f'ranges (n,), directions (n, 3), valid (n,); got {r.shape}, {d.shape}, {ok.shape}')
        scale = scaled_directions is not None
        if scale and not (
            scaled_directions.shape == d.shape
            and scaled_directions.dtype == np.float64
            and scaled_directions.flags.c_contiguous
        ):
            raise ValueError(f'scaled_directions must be a C-contiguous float64 array of shape {d.shape}')
        sigmas = np.empty(len(r))
        _ray_sigmas_kernel(r, d, ok, *self._terms(), sigmas, scaled_directions if scale else d, scale)
        return sigmas

    def _terms(self) -> tuple:
        """(constant^2, proportional, depth_quadratic, unit optical axis (3,), minimum) for the kernels."""
        axis = np.asarray(self.optical_axis, dtype=np.float64)
        return (
            float(self.constant) ** 2,
            float(self.proportional),
            float(self.depth_quadratic),
            axis / np.linalg.norm(axis),
            float(self.minimum),
        )

    def scaled(self, factor: float) -> NoiseModel:
        """The model with every sigma_k multiplied by ``factor`` (> 0), the floor too."""
        factor = float(factor)
        if not (np.isfinite(factor) and factor > 0.0):
            raise ValueError(f'noise scale must be finite and > 0; got {factor!r}')
        return replace(
            self,
            constant=self.constant * factor,
            proportional=self.proportional * factor,
            depth_quadratic=self.depth_quadratic * factor,
            minimum=self.minimum * factor,
        )


@nb.njit(cache=True, error_model='numpy', nogil=True, inline='always')
def _ray_sigma(r, d0, d1, d2, constant2, proportional, depth_quadratic, axis, minimum):
    """NoiseModel.sigmas of one ray of length r and unit direction d: its operations in its order."""
    variance = constant2
    if proportional != 0.0:
        scaled = proportional * r
        variance = variance + scaled * scaled
    if depth_quadratic != 0.0:
        cos = abs((d0 * axis[0] + d1 * axis[1]) + d2 * axis[2])
        z = r * cos
        along = depth_quadratic * z * z / cos if cos > 1e-3 else depth_quadratic * r * r
        variance = variance + along * along
    sigma = np.sqrt(variance)
    return minimum if sigma < minimum else sigma  # np.maximum: NaN stays NaN


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _ray_sigmas_kernel(
    ranges, directions, valid, constant2, proportional, depth_quadratic, axis, minimum, sigmas, scaled, scale
):
    """sigmas[k] (NaN: not valid[k]) and, when scale, scaled[k] = directions[k] * sigma_k (* 0: not valid)."""
    for k in nb.prange(len(ranges)):
        if valid[k]:
            sigma = _ray_sigma(
                ranges[k],
                directions[k, 0],
                directions[k, 1],
                directions[k, 2],
                constant2,
                proportional,
                depth_quadratic,
                axis,
                minimum,
            )
        else:
            sigma = np.nan
        sigmas[k] = sigma
        if scale:
            for c in range(3):
                scaled[k, c] = directions[k, c] * sigma if valid[k] else directions[k, c] * 0.0


def estimate_noise_scale(ranges: np.ndarray, sigmas: np.ndarray) -> float:
    """Ratio of a scan's random range noise to a noise model's sigmas; NaN with too few samples.

    Args:
        ranges: ``(H, W)`` measured ray lengths (m), NaN = no return.
        sigmas: ``(H, W)`` the model's sigma_k (m) of the same rays.

    Along a grid row the second difference ``r[j-1] - 2 r[j] + r[j+1]`` of three rays on one
    surface is, for independent noise of sigma_k, about N(0, 6 sigma_k^2): the surface's range
    profile is close to linear over three neighbouring rays, and per-beam biases and smooth errors
    cancel. The scale is the median of ``|second difference| / (sqrt(6) sigma_k)`` divided by
    0.6745 (the median of |N(0, 1)|): robust to the depth jumps at edges, which are outliers.
    At least 100 triples of valid rays are needed.
    """
    r = np.asarray(ranges, dtype=np.float64)
    sig = np.asarray(sigmas, dtype=np.float64)
    if r.ndim != 2 or r.shape != sig.shape:
        raise ValueError(f'ranges and sigmas must be (H, W) arrays of one shape; got {r.shape} and {sig.shape}')
    second = r[:, :-2] - 2.0 * r[:, 1:-1] + r[:, 2:]
    with np.errstate(invalid='ignore', divide='ignore'):
        ratio = np.abs(second) / (np.sqrt(6.0) * sig[:, 1:-1])
    return _scale_of_ratios(ratio[np.isfinite(ratio)])


def _scale_of_ratios(ratios: np.ndarray) -> float:
    """estimate_noise_scale from its finite ratios |second difference| / (sqrt(6) sigma_k) (any order)."""
    if len(ratios) < 100:
        return float('nan')
    return float(np.median(ratios) / 0.6744897501960817)


def _scan_noise_scale(noise: NoiseModel, points: np.ndarray, starts: np.ndarray) -> float:
    """``estimate_noise_scale(ranges, sigmas)`` of an organized scan (H, W, 3) with ray starts (3,) or
    (H, W, 3): the ranges |p - s| (m) and noise.sigmas of the valid rays (finite, length > 0), the
    ratios in one parallel pass (the same values as numpy's, so the same median)."""
    height, width = points.shape[:2]
    ranges = np.empty((height, width))
    sigmas = np.empty((height, width))
    ratios = np.empty((height, max(width - 2, 0)))
    _second_difference_ratios(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(np.reshape(starts, (-1, 3)), dtype=np.float64),
        *noise._terms(),
        ranges,
        sigmas,
        ratios,
    )
    return _scale_of_ratios(_finite_values(ratios.reshape(-1)))


@nb.njit(cache=True, error_model='numpy', parallel=True)
def _second_difference_ratios(
    points, starts, constant2, proportional, depth_quadratic, axis, minimum, ranges, sigmas, ratios
):
    """Each ray's range |p - s| (m; norm's (x^2 + y^2) + z^2) and sigma (NaN unless the range is finite and
    > 0), then along each row |(r[j-1] - 2 r[j]) + r[j+1]| / (sqrt(6) sigma[j]) into ratios[:, j-1].
    starts: (1, 3), or (H*W, 3) one per ray."""
    height, width = ranges.shape
    per_ray = starts.shape[0] > 1
    for i in nb.prange(height):
        for j in range(width):
            s = i * width + j if per_ray else 0
            x = points[i, j, 0] - starts[s, 0]
            y = points[i, j, 1] - starts[s, 1]
            z = points[i, j, 2] - starts[s, 2]
            r = np.sqrt((x * x + y * y) + z * z)
            ranges[i, j] = r
            inverse = r if r > 0.0 else np.nan
            d0, d1, d2 = x / inverse, y / inverse, z / inverse
            if np.isfinite(r) and r > 0.0 and np.isfinite(d0) and np.isfinite(d1) and np.isfinite(d2):
                sigmas[i, j] = _ray_sigma(r, d0, d1, d2, constant2, proportional, depth_quadratic, axis, minimum)
            else:
                sigmas[i, j] = np.nan
    root6 = np.sqrt(6.0)
    for i in nb.prange(height):
        for j in range(1, width - 1):
            second = (ranges[i, j - 1] - 2.0 * ranges[i, j]) + ranges[i, j + 1]
            ratios[i, j - 1] = abs(second) / (root6 * sigmas[i, j])


@nb.njit(cache=True, error_model='numpy', nogil=True)
def _finite_values(values):
    """The finite entries of values (1-D), in order."""
    out = np.empty(len(values))
    n = 0
    for v in values:
        if np.isfinite(v):
            out[n] = v
            n += 1
    return out[:n]


def check_step_factor(step_factor: float) -> float:
    """``step_factor`` (kappa of the consolidation's step test) as a float; ValueError unless it is a finite
    number >= 1."""
    value = step_factor
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real) or not (1.0 <= value < np.inf):
        raise ValueError(f'step_factor must be a finite number >= 1 (1: the step within t); got {value!r}')
    return float(value)


def is_whole_number(value) -> bool:
    """True for a real number with no fractional part (not a bool): a count given as 300 or 300.0."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_) and float(value).is_integer()


def check_boundary_join_points(min_points: int) -> int:
    """``boundary_join_points`` (the boundary round's smallest surface, rays) as an int; ValueError unless it
    is an integer >= 1."""
    value = min_points
    if not is_whole_number(value) or value < 1:
        raise ValueError(f'boundary_join_points must be an integer >= 1 (rays of a surface) or None; got {value!r}')
    return int(value)


def check_optional_length(name: str, value, what: str) -> None:
    """ValueError unless ``value`` is None or a finite real number > 0 (metres; not a bool)."""
    if value is not None and (
        isinstance(value, bool) or not (isinstance(value, numbers.Real) and np.isfinite(value) and value > 0)
    ):
        raise ValueError(f'{name} must be {what} > 0 m or None; got {value!r}')


@dataclass(frozen=True)
class SensorProfile:
    """The extraction settings of one kind of sensor.

    Attributes:
        name: 'paper', 'lidar' or 'depth_camera' (or a user's own).
        noise: the range noise model; None = the paper's (sigma = 1 m: increments in m^2).
        max_error_increment: the greedy's stop (dimensionless with a noise model, m^2 without).
        max_neighbor_distance: lmax (m); inf = no limit.
        surface_tolerance: tau (m): the RMS deviation from its plane that one physical surface may
            show (flatness, the sensor's systematic errors); None = no consolidation (the paper).
        noise_factor: lambda: the tolerance of a piece is sqrt(tau^2 + lambda^2 mean sigma_k^2).
        connected_only: consolidate only pieces that touch in the grid (no merge across occluders).
        min_plane_points: smaller planes are reported as no plane (with reference_ray_spacing_deg: at that
            spacing; :meth:`min_plane_points_for`).
        reference_ray_spacing_deg: (along rows, along columns) angular spacing (degrees) of the rays at which
            min_plane_points holds, as :func:`ppe_ros.core.scan.ray_spacing_deg` measures it (the grid the
            value was chosen on); a coarser scan needs as many rays as cover the same solid angle, at least
            MIN_PLANE_POINTS_FLOOR; None = min_plane_points on every scan.
        max_plane_rmse_factor: a consolidated plane whose RMS point-to-plane distance exceeds this
            multiple of sqrt(tau^2 + its sensor noise^2) is not planar (trees, bushes, curved
            bodies) and is reported as no plane; inf = keep every plane.
        max_plane_curvature_factor: a consolidated plane whose best quadric surface departs from its
            plane by an RMS of more than this multiple of its tolerance tau_D (flatness_length) is
            curved (car bodies, wheels, poles) and is reported as no plane
            (surfaces.curvature_rms); inf = no curvature test.
        correlation_length: L (m) over which a surface's systematic errors are correlated: the
            covariances add their part, which does not shrink with the number of points
            (surfaces.systematic_covariances); None = the fit's covariance alone (the paper).
        quadrant_jackknife: with correlation_length, also count the spread of each plane's fit over
            its four quadrants (errors correlated over the whole plane: what moves the plane when
            another part of the surface is seen; ppe_ros.core.quadrants).
        row_jackknife: with correlation_length, also count the spread of each plane's fit over the grid
            rows it spans, one left out at a time (a spinning lidar's beams: each beam's range bias and
            angle error is shared by all its points, and a plane seen by few beams moves with them;
            ppe_ros.core.quadrants.jackknife_of_members with row_width); with quadrant_jackknife, per plane
            the one of larger trace.
        flatness_length: D0 (m): the planarity test's tolerance of a plane of size D is
            tau min(1, D / D0) (a small patch must be flat to the noise; surfaces.whole_surfaces);
            None = tau for every plane.
        seed_shapes: the tetrominoes that seed the greedy's planes: 'all' (the paper's 17) or 'square'
            (the 2 x 2 square alone: a 17th of the seed work; ppe_ros.core.ppe.GreedyOptions).
        block_seeds: start the greedy with the 4 x 4 blocks of rays that fit one plane within its stop
            (ppe_ros.core.ppe.GreedyOptions.block_seeds; off in the built-in profiles: see
            docs/algorithm.md for what it costs in consistency).
        candidate_fits, fit_tolerance: how the greedy values the extensions of its small planes
            ('exact' or 'one_step') and the convergence tolerance of their exact fits (None: the exact
            greedy's; ppe_ros.core.ppe.GreedyOptions).
        noise_scale_bounds: (low, high): scale the noise model to each scan by
            :func:`estimate_noise_scale`, clamped to these bounds; None = use the model as it is.
        large_surface_share: a surface holding at least this share of the scan's valid rays also joins
            a coplanar surface across an occluder of any width along a row or column (a floor behind
            furniture; ppe_ros.core.consolidation, large surfaces), not only across 64 pixels; None =
            off. Never with connected_only.
        step_factor: kappa >= 1: two pieces of one surface may be kappa times their tolerance apart
            where their planes are compared at the nearer piece's mean (the consolidation's step test;
            a plane extrapolated there also carries the pieces' tilt, as on a cambered road); 1 = the
            tolerance itself.
        boundary_join_points: after the merges and the absorption, two surfaces of at least this many
            rays that share a boundary (touching, or across at most 3 rays without a surface along a
            row or column) are one surface when each is within t of their union's plane and their
            planes meet at that boundary (a cambered road's halves; not a kerb: ppe_ros.core.boundary_join);
            None = off.
        min_plane_width: w (m): a plane whose points span less than w across (sqrt(12 l2), l2 the
            scatter's second-largest eigenvalue: the width of a uniform strip) is reported as no plane
            (a sliver along a rounded edge, whose curvature across it is too narrow to see); None = off.
        min_plane_breadth: b (m): a plane narrower than b across in the grid is reported as no plane (a
            pole, a trunk, a branch, a person: thin things whose one-sided view fits a plane only because
            it is narrow; :func:`ppe_ros.core.surfaces.plane_breadth`: the smaller of the medians, over the
            grid rows and over the grid columns the plane spans, of the extent of its points on that row or
            column); None = off.
        curvature_max_size: the curvature test (max_plane_curvature_factor) judges only planes smaller
            than this size D (m; as flatness_length's): a larger surface's bend is the sensor's own (a
            depth camera's distortion bends a wall by centimetres), a small one's is the object's (a
            cushion, a lamp shade, a plant); None = every plane.
    """

    name: str
    noise: NoiseModel | None = None
    max_error_increment: float = 0.01
    max_neighbor_distance: float = np.inf
    surface_tolerance: float | None = None
    noise_factor: float = 0.0
    connected_only: bool = False
    min_plane_points: int = 4
    reference_ray_spacing_deg: tuple[float, float] | None = None
    max_plane_rmse_factor: float = np.inf
    max_plane_curvature_factor: float = np.inf
    correlation_length: float | None = None
    noise_scale_bounds: tuple[float, float] | None = None
    flatness_length: float | None = None
    quadrant_jackknife: bool = False
    row_jackknife: bool = False
    seed_shapes: str = 'all'
    candidate_fits: str = 'exact'
    fit_tolerance: float | None = None
    block_seeds: bool = False
    large_surface_share: float | None = None
    step_factor: float = 1.0
    boundary_join_points: int | None = None
    min_plane_width: float | None = None
    min_plane_breadth: float | None = None
    curvature_max_size: float | None = None

    def __post_init__(self) -> None:
        check_step_factor(self.step_factor)
        if self.boundary_join_points is not None:
            check_boundary_join_points(self.boundary_join_points)
        if self.noise_scale_bounds is not None:
            low, high = (float(x) for x in self.noise_scale_bounds)
            if not (np.isfinite(low) and np.isfinite(high) and 0.0 < low <= high):
                raise ValueError(f'noise_scale_bounds must be 0 < low <= high; got {self.noise_scale_bounds!r}')
        if self.reference_ray_spacing_deg is not None:
            spacing = np.asarray(self.reference_ray_spacing_deg, dtype=np.float64)
            if spacing.shape != (2,) or not np.all(np.isfinite(spacing) & (spacing > 0.0)):
                raise ValueError(
                    'reference_ray_spacing_deg must be None or two angles > 0 (degrees, along rows and '
                    f'columns); got {self.reference_ray_spacing_deg!r}'
                )
        check_seed_shapes(self.seed_shapes)
        check_candidate_fits(self.candidate_fits)
        if self.fit_tolerance is not None:
            check_fit_tolerance(self.fit_tolerance)
        factor = self.max_plane_curvature_factor
        if isinstance(factor, bool) or not (isinstance(factor, numbers.Real) and factor > 0):  # NaN fails > 0
            raise ValueError(f'max_plane_curvature_factor must be a number > 0 (inf: no test); got {factor!r}')
        check_optional_length('flatness_length', self.flatness_length, 'a length')
        check_optional_length('min_plane_width', self.min_plane_width, 'a width')
        check_optional_length('min_plane_breadth', self.min_plane_breadth, 'a breadth')
        check_optional_length('curvature_max_size', self.curvature_max_size, 'a size')
        share = self.large_surface_share
        if share is not None and (isinstance(share, bool) or not (isinstance(share, numbers.Real) and 0 < share <= 1)):
            raise ValueError(f'large_surface_share must be a share in (0, 1] of the valid rays or None; got {share!r}')

    def noise_for(self, points: np.ndarray, origins: np.ndarray | None = None) -> NoiseModel | None:
        """The noise model for one organized scan ``points`` (H, W, 3) with ray starts ``origins``
        (None, (3,) or (H, W, 3)): the profile's, scaled to the scan when ``noise_scale_bounds`` is set
        (a scan with too few valid neighbours keeps the model as it is)."""
        if self.noise is None or self.noise_scale_bounds is None:
            return self.noise
        points = np.asarray(points, dtype=np.float64)
        starts = np.zeros(3) if origins is None else np.asarray(origins, dtype=np.float64)
        if points.ndim != 3 or points.shape[-1] != 3 or starts.shape not in ((3,), points.shape):
            return self.noise  # not an organized scan: the extractor's own checks report it
        scale = _scan_noise_scale(self.noise, points, starts)
        if not np.isfinite(scale):
            return self.noise
        low, high = self.noise_scale_bounds
        return self.noise.scaled(min(max(scale, float(low)), float(high)))

    def min_plane_points_for(self, points: np.ndarray, origins: np.ndarray | None = None) -> int:
        """The smallest plane (rays) on one organized scan ``points`` (H, W, 3) with ray starts ``origins``.

        With reference_ray_spacing_deg, a plane must cover the solid angle of min_plane_points rays at that
        spacing: on a scan whose rays are spaced (a, b) degrees (:func:`ppe_ros.core.scan.ray_spacing_deg`),
        ``round(min_plane_points * reference area / (a b))`` rays, never more than min_plane_points (a finer
        scan keeps the count) and never fewer than MIN_PLANE_POINTS_FLOOR. Without a reference, or on a scan
        whose spacing cannot be measured (not organized, too few valid neighbours), min_plane_points.
        """
        count = int(self.min_plane_points)
        if self.reference_ray_spacing_deg is None or np.ndim(points) != 3 or np.shape(points)[-1] != 3:
            return count
        try:
            along_rows, along_columns = ray_spacing_deg(points, origins)
        except ValueError:
            return count  # origins of another shape: the extractor's own checks report it
        area = along_rows * along_columns
        if not (np.isfinite(area) and area > 0.0):
            return count
        reference = float(self.reference_ray_spacing_deg[0]) * float(self.reference_ray_spacing_deg[1])
        scaled = round(count * reference / area)
        return min(count, max(scaled, min(MIN_PLANE_POINTS_FLOOR, count)))

    def with_overrides(self, **overrides) -> SensorProfile:
        """A copy with the given (non-None) settings replaced."""
        return replace(self, **{k: v for k, v in overrides.items() if v is not None})

    def with_range_noise(self, range_noise: float) -> SensorProfile:
        """A copy whose noise model has ``range_noise`` (m) as its constant term (the sensor's range noise at
        short range), what the node's ``range_noise`` and ``ppe extract --range-noise`` set.

        Raises:
            ValueError: the profile has no noise model (the paper's), or NoiseModel refuses the value.
        """
        if self.noise is None:
            raise ValueError(f'profile {self.name!r} has no noise model whose range noise could be set')
        return replace(self, noise=replace(self.noise, constant=range_noise))


#: The names of the greedy's seed shape sets (ppe_ros.core.ppe.seeds.SEED_SHAPES, keyed by these):
#: 'all' the paper's 17 tetrominoes, 'square' the 2 x 2 square alone.
SEED_SHAPE_NAMES = ('all', 'square')


#: How the greedy values the extension candidates of its small planes (GreedyOptions.candidate_fits).
CANDIDATE_FITS = ('exact', 'one_step')
#: The lidar profile's fit tolerance: increments of a few units of the noise variance need no more.
LIDAR_FIT_TOLERANCE = 1e-6
#: The depth camera profile's: its segmentations follow the order of near-tied actions more closely
#: (chosen on its training data: 1e-6 lowered its f and k there, 1e-9 did not).
DEPTH_FIT_TOLERANCE = 1e-9


def check_candidate_fits(candidate_fits: str) -> None:
    """Raise ValueError unless ``candidate_fits`` is one of CANDIDATE_FITS."""
    if candidate_fits not in CANDIDATE_FITS:
        choices = ' or '.join(repr(k) for k in CANDIDATE_FITS)
        raise ValueError(f'candidate_fits must be {choices}; got {candidate_fits!r}')


def check_fit_tolerance(fit_tolerance: float) -> None:
    """Raise ValueError unless ``fit_tolerance`` is a real number in (0, 1)."""
    if isinstance(fit_tolerance, bool) or not isinstance(fit_tolerance, numbers.Real) or not 0.0 < fit_tolerance < 1.0:
        raise ValueError(f'fit_tolerance must be a number in (0, 1); got {fit_tolerance!r}')


def check_seed_shapes(seed_shapes: str) -> None:
    """Raise ValueError unless ``seed_shapes`` is one of SEED_SHAPE_NAMES (SensorProfile's and
    GreedyOptions' check)."""
    if seed_shapes not in SEED_SHAPE_NAMES:
        choices = ' or '.join(repr(k) for k in SEED_SHAPE_NAMES)
        raise ValueError(f'seed_shapes must be {choices}; got {seed_shapes!r}')


#: The fewest rays a profile's min_plane_points_for asks of a coarse scan: on generated 16-beam sweeps
#: (training seeds 0-3) 10 and 7 rays keep f and k, 5 loses half of k.
MIN_PLANE_POINTS_FLOOR = 10
#: The ray spacing (degrees, along rows and columns) of the generated OS-1-128 training sweeps (1024
#: columns), on which the lidar profile's min_plane_points was chosen.
OS1_128_RAY_SPACING_DEG = (0.3456, 0.3400)

#: Spinning lidars (Ouster OS-0/1/2, Velodyne, Hesai): 2 cm range noise, plus 0.1 % of the range.
LIDAR_NOISE = NoiseModel(constant=0.02, proportional=0.001)
#: Kinect v1 (Khoshelham and Elberink 2012): axial sigma_z = 1.43e-3 z^2, a 1 mm floor.
KINECT_V1_NOISE = NoiseModel(constant=0.001, depth_quadratic=1.43e-3)
#: Intel RealSense D435-class stereo: about 2 % of depth at 2 m (sigma_z = 5e-3 z^2).
REALSENSE_NOISE = NoiseModel(constant=0.001, depth_quadratic=5e-3)

#: The built-in profiles, the one source of every default (see docs/parameters.md; docs/algorithm.md
#: for how they were chosen). 'none' is the paper's model without a distance limit: the defaults of
#: extract_planes(sensor=None) and of the node; 'paper' the paper's setting, the defaults of ppe extract.
PROFILES: dict[str, SensorProfile] = {
    'none': SensorProfile(
        name='none', noise=None, max_error_increment=0.01, max_neighbor_distance=np.inf, min_plane_points=4
    ),
    'paper': SensorProfile(
        name='paper', noise=None, max_error_increment=0.0484, max_neighbor_distance=0.18, min_plane_points=4
    ),
    'lidar': SensorProfile(
        name='lidar',
        noise=LIDAR_NOISE,
        max_error_increment=16.0,
        surface_tolerance=0.05,
        min_plane_points=40,
        reference_ray_spacing_deg=OS1_128_RAY_SPACING_DEG,
        max_plane_rmse_factor=1.3,
        max_plane_curvature_factor=1.3,
        correlation_length=1.0,
        flatness_length=4.0,
        quadrant_jackknife=True,
        row_jackknife=True,
        seed_shapes='square',
        candidate_fits='one_step',
        fit_tolerance=LIDAR_FIT_TOLERANCE,
        boundary_join_points=300,
        min_plane_breadth=0.1,
    ),
    'depth_camera': SensorProfile(
        name='depth_camera',
        noise=KINECT_V1_NOISE,
        max_error_increment=16.0,
        surface_tolerance=0.005,
        noise_factor=3.0,
        min_plane_points=100,
        max_plane_rmse_factor=1.5,
        correlation_length=0.7,
        noise_scale_bounds=(0.1, 4.0),
        quadrant_jackknife=True,
        large_surface_share=0.025,
        min_plane_width=0.03,
        flatness_length=1.0,
        max_plane_curvature_factor=3.0,
        curvature_max_size=1.0,
        fit_tolerance=DEPTH_FIT_TOLERANCE,
    ),
}


def sensor_profile(sensor: str | SensorProfile) -> SensorProfile:
    """The profile named ``sensor`` ('paper', 'lidar', 'depth_camera'), or ``sensor`` itself."""
    if isinstance(sensor, SensorProfile):
        return sensor
    try:
        return PROFILES[str(sensor)]
    except KeyError:
        raise ValueError(
            f'sensor must be one of {", ".join(repr(k) for k in PROFILES)} or a SensorProfile; got {sensor!r}'
        ) from None
