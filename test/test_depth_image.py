"""Depth images with their camera info: decoding, the pinhole model, and one frame through process_depth_image."""

from __future__ import annotations

import numpy as np
import pytest
from depth_frames import CX, CY, FX, FY, STAMP, camera_info, corner_depth, depth_image, header, reference_points

from ppe_ros.ros.depth_image import (
    DepthFrame,
    DepthImageError,
    camera_model,
    depth_image_points,
    depth_values,
    pixel_rays,
)
from ppe_ros.ros.messages import rclpy_message_types, rosbags_message_types
from ppe_ros.ros.pointcloud2 import pointcloud2_to_structured, structured_to_pointcloud2
from ppe_ros.ros.processing import ExtractorParams, FrameSkipped, process_cloud, process_depth_image


@pytest.fixture(scope='module', params=['rclpy', 'rosbags'])
def types(request):
    return rclpy_message_types() if request.param == 'rclpy' else rosbags_message_types()


# ------------------------------------------------------------------ decoding and the camera model


@pytest.mark.parametrize('big_endian', [False, True])
@pytest.mark.parametrize('padding', [0, 6])
def test_16uc1_counts_are_millimetres_whatever_the_byte_order_and_row_padding(types, big_endian, padding):
    counts = np.arange(12 * 10, dtype=np.uint16).reshape(10, 12) * 37
    image = depth_image(types, counts, '16UC1', big_endian=big_endian, padding=padding)
    values, scale = depth_values(image)
    np.testing.assert_array_equal(values, counts)
    assert scale == 1.0e-3


def test_32fc1_is_metres_and_non_finite_or_zero_depth_is_no_return(types):
    z = corner_depth()
    z[0, 0], z[1, 1], z[2, 2], z[3, 3] = np.nan, np.inf, 0.0, -1.0
    points = depth_image_points(depth_image(types, z), camera_info(types))
    expected = reference_points(z.astype(np.float32).astype(np.float64), FX, FY, CX, CY)
    np.testing.assert_array_equal(np.isnan(points), np.isnan(expected))
    np.testing.assert_allclose(points, expected, rtol=1e-12, atol=0)
    assert np.isnan(points[[0, 1, 2, 3], [0, 1, 2, 3]]).all()


def test_binning_and_roi_give_the_intrinsics_of_the_published_pixels(types):
    """A 2 x 2 binned ROI at (16, 8) of a 160 x 120 camera: a 40 x 30 image."""
    info = camera_info(types, width=160, height=120, binning=(2, 2), roi=(16, 8, 60, 80))
    camera = camera_model(info)
    assert (camera.height, camera.width) == (30, 40)
    assert camera.intrinsics.as_tuple() == (FX / 2, FY / 2, (CX - 16) / 2, (CY - 8) / 2)
    z = corner_depth(30, 40, fx=FX / 2, fy=FY / 2, cx=(CX - 16) / 2, cy=(CY - 8) / 2)
    points = depth_image_points(depth_image(types, z), info)
    expected = reference_points(z.astype(np.float32).astype(np.float64), *camera.intrinsics.as_tuple())
    np.testing.assert_allclose(points, expected, rtol=1e-12, atol=0)


