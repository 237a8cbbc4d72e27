"""Write the replay example's recorded data: a ROS 2 MCAP, a motion-capture CSV and the truth.

Run from the repository root (the files are committed; run it again only to remake them):

    .venv/bin/python pipeline/data/make_replay_data.py            # writes into pipeline/data/
    .venv/bin/python pipeline/data/make_replay_data.py --out DIR  # writes into DIR

The output is deterministic (fixed seed, fixed base time): running it again gives the same bytes
with the same numpy, mcap and mcap-ros2-support versions. It needs numpy and
mcap-ros2-support only (not fusionlog), so the files are what any ROS 2 tool would record.

What it simulates: one planar target (a holonomic robot that keeps its heading, yaw = 0, so its
base_link stays parallel to the odom frame), a nearly-constant-velocity model with white
acceleration noise of intensity Q_C (m^2 s^-3) on each axis, discretised exactly between the
instants at which anything measures it. State [x, y, vx, vy] in metres and m/s, 45 s, starting
at BASE_NS = 1.7e18 ns (2023-11-14T22:13:20Z).

Files:

- robot_ros2.mcap - ROS 2 (profile "ros2", CDR, ros2msg schemas with the standard Humble
  definitions of common_interfaces), three topics:
    /odom  nav_msgs/msg/Odometry at ~30 Hz: pose.pose.position.{x,y} = position + N(0, 0.05^2),
           twist.twist.linear.{x,y} = velocity + N(0, 0.05^2) (body = world axes since yaw = 0);
           both covariances ALL ZERO, as odometry drivers leave them. header.stamp = the
           measurement instant (1/30 s grid with 1 ms jitter); log_time = stamp + 2..6 ms.
    /pose  geometry_msgs/msg/PoseWithCovarianceStamped at ~1 Hz, a localiser: position drawn
           from the covariance it reports (x-y block varies per message, correlated; z, roll,
           pitch, yaw variances filled in, the rest zero). header.stamp = the measurement instant
           (1 s grid with 50 ms jitter); log_time = arrival = stamp + latency (0.1..0.4 s, and
           1.7 s for messages 5, 14, 26 and 37 (0-based), which arrive after the next one:
           4 messages out of order in log-time order).
    /fix   sensor_msgs/msg/NavSatFix at 1 Hz: the position as WGS 84 latitude/longitude around
           LAT0, LON0 (local tangent plane, ENU), position_covariance diagonal 1.5^2, 1.5^2, 3^2
           (COVARIANCE_TYPE_DIAGONAL_KNOWN); stamp on the 1 s grid + 0.5 s, log_time + 20 ms.
  Read the sensors with time = "header.stamp" (the measurement time); log_time is the arrival.
- mocap.csv - a motion-capture export at 20 Hz of the same target: columns
  `#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1]` (comma and
  a space between fields), integer nanosecond timestamps, position noise N(0, 0.01^2), velocity
  noise N(0, 0.02^2); two rows (MOCAP_GAPS) have `nan` values (marker occlusion).
- truth.csv - the simulated state at every instant used above (the union of /odom, /pose and
  /fix header stamps and mocap timestamps, each once): `#timestamp [ns], x [m], y [m],
  vx [m s^-1], vy [m s^-1]` to 1e-5, for a replay's [truth] table (time_unit = "ns").

Sizes: /odom 1350, /pose 44, /fix 45 messages (110 kB); mocap.csv 900 rows (52 kB); truth.csv
2339 rows (134 kB).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np
from mcap_ros2.writer import Writer

SEED = 20240514
BASE_NS = 1_700_000_000_000_000_000
DURATION_S = 45
Q_C = 0.02  # m^2 s^-3, white-acceleration intensity per axis
X0 = np.array([0.0, 0.0, 0.8, 0.3])  # x, y [m], vx, vy [m/s]

ODOM_HZ = 30
ODOM_SIGMA_P, ODOM_SIGMA_V = 0.05, 0.05
POSE_LATE = (5, 14, 26, 37)  # /pose messages delivered 1.7 s late (overtaken by the next one)
FIX_SIGMA = (1.5, 1.5, 3.0)  # east, north, up [m]
LAT0, LON0, ALT0 = 47.3977, 8.5456, 488.0  # degrees, degrees, metres (WGS 84)
EARTH_R = 6_378_137.0
MOCAP_HZ = 20
MOCAP_SIGMA_P, MOCAP_SIGMA_V = 0.01, 0.02
MOCAP_GAPS = (311, 312)  # rows (0-based) with nan values

# -- ROS 2 message definitions (common_interfaces, Humble), as rosbag2 stores them: the type's
# .msg text, then every dependency once after a "=" * 80 line and "MSG: pkg/Type". --------------

_SEP = "=" * 80 + "\n"

_MSG = {
    "std_msgs/Header": """\
