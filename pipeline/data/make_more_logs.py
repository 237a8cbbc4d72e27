"""Write the recorded logs of the ROS 1 GPS and the TUM examples (pipeline/replay_gps_ros1.toml,
pipeline/replay_tum.toml): logs in the formats other tools record, made here so that their truth
is known.

Run from the repository root (the files are committed; run it again only to remake them):

    .venv/bin/python pipeline/data/make_more_logs.py            # writes into pipeline/data/
    .venv/bin/python pipeline/data/make_more_logs.py --out DIR  # writes into DIR

Deterministic (fixed seeds and base times; no BLAS/LAPACK kernels, geodetic values rounded to
1e-10 degrees, so the same bytes on every CPU). It needs numpy, rosbags and pymap3d only (not
fusionlog), so the files are what the ROS and TUM tools would write.

What it simulates: a target with a nearly-constant-velocity model (white acceleration of
intensity Q_C per axis), discretised exactly between every two times at which anything samples
it (sensors and truth alike).

- gps_ros1.bag - a ROS 1 bag (rosbags' writer, message definitions of ROS Noetic), 60 s of a
  planar vehicle starting at GPS_BASE_NS:
    /fix   sensor_msgs/NavSatFix at 5 Hz: the east/north position about (LAT0, LON0, ALT0) as
           WGS 84 latitude/longitude/altitude (pymap3d.enu2geodetic), drawn from the covariance
           the message reports: position_covariance diag(s^2, s^2, (2 s)^2) in ENU m^2 with s
           between 1 and 2.5 m varying over the log (COVARIANCE_TYPE_DIAGONAL_KNOWN), except
           FIX_NO_COV messages whose covariance is all zero (COVARIANCE_TYPE_UNKNOWN): drawn
           with s = 2 m, where the replay's R applies. header.stamp = the measurement time (the
           0.2 s grid with 5 ms jitter); record time = stamp + 30 ms.
    /vel   geometry_msgs/TwistStamped at 20 Hz (wheel odometry's velocity): twist.linear.{x,y}
           = velocity + N(0, 0.05^2) (body axes = world axes: the vehicle keeps its heading);
           header.stamp on the 0.05 s grid (offset 10 ms) with 1 ms jitter.
- gps_truth.tsv - the truth at 50 Hz (a grid offset by 2 ms, so no truth sample falls on a
  sensor time; the nearest is at most 10 ms away): tab-separated, header
  `time	east	north	v_east	v_north`, times in seconds with nine decimals, east/north about
  (LAT0, LON0, ALT0) in metres to 0.1 mm.
- tum_slam.txt - TUM format (`timestamp tx ty tz qx qy qz qw`, `#` comment header): a 3-D
  trajectory estimate at 30 Hz, 20 s from TUM_BASE_S, position + N(0, 0.02^2) per axis,
  identity orientation; times with six decimals.
- tum_mocap.txt - TUM format, motion-capture truth of the same target at 100 Hz on a grid of
  its own (times with four decimals, as the TUM RGB-D ground truth): for match = "interpolate".

Sizes: gps_ros1.bag (300 fixes, 1200 velocities); gps_truth.tsv 3000 rows;
tum_slam.txt 600 rows; tum_mocap.txt 2001 rows.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

# The same BLAS-free 2x2 arithmetic as the first example's data (same bytes on every CPU).
sys.path.insert(0, str(Path(__file__).resolve().parent))
from make_replay_data import chol2, mul2  # noqa: E402

Q_C = 0.05  # m^2 s^-3, white-acceleration intensity per axis
LAT0, LON0, ALT0 = 46.5197, 6.5657, 372.0  # degrees, degrees, metres (WGS 84)
GPS_BASE_NS = 1_710_000_000_000_000_000
GPS_SECONDS = 60
FIX_NO_COV = (17, 133, 250)  # /fix messages (0-based) with an all-zero covariance
TUM_BASE_S = 1_305_031_100
TUM_SECONDS = 20


def _cv(dt: float, q: float) -> tuple[np.ndarray, np.ndarray]:
    """F, Q of one axis [p, v] over dt (exact for white acceleration of intensity q)."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    Q = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    return F, Q


def _simulate(rng: np.random.Generator, t_ns: np.ndarray, x0: np.ndarray) -> np.ndarray:
    """States (len(t_ns), axes, 2) at the sorted distinct times t_ns; x0 (axes, 2)."""
    out = np.empty((len(t_ns), *x0.shape))
    x = x0.copy()
    out[0] = x
    for k in range(1, len(t_ns)):
        F, Q = _cv((int(t_ns[k]) - int(t_ns[k - 1])) * 1e-9, Q_C)
        L = chol2(Q)
        for a in range(x.shape[0]):
            x[a] = mul2(F, x[a]) + mul2(L, rng.standard_normal(2))
        out[k] = x
    return out


def _grid(rng, base_ns: int, seconds: float, hz: float, jitter_ns: int, offset_ns: int = 0):
    n = int(round(seconds * hz))
    t = base_ns + offset_ns + np.round(np.arange(n) * 1e9 / hz).astype(np.int64)
    if jitter_ns:
        t = t + rng.integers(-jitter_ns, jitter_ns + 1, n)
    return t


