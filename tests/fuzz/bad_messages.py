"""Bad and unusual messages, by type: what a wrong driver, a mistyped command line or a
corrupted bag sends. Each maker returns fresh messages; ``stamp_ns`` lets a caller give
one stamp to the images of one capture."""

import math
import struct
import zlib

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Path
from sensor_msgs.msg import CameraInfo, CompressedImage, JointState
from stereo_msgs.msg import DisparityImage
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from vgm_common.conversions import make_header, numpy_to_image

HUGE = 1e308
NAN = math.nan


def images(stamp_ns, frame_id, width=320, height=240):
    """(label, Image) pairs, each unusable or unusual in one way."""
    rng = np.random.default_rng(stamp_ns % 2**32)

    def mono(array):
        return numpy_to_image(array, 'mono8', stamp_ns, frame_id)

    good = rng.integers(0, 256, (height, width), dtype=np.uint8)
    cases = []
    msg = mono(good)
    msg.encoding = 'yuv422_bogus'
    cases.append(('unknown encoding', msg))
    msg = mono(good)
    msg.data = bytes(msg.data)[: len(msg.data) // 2]
    cases.append(('data shorter than step * height', msg))
    msg = mono(good)
    msg.step = width - 1
    cases.append(('step below width', msg))
    msg = mono(good)
    msg.width = msg.height = 0
    msg.step = 0
    msg.data = b''
    cases.append(('empty image', msg))
    msg = mono(good)
    msg.width, msg.height, msg.step = 100_000, 100_000, 100_000
    cases.append(('declared 100000x100000, data of 320x240', msg))
    cases.append(
        (
            'float depth where grey is expected',
            numpy_to_image(np.full((height, width), NAN, np.float32), '32FC1', stamp_ns, frame_id),
        )
    )
    cases.append(
        (
            '16-bit image',
            numpy_to_image((good.astype(np.uint16) * 257), 'mono16', stamp_ns, frame_id),
        )
    )
    cases.append(('4000x3000 image', mono(np.zeros((3000, 4000), np.uint8))))
    cases.append(('1x1 image', mono(np.zeros((1, 1), np.uint8))))
    msg = mono(good)
    msg.header.frame_id = ''
    cases.append(('empty frame_id', msg))
    return cases


def camera_infos(width=320, height=240):
    """(label, CameraInfo) pairs."""

    def info(**fields):
        K = [300.0, 0, width / 2, 0, 300.0, height / 2, 0, 0, 1]
        msg = CameraInfo(
            header=make_header(1, 'stereo_left_optical_frame'),
            width=width,
            height=height,
            distortion_model='plumb_bob',
            d=[0.0] * 5,
            k=K,
            r=[1.0, 0, 0, 0, 1, 0, 0, 0, 1],
            p=K[:3] + [0.0] + K[3:6] + [0.0] + K[6:] + [0.0],
        )
        for key, value in fields.items():
            setattr(msg, key, value)
        return msg

    return [
        ('NaN in K', info(k=[NAN] * 9)),
        ('zero K', info(k=[0.0] * 9)),
        ('K not upper-triangular', info(k=[300.0, 0, 160, 5, 300, 120, 0, 0, 1])),
        ('14 distortion coefficients', info(d=[0.01] * 14)),
        ('plumb_bob without coefficients', info(d=[])),
        ('unknown distortion model', info(distortion_model='fisheye')),
        ('R not a rotation', info(r=[2.0, 0, 0, 0, 1, 0, 0, 0, 1])),
        ('P with infinities', info(p=[math.inf] * 12)),
        ('P of 1e308', info(p=[HUGE] * 12)),
        ('zero image size', info(width=0, height=0)),
    ]


def _pose(x, y, z, q=(0.0, 0.0, 0.0, 1.0)):
    from geometry_msgs.msg import Pose

    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = x, y, z
    (pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w) = q
    return pose


def poses(stamp_ns=1):
    """(label, PoseStamped) pairs."""

    def stamped(pose, frame='base_link'):
        return PoseStamped(header=make_header(stamp_ns, frame), pose=pose)

    return [
        ('NaN position', stamped(_pose(NAN, 0, 0))),
        ('position of 1e308', stamped(_pose(HUGE, HUGE, HUGE))),
        ('zero quaternion', stamped(_pose(0, 0, 0.5, (0.0, 0.0, 0.0, 0.0)))),
        ('non-unit quaternion', stamped(_pose(0, 0, 0.5, (0.0, 0.0, 0.0, 3.0)))),
        ('wrong frame', stamped(_pose(0, 0, 0.5), frame='map')),
    ]


# A tool pointing down (z axis -z of base_link) with x along base x: q = (1, 0, 0, 0).
_DOWN = (1.0, 0.0, 0.0, 0.0)


def paths(stamp_ns=1):
    """(label, Path) pairs: waypoints no arm can or should follow."""

    def path(points, q=_DOWN, frame='base_link'):
        return Path(
            header=make_header(stamp_ns, frame),
            poses=[
                PoseStamped(header=make_header(stamp_ns, frame), pose=_pose(*p, q)) for p in points
            ],
        )

    line = [(0.6, -0.1 + 0.005 * i, 0.3) for i in range(41)]
    return [
        ('empty path', path([])),
        ('NaN waypoint', path(line[:20] + [(NAN, 0, 0.3)] + line[21:])),
        ('waypoints of 1e308', path([(HUGE, 0, 0)] * 5)),
        ('non-unit quaternions', path(line, q=(0.0, 0.0, 0.0, 2.0))),
        ('wrong frame', path(line, frame='map')),
        ('100 m away', path([(100 + x, y, z) for x, y, z in line])),
        (
            'approach axis along the path',
            path([(0.6, 0.0, 0.30 - 0.001 * i) for i in range(41)], q=(0.0, 0.0, 0.0, 1.0)),
        ),
        ('one point repeated', path([(0.6, 0.0, 0.3)] * 41)),
    ]


def joint_states(names, stamp_ns=1):
    """(label, JointState) pairs for an arm with joints ``names``."""
    n = len(names)

    def state(names_, positions, velocities=None):
        return JointState(
            header=make_header(stamp_ns, ''),
            name=list(names_),
            position=[float(v) for v in positions],
            velocity=[float(v) for v in (velocities or [])],
        )

    return [
        ('unknown joint names', state([f'other{i}' for i in range(n)], [0] * n)),
        ('duplicate joint name', state(list(names[:-1]) + [names[0]], [0] * n)),
        ('fewer positions than names', state(names, [0] * (n - 1))),
        ('NaN position', state(names, [NAN] + [0] * (n - 1))),
        ('position of 1e300', state(names, [1e300] + [0] * (n - 1))),
        ('no joints at all', state([], [])),
    ]


def wrenches(frame='tool0', stamp_ns=1):
    """(label, WrenchStamped) pairs."""

    def wrench(fz, frame_=frame):
        msg = WrenchStamped(header=make_header(stamp_ns, frame_))
        msg.wrench.force.z = fz
        return msg

    return [
        ('NaN force', wrench(NAN)),
        ('force of +1e308', wrench(HUGE)),
        ('force of -1e308', wrench(-HUGE)),
        ('empty frame', wrench(1.0, '')),
    ]


def joint_trajectories(names, stamp_ns=0):
    """(label, JointTrajectory) pairs for an arm with joints ``names``."""
    n = len(names)

    def trajectory(names_, *points):
        msg = JointTrajectory(header=make_header(stamp_ns, ''), joint_names=list(names_))
        for t, positions, velocities in points:
            point = JointTrajectoryPoint(
                positions=[float(v) for v in positions], velocities=[float(v) for v in velocities]
            )
            point.time_from_start.sec, point.time_from_start.nanosec = int(t), int((t % 1) * 1e9)
            msg.points.append(point)
        return msg

    return [
        ('no points', trajectory(names)),
        ('unknown joint names', trajectory([f'other{i}' for i in range(n)], (0.1, [0] * n, []))),
        ('NaN position', trajectory(names, (0.1, [NAN] * n, []))),
        ('velocity of 1e300', trajectory(names, (0.1, [0] * n, [1e300] * n))),
        ('positions of the wrong length', trajectory(names, (0.1, [0] * (n + 1), []))),
        ('times going backwards', trajectory(names, (0.5, [0] * n, []), (0.2, [0] * n, []))),
        ('duplicate joint names', trajectory(list(names[:-1]) + [names[0]], (0.1, [0] * n, []))),
        ('no joint names', trajectory([], (0.1, [0] * n, []))),
        ('NaN velocity', trajectory(names, (0.1, [0] * n, [NAN] * n))),
        ('positions of 1e300 (beyond the limits)', trajectory(names, (0.1, [1e300] * n, []))),
        (
            'last joint at 7 rad, 2.5 beyond its limit',
            trajectory(names, (0.1, [0] * (n - 1) + [7], [])),
        ),
    ]


def unusual_joint_trajectories(names):
    """(label, JointTrajectory) pairs that are odd but not wrong."""
    n = len(names)
    future = joint_trajectories(names, stamp_ns=10**18)[2][1]
    future.points[0].positions = [0.0] * n
    many = JointTrajectory(joint_names=list(names))
    for i in range(10_000):
        point = JointTrajectoryPoint(positions=[0.0] * n)
        point.time_from_start.sec, point.time_from_start.nanosec = divmod((i + 1) * 10**6, 10**9)
        many.points.append(point)
    return [
        ('a stamp far in the future', future),
        ('10000 points', many),
    ]


def disparity_image(values_px, stamp_ns, frame_id, min_disparity=0.0):
    """A DisparityImage of (H, W) ``values_px`` [px] (values below ``min_disparity``
    unknown, by the stereo_msgs convention)."""
    msg = DisparityImage(
        f=500.0, t=0.1, min_disparity=min_disparity, max_disparity=64.0, delta_d=1 / 16
    )
    msg.header = make_header(stamp_ns, frame_id)
    msg.image = numpy_to_image(np.asarray(values_px, np.float32), '32FC1', stamp_ns, frame_id)
    return msg


def disparities(good_px, stamp_ns, frame_id):
    """(label, DisparityImage) pairs for the disparity ``good_px`` (H, W) [px]."""
    infinite = good_px.copy()
    infinite[40:60, 40:60] = np.inf
    huge = good_px.copy()
    huge[100, 100] = 1e9
    wider = good_px.copy()
    wider[10, 10] = good_px.shape[1] + 1.0
    msg_16u = disparity_image(good_px, stamp_ns, frame_id)
    msg_16u.image = numpy_to_image(good_px.astype(np.uint16), 'mono16', stamp_ns, frame_id)
    return [
        ('disparity with +inf', disparity_image(infinite, stamp_ns, frame_id)),
        ('a disparity of 1e9 px', disparity_image(huge, stamp_ns, frame_id)),
        ('a disparity wider than the image', disparity_image(wider, stamp_ns, frame_id)),
        ('min_disparity NaN', disparity_image(good_px, stamp_ns, frame_id, NAN)),
        ('min_disparity -inf', disparity_image(good_px, stamp_ns, frame_id, -math.inf)),
        ('disparity image mono16', msg_16u),
        ('disparity of another size', disparity_image(good_px[:, :200], stamp_ns, frame_id)),
    ]


def png_bomb(width, height):
    """PNG bytes of a ``width`` x ``height`` all-black grey image: a few hundred kB that
    decode to width * height bytes (16000x16000: 249 kB, 256 MB)."""
    compressor = zlib.compressobj(9)
    row = b'\x00' * (width + 1)  # filter byte + pixels
    block_rows = 64
    parts = []
    for start in range(0, height, block_rows):
        parts.append(compressor.compress(row * min(block_rows, height - start)))
    parts.append(compressor.flush())

    def chunk(kind, data):
        return (
            struct.pack('>I', len(data))
            + kind
            + data
            + struct.pack('>I', zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    header = struct.pack('>IIBBBBB', width, height, 8, 0, 0, 0, 0)
    return (
        b'\x89PNG\r\n\x1a\n'
        + chunk(b'IHDR', header)
        + chunk(b'IDAT', b''.join(parts))
        + chunk(b'IEND', b'')
    )


def jpeg_declaring(width, height, quality=90):
    """A small JPEG whose frame header declares ``width`` x ``height``."""
    ok, encoded = cv2.imencode(
        '.jpg', np.zeros((16, 16), np.uint8), [cv2.IMWRITE_JPEG_QUALITY, quality]
    )
    data = bytearray(encoded.tobytes())
    sof = data.index(b'\xff\xc0')  # baseline frame header: length, precision, height, width
    data[sof + 5 : sof + 9] = struct.pack('>HH', height, width)
    return bytes(data)


def compressed_images(stamp_ns, frame_id):
    """(label, CompressedImage) pairs a decoder must refuse before decoding, or cannot."""

    def compressed(data, fmt='mono8; jpeg compressed mono8'):
        return CompressedImage(header=make_header(stamp_ns, frame_id), format=fmt, data=data)

    ok, good = cv2.imencode('.jpg', np.full((240, 320), 128, np.uint8))
    return [
        ('PNG of 16000x16000 (249 kB)', compressed(png_bomb(16000, 16000), 'png')),
        ('JPEG header declaring 20000x20000', compressed(jpeg_declaring(20000, 20000))),
        ('no data', compressed(b'')),
        ('not an image', compressed(b'\x00\x01not a jpeg' * 50)),
        ('JPEG cut to its header', compressed(good.tobytes()[:200])),
    ]