# Standard metadata for higher-level stamped data types.
# This is generally used to communicate timestamped data
# in a particular coordinate frame.

# Two-integer timestamp that is expressed as seconds and nanoseconds.
builtin_interfaces/Time stamp

# Transform frame with which this data is associated.
string frame_id
""",
    "builtin_interfaces/Time": """\
# This message communicates ROS Time defined here:
# https://design.ros2.org/articles/clock_and_time.html

# The seconds component, valid over all int32 values.
int32 sec

# The nanoseconds component, valid in the range [0, 10e9).
uint32 nanosec
""",
    "geometry_msgs/PoseWithCovariance": """\
# This represents a pose in free space with uncertainty.

Pose pose

# Row-major representation of the 6x6 covariance matrix
# The orientation parameters use a fixed-axis representation.
# In order, the parameters are:
# (x, y, z, rotation about X axis, rotation about Y axis, rotation about Z axis)
float64[36] covariance
""",
    "geometry_msgs/Pose": """\
# A representation of pose in free space, composed of position and orientation.

Point position
Quaternion orientation
""",
    "geometry_msgs/Point": """\
# This contains the position of a point in free space
float64 x
float64 y
float64 z
""",
    "geometry_msgs/Quaternion": """\
# This represents an orientation in free space in quaternion form.

float64 x 0
float64 y 0
float64 z 0
float64 w 1
""",
    "geometry_msgs/TwistWithCovariance": """\
# This expresses velocity in free space with uncertainty.

Twist twist

# Row-major representation of the 6x6 covariance matrix
# The orientation parameters use a fixed-axis representation.
# In order, the parameters are:
# (x, y, z, rotation about X axis, rotation about Y axis, rotation about Z axis)
float64[36] covariance
""",
    "geometry_msgs/Twist": """\
# This expresses velocity in free space broken into its linear and angular parts.

Vector3  linear
Vector3  angular
""",
    "geometry_msgs/Vector3": """\
# This represents a vector in free space.

# This is semantically different than a point.
# A vector is always anchored at the origin.
# When a trasform is applied to a vector only
# the rotational component is applied.

float64 x
float64 y
float64 z
""",
    "sensor_msgs/NavSatStatus": """\
# Navigation Satellite fix status for any Global Navigation Satellite System.
#
# Whether to output an augmented fix is determined by both the fix
# type and the last time differential corrections were received.  A
# fix is valid when status >= STATUS_FIX.

int8 STATUS_NO_FIX =  -1        # unable to fix position
int8 STATUS_FIX =      0        # unaugmented fix
int8 STATUS_SBAS_FIX = 1        # with satellite-based augmentation
int8 STATUS_GBAS_FIX = 2        # with ground-based augmentation

int8 status

# Bits defining which Global Navigation Satellite System signals were
# used by the receiver.

uint16 SERVICE_GPS =     1
uint16 SERVICE_GLONASS = 2
uint16 SERVICE_COMPASS = 4      # includes BeiDou.
uint16 SERVICE_GALILEO = 8

uint16 service
""",
}

ODOMETRY = """\
# This represents an estimate of a position and velocity in free space.
# The pose in this message should be specified in the coordinate frame given by header.frame_id
# The twist in this message should be specified in the coordinate frame given by the child_frame_id

# Includes the frame id of the pose parent.
std_msgs/Header header

# Frame id the pose points to. The twist is in this coordinate frame.
string child_frame_id