def test_p_is_used_and_k_when_p_is_zero(types):
    k = [200.0, 0.0, 30.0, 0.0, 210.0, 20.0, 0.0, 0.0, 1.0]
    p = [100.0, 0.0, 35.0, 0.0, 0.0, 105.0, 25.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert camera_model(camera_info(types, k=k, p=p)).intrinsics.as_tuple() == (100.0, 105.0, 35.0, 25.0)
    assert camera_model(camera_info(types, k=k, p=[0.0] * 12)).intrinsics.as_tuple() == (200.0, 210.0, 30.0, 20.0)
    distorted = camera_model(camera_info(types, d=(0.1, 0, 0, 0, 0)))
    assert distorted.distorted and distorted.describe() == (
        '80 x 60 images, fx 120.0 fy 118.0 cx 39.5 cy 29.2 (from P); distortion coefficients not applied '
        '(the image is taken as rectified)'
    )
    plain = camera_model(camera_info(types, d=(0.0,) * 5, p=[0.0] * 12))
    assert not plain.distorted and plain.describe() == '80 x 60 images, fx 120.0 fy 118.0 cx 39.5 cy 29.2 (from K)'


@pytest.mark.parametrize(
    ('change', 'message'),
    [
        (dict(k=[0.0] * 9, p=[0.0] * 12), 'no usable calibration'),
        (dict(k=[np.nan] * 9, p=[0.0] * 12), 'no usable calibration'),
        (dict(p=[-5.0, 0, 1, 0, 0, 5.0, 1, 0, 0, 0, 1, 0]), 'no usable calibration'),
        (dict(width=0), 'camera info size is 60 x 0'),
        (
            dict(p=[1e-300, 0, 1, 0, 0, 5.0, 1, 0, 0, 0, 1, 0]),
            'camera info gives rays up to 7.8e+301 times their depth sideways (fx 1e-300',
        ),
        (dict(p=[1e-5, 0, 1, 0, 0, 5.0, 1, 0, 0, 0, 1, 0]), 'not a pinhole calibration'),
        (dict(roi=(70, 0, 10, 20)), 'ROI 20 x 10 at (70, 0) is outside its 80 x 60 image'),
    ],
)
def test_unusable_camera_info_is_named(types, change, message):
    with pytest.raises(DepthImageError, match=None) as caught:
        camera_model(camera_info(types, **change))
    assert caught.value.kind == 'invalid_camera_info'
    assert message in caught.value.reason


def test_a_camera_info_with_a_p_of_the_wrong_length_is_named():
    types = rosbags_message_types()
    info = camera_info(types)
    info.p = np.zeros(5)
    with pytest.raises(DepthImageError, match='P has 5 numbers, not 12'):
        camera_model(info)


@pytest.mark.parametrize(
    ('image_kwargs', 'message'),
    [
        (dict(encoding='rgb8'), "image encoding 'rgb8' is not a depth encoding"),
        (dict(data_size=100), '100 data bytes, not step x height'),
    ],
)
def test_unusable_images_are_named(types, image_kwargs, message):
    counts = np.ones((6, 8), dtype=np.uint16)
    image = depth_image(types, counts, '16UC1', data_size=image_kwargs.get('data_size'))
    if 'encoding' in image_kwargs:
        image.encoding = image_kwargs['encoding']
    with pytest.raises(DepthImageError) as caught:
        depth_values(image)
    assert caught.value.kind == 'invalid_image'
    assert message in caught.value.reason


def test_a_row_step_shorter_than_a_row_is_named(types):
    image = depth_image(types, np.ones((6, 8), dtype=np.uint16), '16UC1')
    image.step = 10
    with pytest.raises(DepthImageError, match='row step 10 bytes is shorter than a row of 8 x 2 bytes'):
        depth_values(image)


# ------------------------------------------------------------------ one frame through process_depth_image


def test_a_depth_frame_gives_the_planes_of_the_same_points_as_a_cloud(types):
    """The image path is the cloud path on the back-projected points: same labels, the image's header."""
    z = corner_depth()
    frame = DepthFrame(depth_image(types, z), camera_info(types))
    params = ExtractorParams(sensor='depth_camera', min_plane_points=20)
    result = process_depth_image(frame, params, types)
    points = depth_image_points(frame.image, frame.camera_info)
    table = np.zeros(z.shape, [('x', '<f8'), ('y', '<f8'), ('z', '<f8')])
    table['x'], table['y'], table['z'] = points[..., 0], points[..., 1], points[..., 2]
    cloud = structured_to_pointcloud2(
        table, header=header(types), msg_class=types.PointCloud2, field_class=types.PointField
    )
    same = process_cloud(cloud, params, types)
    np.testing.assert_array_equal(result.planes.labels, same.planes.labels)
    assert result.planes.num_planes == 2  # the wall and the floor
    normals = sorted(np.round(np.abs(result.planes.normals), 3).tolist())
    assert normals == [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]
    labeled = pointcloud2_to_structured(result.labeled_points)
    assert labeled.shape == z.shape
    assert result.labeled_points.header.frame_id == 'camera_depth_optical_frame'
    assert (result.stamped.sec, result.stamped.nanosec) == STAMP


@pytest.mark.parametrize(
    ('kind', 'build'),
    [
        ('no_camera_info', lambda t: DepthFrame(depth_image(t, corner_depth()), None)),
        (
            'camera_info_mismatch',
            lambda t: DepthFrame(depth_image(t, corner_depth(30, 40)), camera_info(t)),
        ),
        ('no_valid_points', lambda t: DepthFrame(depth_image(t, np.zeros((60, 80))), camera_info(t))),
        ('too_large', lambda t: DepthFrame(depth_image(t, corner_depth()), camera_info(t))),
        (
            'invalid_camera_info',
            lambda t: DepthFrame(depth_image(t, corner_depth()), camera_info(t, k=[0.0] * 9, p=[0.0] * 12)),
        ),
    ],
)
def test_unusable_depth_frames_are_skipped_with_the_reason(types, kind, build):
    params = ExtractorParams(max_points=4000 if kind == 'too_large' else 2_000_000)
    with pytest.raises(FrameSkipped) as caught:
        process_depth_image(build(types), params, types)
    assert caught.value.kind == kind
    expected = {
        'no_camera_info': 'depth image without camera info: none received on depth/camera_info yet',
        'camera_info_mismatch': 'depth image: its size 40 x 30 is not the 80 x 60 that its camera info describes',
        'no_valid_points': 'has no valid depth',
        'too_large': 'depth image of 60 x 80 = 4800 pixels exceeds max_points = 4000',
        'invalid_camera_info': 'no usable calibration',
    }[kind]
    assert expected in caught.value.reason


def test_the_kinect_frame_as_a_depth_image_gives_the_points_of_the_png_loader(shared_data):
    """Kinect v1 depth in millimetres (16UC1) with the calibration next to the PNG: the same points as
    ``ppe extract`` reads from the file."""
    from ppe_ros.io.depth import find_depth_calibration, read_depth_png
    from ppe_ros.io.loading import load_scan

    path = shared_data / 'kinect' / 'depth_0.png'
    counts = read_depth_png(path)
    calibration = find_depth_calibration(path)
    assert calibration is not None and calibration.depth_scale == 1.0e-3
    fx, fy, cx, cy = calibration.intrinsics.as_tuple()
    types = rosbags_message_types()
    height, width = counts.shape
    info = camera_info(
        types, width=width, height=height, k=[fx, 0, cx, 0, fy, cy, 0, 0, 1], p=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0]
    )
    points = depth_image_points(depth_image(types, counts, '16UC1'), info)
    np.testing.assert_array_equal(points, load_scan(path).points)


