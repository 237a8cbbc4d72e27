"""Each sensor's own Kalman filter on one run, written from eqs. (14)-(18) (a reference for the
fusion rules that read the local filters: tests/test_ici.py, test_registry.py)."""

from __future__ import annotations

import numpy as np

from fusionlog.core.model import System


def local_kfs(sys: System, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each sensor's own Kalman filter on one run z (K+1, m), NaN = missing: means (K+1, S, n)
    and covariances (K+1, S, n, n); update at k = 0, then predict and update (Joseph form)."""
    K1, S, n = len(z), len(sys.sensors), sys.n
    xs, Ps = np.empty((K1, S, n)), np.empty((K1, S, n, n))
    for j, (sen, sl) in enumerate(zip(sys.sensors, sys.sensor_slices, strict=True)):
        x, P = sys.prior.mean.copy(), sys.prior.cov.copy()
        for k in range(K1):
            if k:
                x, P = sys.F @ x, sys.F @ P @ sys.F.T + sys.GQG
            zk = z[k, sl]
            keep = ~np.isnan(zk)
            if keep.any():
                H, R = sen.H[keep], sen.R[np.ix_(keep, keep)]
                G = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
                x = x + G @ (zk[keep] - H @ x)
                A = np.eye(n) - G @ H
                P = A @ P @ A.T + G @ R @ G.T
            xs[k, j], Ps[k, j] = x, P
    return xs, Ps