# Estimated pose that is typically relative to a fixed world frame.
geometry_msgs/PoseWithCovariance pose

# Estimated linear and angular velocity relative to child_frame_id.
geometry_msgs/TwistWithCovariance twist
"""

POSE_WITH_COVARIANCE_STAMPED = """\
# This expresses an estimated pose with a reference coordinate frame and timestamp

std_msgs/Header header
PoseWithCovariance pose
"""

NAV_SAT_FIX = """\
# Navigation Satellite fix for any Global Navigation Satellite System
#
# Specified using the WGS 84 reference ellipsoid

# header.stamp specifies the ROS time for this measurement (the
#        corresponding satellite time may be reported using the
#        sensor_msgs/TimeReference message).
#
# header.frame_id is the frame of reference reported by the satellite
#        receiver, usually the location of the antenna.  This is a
#        Euclidean frame relative to the vehicle, not a reference
#        ellipsoid.
std_msgs/Header header

# Satellite fix status information.
NavSatStatus status

# Latitude [degrees]. Positive is north of equator; negative is south.
float64 latitude

# Longitude [degrees]. Positive is east of prime meridian; negative is west.
float64 longitude

# Altitude [m]. Positive is above the WGS 84 ellipsoid
# (quiet NaN if no altitude is available).
float64 altitude

# Position covariance [m^2] defined relative to a tangential plane
# through the reported position. The components are East, North, and
# Up (ENU), in row-major order.
#
# Beware: this coordinate system exhibits singularities at the poles.
float64[9] position_covariance

# If the covariance of the fix is known, fill it in completely. If the
# GPS receiver provides the variance of each measurement, put them
# along the diagonal. If only Dilution of Precision is available,
# estimate an approximate covariance from that.

uint8 COVARIANCE_TYPE_UNKNOWN = 0
uint8 COVARIANCE_TYPE_APPROXIMATED = 1
uint8 COVARIANCE_TYPE_DIAGONAL_KNOWN = 2
uint8 COVARIANCE_TYPE_KNOWN = 3

uint8 position_covariance_type
"""


def msgdef(root: str, deps: list[str]) -> str:
    """The root .msg text followed by its dependencies in rosbag2's concatenated layout."""
    return root + "".join(f"{_SEP}MSG: {d}\n{_MSG[d]}" for d in deps)


_POSE_DEPS = ["geometry_msgs/Pose", "geometry_msgs/Point", "geometry_msgs/Quaternion"]
_HEADER_DEPS = ["std_msgs/Header", "builtin_interfaces/Time"]
ODOMETRY_DEF = msgdef(
    ODOMETRY,
    _HEADER_DEPS
    + ["geometry_msgs/PoseWithCovariance", *_POSE_DEPS]
    + ["geometry_msgs/TwistWithCovariance", "geometry_msgs/Twist", "geometry_msgs/Vector3"],
)
POSE_DEF = msgdef(
    POSE_WITH_COVARIANCE_STAMPED,
    _HEADER_DEPS + ["geometry_msgs/PoseWithCovariance", *_POSE_DEPS],
)
FIX_DEF = msgdef(NAV_SAT_FIX, _HEADER_DEPS + ["sensor_msgs/NavSatStatus"])


# -- the simulation -----------------------------------------------------------------------------