# ------------------------------------------------------------------ raw (distorted) depth images

#: (model, D, width, height, fx, fy, cx, cy): a webcam-like plumb_bob lens and an Azure Kinect-like
#: rational_polynomial depth camera (large coefficients that nearly cancel).
LENSES = [
    ('plumb_bob', (-0.28, 0.09, 0.001, -0.0015, -0.012), 160, 120, 150.0, 152.0, 81.3, 58.9),
    ('rational_polynomial', (5.0, 3.3, -6e-5, 1e-5, 0.17, 5.3, 5.1, 0.86), 160, 144, 126.0, 126.2, 80.4, 82.6),
]


def reference_ray(u, v, model, d, fx, fy, cx, cy):
    """(x, y) with distort(x, y) = pixel (u, v): Newton's method on the forward model with a numerical
    Jacobian, pixel by pixel (slow, obviously correct)."""
    k = list(d) + [0.0] * (8 - len(d))
    k1, k2, p1, p2, k3, k4, k5, k6 = k

    def forward(x, y):
        r2 = x * x + y * y
        radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        return (
            fx * (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)) + cx,
            fy * (y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y) + cy,
        )

    x, y = (u - cx) / fx, (v - cy) / fy
    for _ in range(100):
        fu, fv = forward(x, y)
        h = 1e-7
        jac = np.array(
            [
                [(forward(x + h, y)[0] - fu) / h, (forward(x, y + h)[0] - fu) / h],
                [(forward(x + h, y)[1] - fv) / h, (forward(x, y + h)[1] - fv) / h],
            ]
        )
        step = np.linalg.solve(jac, [u - fu, v - fv])
        x, y = x + step[0], y + step[1]
        if abs(step).max() < 1e-15:
            break
    return x, y


def raw_info(types, model, d, width, height, fx, fy, cx, cy):
    info = camera_info(types, width=width, height=height, k=[fx, 0, cx, 0, fy, cy, 0, 0, 1], d=d)
    info.distortion_model = model
    info.p = np.asarray([fx * 0.9, 0, cx, 0, 0, fy * 0.9, cy, 0, 0, 0, 1, 0], dtype=np.float64)  # rectified's
    return info


