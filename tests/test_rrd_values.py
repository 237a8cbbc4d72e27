"""The recording's values against independent computations, not only its structure.

The estimates and the truth are read from the MCAP files with the plain `mcap` reader and
`mcap-protobuf-support`'s DecoderFactory (not fusionlog's reader); the recording with Rerun's
RrdReader. Pinned here (each was once wrong without a structural test noticing):

- the sample runs' ±2σ band is mean ± 2 sqrt(diag P) (not ± 2 P_ii),
- the NEES band is chi2.ppf((1 ± c)/2, n M) / M (scipy.stats, two-sided, n M degrees of
  freedom for the run average),
- the state-plane ellipse {x : (x - x_true)^T P^-1 (x - x_true) = chi2.ppf(c, 2)} uses 2
  degrees of freedom (not 1), checked on the logged polygon's vertices.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from fusionlog.io.rrd import entity_path, read_recording
from fusionlog.scenario import load_scenario
from fusionlog.stages.estimate import run_estimate
from fusionlog.stages.evaluate import run_evaluate
from fusionlog.stages.simulate import run_simulate

PIPELINE = Path(__file__).parents[1] / "pipeline"
RUNS = 300


def read_topic(path: Path, topic: str) -> dict[int, list]:
    """{step: [decoded messages of that step, one per block of runs]} of one topic."""
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out: dict[int, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for _, _, _, msg in reader.iter_decoded_messages(topics=[topic]):
            out.setdefault(msg.step, []).append(msg)
    return out


def estimates(path: Path, topic: str) -> tuple[np.ndarray, np.ndarray]:
    """(mean (M, K+1, n), covariance (M, K+1, n, n)) of every run, from the estimates file."""
    means, covs = [], []
    for _, msgs in sorted(read_topic(path, topic).items()):
        mk, ck = [], []
        for msg in sorted(msgs, key=lambda m: m.run_offset):
            n, runs = msg.dim, msg.runs
            mk.append(np.array(msg.mean).reshape(runs, n))
            c = np.array(msg.covariance)
            ck.append(
                np.broadcast_to(c.reshape(n, n), (runs, n, n))
                if c.size == n * n
                else c.reshape(runs, n, n)
            )
        means.append(np.concatenate(mk))
        covs.append(np.concatenate(ck))
    return np.stack(means, axis=1), np.stack(covs, axis=1)


def truth(path: Path) -> np.ndarray:
    """(M, K+1, n) true states from the sensors file."""
    steps = []
    for _, msgs in sorted(read_topic(path, "/truth").items()):
        steps.append(
            np.concatenate(
                [
                    np.array(m.values).reshape(m.runs, m.dim)
                    for m in sorted(msgs, key=lambda m: m.run_offset)
                ]
            )
        )
    return np.stack(steps, axis=1)


def pipeline(d: Path, scenario_path: Path, runs: int = RUNS) -> Path:
    sc = load_scenario(scenario_path, runs=runs)
    run_simulate(sc, d / "sensors.mcap")
    run_estimate(d / "sensors.mcap", d / "estimates.mcap")
    run_evaluate(d / "sensors.mcap", d / "estimates.mcap", d / "evaluation.rrd")
    return d


@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> Path:
    return pipeline(tmp_path_factory.mktemp("paper"), PIPELINE / "ajgl2009.toml")


def test_sample_run_bands_are_two_standard_deviations(paper) -> None:
    d = paper
    sc = load_scenario(PIPELINE / "ajgl2009.toml")
    ser = read_recording(d / "evaluation.rrd")["series"]
    x = truth(d / "sensors.mcap")
    runs = sorted({int(k.split("/")[1]) for k in ser if k.startswith("runs/")})
    assert runs == list(range(sc.sample_runs))
    for arch in sc.architectures:
        topic = f"/estimates/{arch}"
        mean, cov = estimates(d / "estimates.mcap", topic)
        for m in runs:
            for i, state in enumerate(sc.state_names):
                base = ("runs", m, state, arch)
                mu = mean[m, :, i]
                sd = np.sqrt(cov[m, :, i, i])
                np.testing.assert_allclose(ser[entity_path(*base, "mean")], mu, rtol=1e-12)
                np.testing.assert_allclose(
                    ser[entity_path(*base, "upper")], mu + 2 * sd, rtol=1e-12, atol=1e-12
                )
                np.testing.assert_allclose(
                    ser[entity_path(*base, "lower")], mu - 2 * sd, rtol=1e-12, atol=1e-12
                )
                np.testing.assert_array_equal(
                    ser[entity_path("runs", m, state, "truth")], x[m, :, i]
                )


def test_nees_band_is_the_two_sided_chi_square_quantile_of_the_run_average(paper) -> None:
    rec = read_recording(paper / "evaluation.rrd")
    c, n, M = rec["summary"]["confidence"], len(rec["summary"]["state_names"]), RUNS
    ser = rec["series"]
    lower = stats.chi2.ppf((1 - c) / 2, n * M) / M
    upper = stats.chi2.ppf((1 + c) / 2, n * M) / M
    np.testing.assert_allclose(ser["metrics/nees/bounds/lower"], lower, rtol=1e-12)
    np.testing.assert_allclose(ser["metrics/nees/bounds/upper"], upper, rtol=1e-12)
    assert 1.5 < lower < 2 < upper < 2.5  # sanity: a band around n = 2


def test_nees_series_is_the_run_average_of_the_nees(paper) -> None:
    ser = read_recording(paper / "evaluation.rrd")["series"]
    x = truth(paper / "sensors.mcap")
    mean, cov = estimates(paper / "estimates.mcap", "/estimates/CKF")
    e = x - mean
    nees = np.einsum("mki,mkij,mkj->mk", e, np.linalg.inv(cov), e).mean(axis=0)
    np.testing.assert_allclose(ser["metrics/nees/CKF"], nees, rtol=1e-9)


# ------------------------------------------------------------------------------- state plane
def plane_entities(path: Path, prefix: str) -> dict[str, list]:
    """{entity: rows} of the non-static chunks under `prefix`; a row is the list of instances
    (strips or points) logged at one step."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for ch in RrdReader(str(path)).store().stream().to_chunks():
        ent = str(ch.entity_path)
        if ch.is_static or not ent.startswith(prefix):
            continue
        d = ch.to_record_batch().to_pydict()
        col = "LineStrips2D:strips" if "LineStrips2D:strips" in d else "Points2D:positions"
        if col in d:
            out.setdefault(ent, []).extend(d[col])
    return out