def _stamp(t_ns: int) -> dict:
    return {"sec": t_ns // 1_000_000_000, "nanosec": t_ns % 1_000_000_000}


def _header(t_ns: int, frame: str) -> dict:
    return {"stamp": _stamp(t_ns), "frame_id": frame}


def _instants(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Measurement instants (int64 ns since BASE_NS) of every sensor."""
    n_odom = DURATION_S * ODOM_HZ
    odom = np.round(np.arange(n_odom) * (1e9 / ODOM_HZ) + rng.uniform(-1e6, 1e6, n_odom))
    pose = np.round(np.arange(1, DURATION_S) * 1e9 + rng.uniform(-5e7, 5e7, DURATION_S - 1))
    fix = np.arange(DURATION_S) * 1e9 + 5e8
    n_mocap = DURATION_S * MOCAP_HZ
    mocap = np.arange(n_mocap) * (1e9 / MOCAP_HZ) + 1.25e7  # a clock offset of 12.5 ms
    out = {k: v.astype(np.int64) for k, v in dict(odom=odom, pose=pose, fix=fix).items()}
    out["odom"][0] = 0
    out["mocap"] = mocap.astype(np.int64)
    return out


def chol2(C: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a 2x2 covariance, written out: the data must be the same bytes
    on every machine, and LAPACK/BLAS kernels (chosen by CPU) round differently."""
    l11 = math.sqrt(C[0, 0])
    l21 = C[1, 0] / l11
    return np.array([[l11, 0.0], [l21, math.sqrt(C[1, 1] - l21 * l21)]])


def mul2(A: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A @ v for a 2x2 A, one IEEE operation at a time (see `chol2`)."""
    a, b = float(v[0]), float(v[1])
    return np.array([A[0, 0] * a + A[0, 1] * b, A[1, 0] * a + A[1, 1] * b])


def _trajectory(rng: np.random.Generator, t_ns: np.ndarray) -> np.ndarray:
    """(N, 4) states at the sorted distinct instants t_ns: exact discretisation of the
    continuous white-noise-acceleration model over each interval."""
    x = np.empty((len(t_ns), 4))
    x[0] = X0
    for k in range(1, len(t_ns)):
        dt = (t_ns[k] - t_ns[k - 1]) * 1e-9
        F = np.array([[1.0, dt], [0.0, 1.0]])
        Q = Q_C * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
        L = chol2(Q)
        for axis in (0, 1):  # state [x, y, vx, vy]: axis a is (a, a + 2)
            i = [axis, axis + 2]
            x[k, i] = mul2(F, x[k - 1, i]) + mul2(L, rng.standard_normal(2))
    return x


def simulate() -> dict:
    rng = np.random.default_rng(SEED)
    inst = _instants(rng)
    t_all = np.unique(np.concatenate(list(inst.values())))
    states = _trajectory(rng, t_all)
    at = {k: states[np.searchsorted(t_all, v)] for k, v in inst.items()}
    return {"rng": rng, "inst": inst, "t_all": t_all, "states": states, "at": at}


def _pose_cov(rng: np.random.Generator) -> np.ndarray:
    """A localiser's 6x6 covariance: a varying correlated x-y block, z and angles filled in."""
    sx, sy = rng.uniform(0.15, 0.5, 2)
    rho = rng.uniform(-0.6, 0.6)
    C = np.zeros((6, 6))
    C[:2, :2] = [[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]]
    C[2, 2] = 0.5**2
    C[3, 3] = C[4, 4] = 0.02**2
    C[5, 5] = 0.05**2
    return C


def write_ros2(path: Path, sim: dict) -> None:
    rng, inst, at = sim["rng"], sim["inst"], sim["at"]
    zeros36 = [0.0] * 36
    records = []  # (log_time, topic, schema key, message)

    for t, s in zip(inst["odom"], at["odom"], strict=True):
        stamp = BASE_NS + int(t)
        p = s[:2] + ODOM_SIGMA_P * rng.standard_normal(2)
        v = s[2:] + ODOM_SIGMA_V * rng.standard_normal(2)
        msg = {
            "header": _header(stamp, "odom"),
            "child_frame_id": "base_link",
            "pose": {
                "pose": {
                    "position": {"x": p[0], "y": p[1], "z": 0.0},
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
                "covariance": zeros36,
            },
            "twist": {
                "twist": {
                    "linear": {"x": v[0], "y": v[1], "z": 0.0},
                    "angular": {"x": 0.0, "y": 0.0, "z": 0.0},
                },
                "covariance": zeros36,
            },
        }
        records.append((stamp + int(rng.integers(2_000_000, 6_000_001)), "/odom", "odom", msg))

    for k, (t, s) in enumerate(zip(inst["pose"], at["pose"], strict=True)):
        stamp = BASE_NS + int(t)
        C = _pose_cov(rng)
        p = s[:2] + mul2(chol2(C[:2, :2]), rng.standard_normal(2))
        latency = 1_700_000_000 if k in POSE_LATE else int(rng.integers(100_000_000, 400_000_001))
        msg = {
            "header": _header(stamp, "map"),
            "pose": {
                "pose": {
                    "position": {"x": p[0], "y": p[1], "z": 0.5 * rng.standard_normal()},
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
                },
                "covariance": [float(c) for c in C.ravel()],
            },
        }
        records.append((stamp + latency, "/pose", "pose", msg))

    for t, s in zip(inst["fix"], at["fix"], strict=True):
        stamp = BASE_NS + int(t)
        east, north = s[:2] + np.array(FIX_SIGMA[:2]) * rng.standard_normal(2)
        up = FIX_SIGMA[2] * rng.standard_normal()
        lat = LAT0 + math.degrees(north / EARTH_R)
        lon = LON0 + math.degrees(east / (EARTH_R * math.cos(math.radians(LAT0))))
        msg = {
            "header": _header(stamp, "gps"),
            "status": {"status": 0, "service": 1},
            "latitude": lat,
            "longitude": lon,
            "altitude": ALT0 + up,
            "position_covariance": [
                *(FIX_SIGMA[0] ** 2, 0.0, 0.0),
                *(0.0, FIX_SIGMA[1] ** 2, 0.0),
                *(0.0, 0.0, FIX_SIGMA[2] ** 2),
            ],
            "position_covariance_type": 2,
        }
        records.append((stamp + 20_000_000, "/fix", "fix", msg))

    records.sort(key=lambda r: r[0])  # a recorder writes in arrival order
    with open(path, "wb") as f:
        w = Writer(f)
        schemas = {
            "odom": w.register_msgdef("nav_msgs/msg/Odometry", ODOMETRY_DEF),
            "pose": w.register_msgdef("geometry_msgs/msg/PoseWithCovarianceStamped", POSE_DEF),
            "fix": w.register_msgdef("sensor_msgs/msg/NavSatFix", FIX_DEF),
        }
        seq: dict[str, int] = {}
        for log_time, topic, key, msg in records:
            seq[topic] = seq.get(topic, 0) + 1
            w.write_message(topic, schemas[key], msg, log_time=log_time, sequence=seq[topic])
        w.finish()


def _row(t_ns: int, vals) -> str:
    return ", ".join([str(t_ns), *vals]) + "\n"


def write_mocap(path: Path, sim: dict) -> None:
    rng, inst, at = sim["rng"], sim["inst"], sim["at"]
    lines = ["#timestamp [ns], p_RS_R_x [m], p_RS_R_y [m], v_RS_R_x [m s^-1], v_RS_R_y [m s^-1]\n"]
    for i, (t, s) in enumerate(zip(inst["mocap"], at["mocap"], strict=True)):
        p = s[:2] + MOCAP_SIGMA_P * rng.standard_normal(2)
        v = s[2:] + MOCAP_SIGMA_V * rng.standard_normal(2)
        vals = [f"{p[0]:.5f}", f"{p[1]:.5f}", f"{v[0]:.5f}", f"{v[1]:.5f}"]
        if i in MOCAP_GAPS:
            vals = ["nan"] * 4
        lines.append(_row(BASE_NS + int(t), vals))
    path.write_text("".join(lines), encoding="utf-8")


def write_truth(path: Path, sim: dict) -> None:
    lines = ["#timestamp [ns], x [m], y [m], vx [m s^-1], vy [m s^-1]\n"]
    for t, s in zip(sim["t_all"], sim["states"], strict=True):
        lines.append(_row(BASE_NS + int(t), [f"{v:.5f}" for v in s]))
    path.write_text("".join(lines), encoding="utf-8")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    sim = simulate()
    write_ros2(args.out / "robot_ros2.mcap", sim)
    write_mocap(args.out / "mocap.csv", sim)
    write_truth(args.out / "truth.csv", sim)
    for name in ("robot_ros2.mcap", "mocap.csv", "truth.csv"):
        print(f"{args.out / name}: {(args.out / name).stat().st_size} bytes")


if __name__ == "__main__":
    main()