@pytest.mark.parametrize('lens', LENSES, ids=[lens[0] for lens in LENSES])
def test_raw_depth_pixels_get_the_undistorted_rays_of_a_slow_reference(types, lens):
    model, d, width, height, fx, fy, cx, cy = lens
    camera = camera_model(raw_info(types, *lens), rectified=False)
    assert camera.source == 'K' and camera.distortion_model == model
    assert camera.describe().endswith(f'(from K); {model} distortion undone (the image is taken as raw)')
    rays = pixel_rays(camera)
    assert not np.isnan(rays).any()
    for v, u in [(0, 0), (0, width - 1), (height - 1, 0), (height - 1, width - 1), (height // 2, width // 3), (7, 101)]:
        np.testing.assert_allclose(rays[v, u], reference_ray(u, v, model, d, fx, fy, cx, cy), rtol=0, atol=1e-9)


@pytest.mark.parametrize('lens', LENSES, ids=[lens[0] for lens in LENSES])
def test_a_raw_depth_image_of_a_tilted_wall_lies_on_the_wall_only_when_undistorted(types, lens):
    """z-depths of the plane 0.3 x - 0.2 y + z = 2.5 seen through the lens: with depth_image_rectified
    false every point is on the plane; taken as rectified, the distortion bends it by centimetres."""
    info = raw_info(types, *lens)
    rays = pixel_rays(camera_model(info, rectified=False))
    normal = np.array([0.3, -0.2, 1.0])
    z = 2.5 / (normal[0] * rays[..., 0] + normal[1] * rays[..., 1] + 1.0)
    image = depth_image(types, z)  # 32FC1
    raw = depth_image_points(image, info, rectified=False)
    assert not np.isnan(raw).any()
    np.testing.assert_allclose(raw @ normal, 2.5, rtol=0, atol=2e-6)  # float32 depths
    bent = depth_image_points(image, info)  # taken as rectified (P, no D)
    assert np.abs(bent @ normal - 2.5).max() > 0.01


def test_a_raw_depth_image_of_another_distortion_model_is_refused_and_a_rectified_one_ignores_it(types):
    info = raw_info(types, 'equidistant', (0.1, 0.01, 0.0, 0.0), 80, 60, FX, FY, CX, CY)
    with pytest.raises(DepthImageError) as caught:
        camera_model(info, rectified=False)
    assert caught.value.kind == 'invalid_camera_info'
    assert "distortion 'equidistant' with D = [0.1, 0.01, 0.0, 0.0] cannot be undone" in caught.value.reason
    assert 'plumb_bob, rational_polynomial' in caught.value.reason
    assert camera_model(info).distortion == ()  # rectified: D is not applied
    zero = raw_info(types, 'equidistant', (0.0,) * 4, 80, 60, FX, FY, CX, CY)
    assert camera_model(zero, rectified=False).intrinsics.as_tuple() == (FX, FY, CX, CY)  # K, nothing to undo
    extra = raw_info(types, 'plumb_bob', (0.1, 0.0, 0.0, 0.0, 0.0, 0.3), 80, 60, FX, FY, CX, CY)
    with pytest.raises(DepthImageError, match='cannot be undone'):  # a 6th plumb_bob coefficient
        camera_model(extra, rectified=False)


def test_the_node_parameter_takes_raw_depth_images(types):
    width, height = LENSES[0][2:4]
    info = raw_info(types, *LENSES[0])
    z = np.full((height, width), 2.0)
    frame = DepthFrame(depth_image(types, z), info)
    raw = process_depth_image(frame, ExtractorParams(depth_image_rectified=False, min_plane_points=20), types)
    np.testing.assert_allclose(raw.points, depth_image_points(frame.image, info, rectified=False))
    rectified = process_depth_image(frame, ExtractorParams(min_plane_points=20), types)
    assert not np.allclose(rectified.points, raw.points)


def test_a_compressed_depth_frame_gives_the_planes_of_the_raw_image(types):
    """image_transport's compressedDepth (RVL) of the same millimetres: the same points and labels."""
    from depth_frames import compressed_depth_image

    millimetres = np.round(corner_depth() * 1000.0).astype(np.uint16)
    params = ExtractorParams(sensor='depth_camera', min_plane_points=20)
    raw = process_depth_image(DepthFrame(depth_image(types, millimetres, '16UC1'), camera_info(types)), params, types)
    compressed = compressed_depth_image(types, millimetres)
    frame = process_depth_image(DepthFrame(compressed, camera_info(types)), params, types)
    np.testing.assert_array_equal(frame.points, raw.points)
    np.testing.assert_array_equal(frame.planes.labels, raw.planes.labels)
    assert frame.labeled_points.header.frame_id == 'camera_depth_optical_frame'
    # its size comes from the header: checked before anything is decoded
    with pytest.raises(FrameSkipped, match='depth image of 60 x 80 = 4800 pixels exceeds max_points = 100'):
        process_depth_image(DepthFrame(compressed, camera_info(types)), params.replace(max_points=100), types)
    compressed.data = compressed.data[:30]
    with pytest.raises(FrameSkipped) as caught:
        process_depth_image(DepthFrame(compressed, camera_info(types)), params, types)
    assert (
        caught.value.kind == 'invalid_image'
        and 'depth image: compressedDepth: RVL code ends after' in caught.value.reason
    )