def write_gps(out: Path) -> None:
    import pymap3d
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    rng = np.random.default_rng(20251126)
    fix_t = _grid(rng, GPS_BASE_NS, GPS_SECONDS, 5, 5_000_000)
    odom_t = _grid(rng, GPS_BASE_NS, GPS_SECONDS, 20, 1_000_000, 10_000_000)
    truth_t = _grid(rng, GPS_BASE_NS, GPS_SECONDS, 50, 0, 2_000_000)
    times = np.unique(np.concatenate([fix_t, odom_t, truth_t]))
    x = _simulate(rng, times, np.array([[0.0, 4.0], [0.0, 1.5]]))  # east, north: [p, v]
    at = {k: np.searchsorted(times, t) for k, t in (("fix", fix_t), ("odom", odom_t))}

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]
    Fix, Status = T["sensor_msgs/msg/NavSatFix"], T["sensor_msgs/msg/NavSatStatus"]
    Twist, TwistS = T["geometry_msgs/msg/Twist"], T["geometry_msgs/msg/TwistStamped"]
    Vec = T["geometry_msgs/msg/Vector3"]

    def header(seq: int, t: int, frame: str):
        return Header(
            seq=seq, stamp=Time(sec=int(t) // 10**9, nanosec=int(t) % 10**9), frame_id=frame
        )

    msgs = []  # (record time, topic, message)
    for i, (t, k) in enumerate(zip(fix_t, at["fix"], strict=True)):
        s = 1.0 + 1.5 * (0.5 + 0.5 * math.sin(2 * math.pi * (int(t) - GPS_BASE_NS) * 1e-9 / 40.0))
        unknown = i in FIX_NO_COV
        sd = np.array([2.0, 2.0, 4.0]) if unknown else np.array([s, s, 2 * s])
        e, n, u = np.array([x[k, 0, 0], x[k, 1, 0], 0.0]) + sd * rng.standard_normal(3)
        lat, lon, alt = pymap3d.enu2geodetic(e, n, u, LAT0, LON0, ALT0)
        # to 1e-10 degrees (about 10 µm) and 1e-6 m: the same bytes whatever the CPU's
        # vectorised sin/cos round their last bit to
        lat, lon, alt = round(float(lat), 10), round(float(lon), 10), round(float(alt), 6)
        cov = np.zeros(9) if unknown else np.diag(sd**2).ravel()
        msg = Fix(
            header=header(i, t, "gps"),
            status=Status(status=0, service=1),
            latitude=float(lat),
            longitude=float(lon),
            altitude=float(alt),
            position_covariance=cov,
            position_covariance_type=0 if unknown else 2,
        )
        msgs.append((int(t) + 30_000_000, "/fix", Fix.__msgtype__, msg))
    for i, (t, k) in enumerate(zip(odom_t, at["odom"], strict=True)):
        vx, vy = np.array([x[k, 0, 1], x[k, 1, 1]]) + 0.05 * rng.standard_normal(2)
        msg = TwistS(
            header=header(i, t, "base_link"),
            twist=Twist(
                linear=Vec(x=float(vx), y=float(vy), z=0.0), angular=Vec(x=0.0, y=0.0, z=0.0)
            ),  # fmt: skip
        )
        msgs.append((int(t) + 4_000_000, "/vel", TwistS.__msgtype__, msg))
    msgs.sort(key=lambda m: m[0])
    path = out / "gps_ros1.bag"
    path.unlink(missing_ok=True)
    with Writer(path) as w:
        conns = {
            topic: w.add_connection(topic, mt, typestore=ts)
            for topic, mt in (("/fix", Fix.__msgtype__), ("/vel", TwistS.__msgtype__))
        }
        for rec, topic, mt, msg in msgs:
            w.write(conns[topic], rec, ts.serialize_ros1(msg, mt))

    rows = ["time\teast\tnorth\tv_east\tv_north"]
    for t, k in zip(truth_t, np.searchsorted(times, truth_t), strict=True):
        sec, ns = divmod(int(t), 10**9)
        rows.append(f"{sec}.{ns:09d}\t" + "\t".join(f"{v:.4f}" for v in
                    (x[k, 0, 0], x[k, 1, 0], x[k, 0, 1], x[k, 1, 1])))  # fmt: skip
    (out / "gps_truth.tsv").write_text("\n".join(rows) + "\n")


def write_tum(out: Path) -> None:
    rng = np.random.default_rng(20251127)
    base = TUM_BASE_S * 10**9
    # the times as the files write them (six and four decimals): the state at exactly those
    slam_t = (_grid(rng, base, TUM_SECONDS, 30, 2_000_000, 30_000_000) // 1000) * 1000
    mocap_t = (_grid(rng, base, TUM_SECONDS + 0.01, 100, 0) // 100_000) * 100_000
    times = np.unique(np.concatenate([slam_t, mocap_t]))
    x = _simulate(rng, times, np.array([[1.3, 0.05], [0.6, -0.02], [1.6, 0.0]]))

    def tum(t_ns, decimals: int, pos) -> str:
        sec, ns = divmod(int(t_ns), 10**9)
        frac = f"{ns:09d}"[:decimals]
        return f"{sec}.{frac} " + " ".join(f"{p:.4f}" for p in pos) + " 0.0000 0.0000 0.0000 1.0000"

    head = "# timestamp tx ty tz qx qy qz qw\n"
    lines = ["# trajectory estimate (simulated visual SLAM)\n", head]
    for t, k in zip(slam_t, np.searchsorted(times, slam_t), strict=True):
        lines.append(tum(t, 6, x[k, :, 0] + 0.02 * rng.standard_normal(3)) + "\n")
    (out / "tum_slam.txt").write_text("".join(lines))
    lines = ["# ground truth trajectory (simulated motion capture)\n", head]
    for t, k in zip(mocap_t, np.searchsorted(times, mocap_t), strict=True):
        lines.append(tum(t, 4, x[k, :, 0]) + "\n")
    (out / "tum_mocap.txt").write_text("".join(lines))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    write_gps(args.out)
    write_tum(args.out)


if __name__ == "__main__":
    main()