@pytest.fixture(scope="module")
def triangulation(tmp_path_factory) -> Path:
    return pipeline(tmp_path_factory.mktemp("plane"), PIPELINE / "gustafsson_triangulation.toml")


def mahalanobis2(points: np.ndarray, centre: np.ndarray, P: np.ndarray) -> np.ndarray:
    e = points - centre
    return np.einsum("pi,ij,pj->p", e, np.linalg.inv(P), e)


def test_plane_ellipse_scale_has_two_degrees_of_freedom(triangulation) -> None:
    d = triangulation
    sc = load_scenario(PIPELINE / "gustafsson_triangulation.toml")
    want = stats.chi2.ppf(sc.confidence, 2)  # 5.99; with 1 degree of freedom it would be 3.84
    x = truth(d / "sensors.mcap")[0, 0]
    ents = plane_entities(d / "evaluation.rrd", "/plane/ellipses/")
    covs = {f"input {s.name}": s.R for s in sc.system.sensors}  # H = I: the inputs' P is R
    for arch in ("CKF", "MSC", "CI", "AVG"):
        covs[arch] = estimates(d / "estimates.mcap", f"/estimates/{arch}")[1][0, 0]
    for label, P in covs.items():
        (strip,) = ents["/" + entity_path("plane", "ellipses", label)][0]
        pts = np.array(strip, dtype=float)
        assert pts.shape[0] > 50
        np.testing.assert_allclose(pts[0], pts[-1], atol=1e-6)  # closed
        # float32 on the wire: a relative error of ~1e-7 in the coordinates
        np.testing.assert_allclose(mahalanobis2(pts, x, P), want, rtol=1e-5)
        # the label point sits on its ellipse
        (at,) = ents["/" + entity_path("plane", "ellipses", label, "name")][0]
        np.testing.assert_allclose(mahalanobis2(np.array([at]), x, P), want, rtol=1e-5)
    np.testing.assert_allclose(covs["CKF"], 0.018 * np.eye(2), rtol=1e-9)  # the slides' WLS


def test_plane_labels_are_apart(triangulation) -> None:
    """Every ellipse is named, and no two names sit on the same spot (coinciding ellipses:
    CKF, MSC and MSC-GMF; an input and the SKF on it)."""
    ents = plane_entities(triangulation / "evaluation.rrd", "/plane/ellipses/")
    names = {k: np.array(v[0][0]) for k, v in ents.items() if k.endswith("/name")}
    assert len(names) == 9
    spots = np.stack(list(names.values()))
    gaps = np.linalg.norm(spots[:, None] - spots[None], axis=-1)[np.triu_indices(len(spots), 1)]
    assert gaps.min() > 0.05  # the picture is about 1.5 wide
